"""Per-cell integrals by one vector-DG0 assembly, a chunk of cells at a time (§7, §12).

A `CellForm` holds a linear form Σ_i q_i(w[i]) tested with vector DG0: one assembly gives its k
integrals on every owned cell. The estimators (`estimators`) and the energy error
(`energy_error`) take their per-cell values from such forms; global values are sums over the
owned cells reduced over the communicator (`global_sums`).
"""

import numpy as np
import ufl
from mpi4py import MPI

from ..fem.meshes import owned_cells

CHUNK_CELLS = 1 << 17     # cells per assembly of a CellForm (bounds dolfinx's packed coefficients)


class CellForm:
    """A linear form Σ_i q_i(w[i]) tested with vector DG0 (k components), compiled once: one
    assembly gives the k integrals on every owned cell, as an array (owned cells, k) in the
    mesh's cell order.

    dolfinx packs every coefficient of a form on every cell of its integration domain before
    it assembles (an array of (cells, coefficient dofs per cell)): for the estimators' forms
    that is several times the iterate's size, on top of everything a run keeps. A form over
    the whole mesh is therefore assembled a chunk of CHUNK_CELLS owned cells at a time (the
    same integrand restricted to tagged cells: one compiled kernel, `chunks`); the integrals
    are the same, the transient memory is bounded."""

    def __init__(self, mesh, k, build):
        from dolfinx import fem
        self.W = fem.VectorFunctionSpace(mesh, ("DG", 0), dim=k)
        self.k = k
        self.forms = [fem.form(f) for f in chunks(build(ufl.TestFunction(self.W)), mesh)]
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


def global_sums(comm, columns):
    """Σ over the owned cells of every column, summed over the communicator."""
    local = np.asarray(columns, dtype=float).sum(axis=0)
    return comm.allreduce(local, op=MPI.SUM)
