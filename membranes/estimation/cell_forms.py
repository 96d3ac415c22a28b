"""Per-cell integrals by one vector-DG0 assembly, a chunk of cells at a time (§7, §12).

A `CellForm` holds a linear form Σ_i q_i(w[i]) tested with vector DG0: one assembly gives its k
integrals on every owned cell. The estimators (`estimators`) and the energy error
(`energy_error`) take their per-cell values from such forms; global values are sums over the
owned cells reduced over the communicator (`global_sums`).

**Chunks.** dolfinx packs every coefficient of a form on every cell of its integration domain
before it assembles: an array (cells, coefficient dofs per cell) written one coefficient at a
time, then read by the kernel. Over many cells that array outgrows the processor's caches,
and each pass over it goes to memory: the estimators' evaluation form packs 43 doubles a cell,
2.8 MB for 2¹³ cells, which a cache of a few MB holds, but 45 MB for 2¹⁷ (BENCHMARKS.md has
the measured difference). So a form over the whole mesh is assembled CHUNK_CELLS owned cells
at a time (`chunks`): the same integrand restricted to tagged cells, one compiled kernel.
`compiled` makes the dolfinx forms of all the chunks from one JIT lookup (a lookup hashes the
UFL form, which costs more than assembling a small chunk). The chunks also bound the transient
memory of the packing.
"""

import numpy as np
import ufl
from mpi4py import MPI

from ..fem.meshes import owned_cells

CHUNK_CELLS = 1 << 13     # cells per assembly of a chunked form (`chunks`, module notes)


class CellForm:
    """A linear form Σ_i q_i(w[i]) tested with vector DG0 (k components), compiled once: one
    assembly gives the k integrals on every owned cell, as an array (owned cells, k) in the
    mesh's cell order.

    dolfinx packs every coefficient of a form on every cell of its integration domain before
    it assembles (an array of (cells, coefficient dofs per cell)): for the estimators' forms
    that is several times the iterate's size, on top of everything a run keeps. A form over
    the whole mesh is therefore assembled a chunk of CHUNK_CELLS owned cells at a time (the
    same integrand restricted to tagged cells: one compiled kernel, `chunks`, module notes);
    the integrals are the same, the transient memory is bounded."""

    def __init__(self, mesh, k, build):
        from dolfinx import fem
        self.W = fem.VectorFunctionSpace(mesh, ("DG", 0), dim=k)
        self.k = k
        self.forms = compiled(chunks(build(ufl.TestFunction(self.W)), mesh), mesh)
        imap = self.W.dofmap.index_map
        self._size = (imap.size_local + imap.num_ghosts) * k
        self.nc = nc = owned_cells(mesh)
        # the block (one per cell) of each owned cell: DG0 dofs need not follow the cells
        # (None where they do: the integrals are then returned without a copy)
        cells = self.W.dofmap.list.array.reshape(-1)[:nc]
        self._cells = None if np.array_equal(cells, np.arange(nc)) else cells.copy()

    def cells(self):
        """The k integrals on every owned cell, shape (owned cells, k): a view of the form's
        vector where the DG0 dofs follow the cells. The vector is made per call and not kept
        (k doubles per cell: it would stay alive under the Krylov solves between calls)."""
        from dolfinx import fem
        b = np.zeros(self._size)
        for form in self.forms:
            fem.assemble_vector(b, form)
        q = b.reshape(-1, self.k)
        return q[:self.nc] if self._cells is None else q[self._cells]


def chunks(form, mesh, size=None):
    """The UFL `form` restricted to consecutive chunks of about `size` owned cells (as many
    chunks on every process: creating a dolfinx form is collective), or [form] if it has an
    integral that is not over the whole mesh (data measures with tagged cut cells). Their sum
    is `form` on the owned cells. `size`: CHUNK_CELLS.

    A mesh that needs one chunk gets one tagged chunk too, not `form` itself: the tagged
    integral is another UFL signature, hence another compiled kernel, and the JIT warm-up's
    tiny meshes (membranes.app.warmup) must compile the kernel that large meshes use."""
    from dolfinx.mesh import meshtags
    size = CHUNK_CELLS if size is None else size
    if any(itg.subdomain_id() != "everywhere" or itg.subdomain_data() is not None
           for itg in form.integrals()):
        return [form]
    nc = owned_cells(mesh)
    count = mesh.comm.allreduce(max(1, -(-nc // size)), op=MPI.MAX)
    bounds = np.linspace(0, nc, count + 1).astype(np.int64)
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        cells = np.arange(a, b, dtype=np.int32)
        tags = meshtags(mesh, mesh.topology.dim, cells, np.ones(cells.size, dtype=np.int32))
        out.append(ufl.Form([itg.reconstruct(subdomain_id=1, subdomain_data=tags)
                             for itg in form.integrals()]))
    return out


def compiled(parts, mesh):
    """The dolfinx forms of the UFL forms `parts`, which differ only in their cells' tags (the
    chunks of one form, `chunks`): one JIT lookup for the first, whose compiled form, spaces,
    coefficients and constants the others share (what `dolfinx.fem.form` does for each form,
    less the lookup: the chunks have one UFL signature). Collective, as `dolfinx.fem.form`."""
    from dolfinx import cpp, fem, jit
    from petsc4py import PETSc
    first = parts[0]
    if (len(parts) == 1 or PETSc.ScalarType != np.float64
            or any(itg.integral_type() != "cell" for itg in first.integrals())):
        return [fem.form(part) for part in parts]
    ufcx_form, module, code = jit.ffcx_jit(mesh.comm, first,
                                           form_compiler_params={"scalar_type": "double"})
    spaces = [arg.ufl_function_space()._cpp_object for arg in first.arguments()]
    coefficients = first.coefficients()
    coefficients = [coefficients[ufcx_form.original_coefficient_position[i]]._cpp_object
                    for i in range(ufcx_form.num_coefficients)]
    constants = [c._cpp_object for c in first.constants()]
    domain = first.ufl_domain().ufl_cargo()
    form_class = type("Form", (fem.forms.FormMetaClass, cpp.fem.Form_float64), {})
    kinds = (cpp.fem.IntegralType.exterior_facet, cpp.fem.IntegralType.interior_facet,
             cpp.fem.IntegralType.vertex)
    out = []
    for part in parts:
        tags = part.integrals()[0].subdomain_data()
        subdomains = {cpp.fem.IntegralType.cell: tags, **{kind: None for kind in kinds}}
        out.append(form_class(ufcx_form, spaces, coefficients, constants, subdomains,
                              domain, module.ffi, code))
    return out


def global_sums(comm, columns):
    """Σ over the owned cells of every column, summed over the communicator."""
    local = np.asarray(columns, dtype=float).sum(axis=0)
    return comm.allreduce(local, op=MPI.SUM)
