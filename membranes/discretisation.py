"""Conforming P1 discretisation with lumped contact (DESIGN §2).

`discretise(problem)` assembles, once per mesh, everything the Newton driver needs:

    S_α = μ_α (∇ψ_b, ∇ψ_a)      membrane stiffness matrices (forms.membrane.membrane_bilinear)
    D_a = (ψ_a, 1)              lumped contact weights       (forms.membrane.contact_weight)
    F_α,a = (f_α, ψ_a)          loads                        (forms.membrane.membrane_linear)

and the boundary vertices (Dirichlet: u1 = g, u2 = 0, λ = 0). The loads are integrated with a
degree-6 Gauss rule, and on cells cut by the scene's interface (where the data jump, e.g. the
circle r = 1/√2 of the disk scene, DESIGN §9) with a composite rule: the reference triangle split
into 16² sub-triangles, each with a degree-4 Gauss rule. The same measure integrates the exact
energy error.

**Forms.** `form(ufl_form)` is this package's dolfinx.fem.form: the kernel of a UFL form is
compiled (or found in the JIT cache) once per process, and every later form of the same
structure, on any mesh, gets a dolfinx Form of that kernel at the cost of a cheap signature
(`form_signature`). dolfinx 0.5.2's fem.form computes UFL's signature on every call, which
turns every number of a custom quadrature rule into a string: a load on the data measures
took 9 ms in fem.form, 0.8 ms in `form` (disk, T_0). Other modules' forms may use it too.

Serial: the matrices are handed to the driver as scipy CSR (owned rows = all rows). S, D and the
boundary vertices then come from compiled passes (`p1_assembly`: the cells of each vertex, their
neighbours, then the cells), bit for bit what dolfinx assembles from the forms above: 0.27 s where
dolfinx took 0.85 s at 9.3e5 vertices. On several processes (ghosts, global numbers), and for the
loads, dolfinx assembles.
"""

import contextlib
import functools
import hashlib
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import ufl

from forms.membrane import (contact_weight, energy_error_expansion, energy_norm_squared,
                            membrane_bilinear, membrane_linear)

from .compiled import kernel
from .meshes import cells_by_vertex, holding_cells, p1_cells
from .problem import as_builder

DATA_DEGREE = 6          # Gauss degree for data on cells the interface does not cut
CUT_SUBDIVISIONS = 16    # composite rule on cut cells: 16² sub-triangles …
CUT_DEGREE = 4           # … each with a degree-4 Gauss rule


def _metadata_key(metadata):
    """An integral's metadata as a short hashable value: a list of numbers (a custom rule's
    points or weights) as its shape and the SHA-1 of its float64 bytes, anything else as its
    repr (distinct metadata, distinct keys)."""
    items = []
    for name in sorted(metadata):
        value = metadata[name]
        if isinstance(value, (list, tuple, np.ndarray)):
            try:
                a = np.ascontiguousarray(value, dtype=np.float64)
                value = (a.shape, hashlib.sha1(a.tobytes()).hexdigest())
            except (TypeError, ValueError):
                pass
        items.append((name, repr(value)))
    return tuple(items)


def form_signature(ufl_form):
    """UFL's signature of a form (ufl.algorithms.signature.compute_form_signature: the
    integrands with coefficients, constants and domains renumbered, the integral types,
    subdomain ids and metadata) with the metadata hashed by `_metadata_key`: two forms with
    the same signature have the same kernel, whatever their mesh, coefficients and constants."""
    from ufl.algorithms.signature import compute_expression_hashdata, compute_terminal_hashdata
    renumbering = ufl_form._compute_renumbering()
    integrals = ufl_form.integrals()
    terminals = compute_terminal_hashdata([i.integrand() for i in integrals], renumbering)
    data = [(compute_expression_hashdata(i.integrand(), terminals),
             i.ufl_domain()._ufl_signature_data_(renumbering), i.integral_type(),
             i.subdomain_id(), _metadata_key(i.metadata())) for i in integrals]
    return hashlib.sha512(str(data).encode("utf-8")).hexdigest()


_KERNELS = {}     # form_signature -> (ufcx form, its cffi module, its code)


def _kernel(ufl_form, comm):
    """(ufcx form, cffi module, code) of a UFL form: the entry of `_KERNELS` under its
    `form_signature`, compiled by dolfinx.jit.ffcx_jit the first time. The signature is taken
    before the compilation: when ffcx compiles a form (not when it finds it in its disk cache)
    it gives the coordinate element of a mesh made with a plain ufl element the variant
    'equispaced', and the same form's signature afterwards is another."""
    from dolfinx import jit
    key = form_signature(ufl_form)
    if key not in _KERNELS:
        _KERNELS[key] = jit.ffcx_jit(comm, ufl_form, form_compiler_params={"scalar_type": "double"})
    return _KERNELS[key]


@functools.lru_cache(maxsize=None)
def _form_class():
    from dolfinx import cpp
    from dolfinx.fem.forms import FormMetaClass
    return type("Form", (FormMetaClass, cpp.fem.Form_float64), {})


def form(ufl_form):
    """The dolfinx Form (float64) of a UFL form: dolfinx.fem.form, with the kernel looked up
    by `form_signature` among those this process has compiled (dolfinx.jit.ffcx_jit, the
    first time) and the C++ form built from it as dolfinx.fem.forms.form builds it: the
    argument spaces, the coefficients in the kernel's order, the constants, the subdomain
    tags and the mesh of this form. For every form of the package that is assembled on more
    than one mesh (nested iteration builds each on every level)."""
    from dolfinx import cpp
    domain_data, = ufl_form.subdomain_data().items()
    domain, subdomains = domain_data
    mesh = domain.ufl_cargo()
    if mesh is None:
        raise RuntimeError("expecting a mesh in the form")
    ufcx_form, module, code = _kernel(ufl_form, mesh.comm)
    spaces = [arg.ufl_function_space()._cpp_object for arg in ufl_form.arguments()]
    original = ufl_form.coefficients()
    coefficients = [original[ufcx_form.original_coefficient_position[i]]._cpp_object
                    for i in range(ufcx_form.num_coefficients)]
    constants = [c._cpp_object for c in ufl_form.constants()]
    kinds = cpp.fem.IntegralType
    tags = {kinds.cell: subdomains.get("cell"),
            kinds.exterior_facet: subdomains.get("exterior_facet"),
            kinds.interior_facet: subdomains.get("interior_facet"),
            kinds.vertex: subdomains.get("vertex")}
    return _form_class()(ufcx_form, spaces, coefficients, constants, tags, mesh, module.ffi,
                         code)


@functools.lru_cache(maxsize=None)
def composite_rule(n=CUT_SUBDIVISIONS, degree=CUT_DEGREE):
    """Points and weights of a composite Gauss rule on the reference triangle (n² pieces),
    computed once per process (read-only arrays)."""
    import basix
    p, w = basix.make_quadrature(basix.CellType.triangle, degree)
    pts, wts = [], []
    for i in range(n):
        for j in range(n - i):
            tris = [((i, j), (i + 1, j), (i, j + 1))]
            if i + j < n - 1:
                tris.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
            for a, b, c in tris:
                a, b, c = (np.array(v, dtype=float) / n for v in (a, b, c))
                pts.append(a + np.outer(p[:, 0], b - a) + np.outer(p[:, 1], c - a))
                wts.append(w / n**2)
    pts, wts = np.vstack(pts), np.concatenate(wts)
    pts.flags.writeable = wts.flags.writeable = False     # one copy per process (cached)
    return pts, wts


def cut_cells(mesh, interface, samples=4, chunk=16384):
    """Local cells on which the level set `interface` changes sign (sampled on a grid: the
    points (v0 + s (v1 - v0)) + t (v2 - v0), s, t ∈ {0, 1/samples, …}, s + t ≤ 1), `chunk`
    cells at a time (their samples stay in cache)."""
    x = mesh.geometry.x[:, :2].T.copy()                          # (2, vertices)
    ncells = mesh.topology.index_map(2).size_local
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells]
    cut = np.zeros(ncells, dtype=bool)
    for start in range(0, ncells, chunk):
        c = cells[start:start + chunk]
        v0 = x[:, c[:, 0]]
        e1, e2 = x[:, c[:, 1]] - v0, x[:, c[:, 2]] - v0
        lo = np.full(len(c), np.inf)
        hi = np.full(len(c), -np.inf)
        row, q = np.empty_like(v0), np.empty_like(v0)
        for i in range(samples + 1):
            np.add(v0, np.multiply(i / samples, e1, out=row), out=row)
            for j in range(samples + 1 - i):
                phi = interface(np.add(row, np.multiply(j / samples, e2, out=q), out=q))
                np.minimum(lo, phi, out=lo)
                np.maximum(hi, phi, out=hi)
        cut[start:start + chunk] = (lo < 0) & (hi > 0)
    return np.flatnonzero(cut).astype(np.int32)


@functools.lru_cache(maxsize=None)
def _composite_metadata():
    """The form metadata of the composite rule on cut cells (one dict per process)."""
    pts, wts = composite_rule()
    return {"quadrature_rule": "custom", "quadrature_degree": DATA_DEGREE,
            "quadrature_points": pts.tolist(), "quadrature_weights": wts.tolist()}


def data_measures(mesh, interface=None):
    """Measures for data integrals, to be summed: Gauss degree 6, composite rule on cut cells."""
    smooth = {"quadrature_degree": DATA_DEGREE}
    if interface is None:
        return [ufl.dx(domain=mesh, metadata=smooth)]
    from dolfinx import mesh as dmesh
    ncells = mesh.topology.index_map(2).size_local
    marker = np.zeros(ncells, dtype=np.int32)
    marker[cut_cells(mesh, interface)] = 1
    tags = dmesh.meshtags(mesh, 2, np.arange(ncells, dtype=np.int32), marker)
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)
    return [dx(0, metadata=smooth), dx(1, metadata=_composite_metadata())]


def over(measures, form_of):
    """Σ form_of(dx) over the data measures: one integral per quadrature rule."""
    forms = [form_of(dx) for dx in measures]
    total = forms[0]
    for f in forms[1:]:
        total = total + f
    return total


def load(data, mesh):
    """The UFL expression of a load f (a scene's builder or a Formula) on `mesh`; constant data
    as a dolfinx Constant: UFL would fold 0 * v * dx into an empty form, and a Constant keeps
    one compiled kernel for every value."""
    from dolfinx import fem
    expr = ufl.as_ufl(as_builder(data)(ufl.SpatialCoordinate(mesh)))
    if isinstance(expr, (ufl.constantvalue.Zero, ufl.constantvalue.ScalarValue)):
        return fem.Constant(mesh, float(expr))
    return expr


def assemble_matrix_csr(a):
    """Assemble a bilinear form (UFL, or a dolfinx Form) without boundary conditions into
    scipy CSR: the owned rows, global column numbers. Scalar spaces go through dolfinx's own
    CSR matrix, blocked spaces (which it does not take in dolfinx 0.5.2) through PETSc's:
    the same entries, PETSc's matrix costs a second sparsity pass (twice the time)."""
    from dolfinx import fem, la
    a = form(a) if isinstance(a, ufl.Form) else a
    if any(V.dofmap.index_map_bs != 1 for V in a.function_spaces):
        from dolfinx.fem.petsc import assemble_matrix
        A = assemble_matrix(a)
        A.assemble()
        indptr, indices, data = A.getValuesCSR()
        out = sp.csr_matrix((data, indices, indptr), shape=A.getSize())
        A.destroy()
    else:
        pattern = fem.create_sparsity_pattern(a)
        pattern.assemble()
        A = la.matrix_csr(pattern)
        fem.assemble_matrix(A, a)
        A.finalize()
        rows, cols = (V.dofmap.index_map for V in a.function_spaces)
        m = rows.size_local
        indptr = np.array(A.indptr[:m + 1])
        indices = np.array(A.indices[:indptr[-1]])
        if cols.num_ghosts or cols.size_global != cols.size_local:   # else: local = global
            indices = cols.local_to_global(indices)
        out = sp.csr_matrix((np.array(A.data[:indptr[-1]]), indices, indptr),
                            shape=(m, cols.size_global))
        del A, pattern
    release_memory()
    return out


def p1_assembly(V):
    """(S, D, boundary) of a serial P1 space V: S = (∇ψ_b, ∇ψ_a) (scipy CSR), D = (ψ_a, 1) (DESIGN
    §2) and `boundary_dofs`, in compiled passes: the neighbours of every vertex
    (`vertex_neighbours`: its cells, meshes.cells_by_vertex, then their vertices), which give S's
    sparsity and the boundary, then one over the cells (`_p1_entries`), bit for bit dolfinx's
    assembly of forms.membrane.membrane_bilinear(1, u, v) and contact_weight(v)
    (assemble_matrix_csr, assemble_vector_array): the same sparsity (every pair of vertices of a
    cell, columns sorted, zeros stored), FFCx's arithmetic of the P1 kernels (one Gauss point of
    weight 1/2; the Jacobian summed from the reference gradients (-1, 1, 0), (-1, 0, 1) as FFCx's
    code sums them, then its inverse, |det J| and the products in FFCx's order) and the cell
    contributions summed in the cells' order, as dolfinx adds them. The values of ψ_a at the Gauss
    point are those of the form's own compiled kernel (`reference_element_vector`): basix's
    tabulation gives 1 - 1/3 - 1/3 as 0.3333333333333334 or 0.3333333333333333 depending on how the
    mesh's coordinate element was made. At 9.3e5 vertices dolfinx took 0.56 s for S (sparsity
    pattern, its assembly and the kernel's) and 0.13 s for D, the boundary count 0.16 s; the
    compiled passes take 0.27 s for all three (least of 4, 2026-11-22)."""
    mesh = V.mesh
    centroid_values = 2.0 * reference_element_vector(contact_weight(ufl.TestFunction(V)))
    n = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
    ncells = mesh.topology.index_map(2).size_local
    geometry = mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells]
    cells = p1_cells(V)
    boundary, indptr, indices = vertex_neighbours(cells, n, True)
    data, D = _p1_entries(mesh.geometry.x, geometry, cells, indptr, indices, centroid_values)
    S = sp.csr_matrix((data, indices, indptr), shape=(n, n))
    S.has_sorted_indices = True
    return S, D, np.flatnonzero(boundary).astype(np.int32)


def reference_element_vector(ufl_form):
    """The element vector of a linear cell form (one cell integral) on the reference triangle
    (0, 0), (1, 0), (0, 1), computed by its compiled kernel (`form`'s)."""
    ufcx_form, module, _ = _kernel(ufl_form, ufl_form.ufl_domain().ufl_cargo().comm)
    integral, = (ufcx_form.integrals(module.lib.cell)[i]
                 for i in range(ufcx_form.num_integrals(module.lib.cell)))
    ffi = module.ffi
    values = np.zeros(3)
    corners = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    integral.tabulate_tensor_float64(ffi.cast("double *", values.ctypes.data), ffi.NULL,
                                     ffi.NULL, ffi.cast("double *", corners.ctypes.data),
                                     ffi.NULL, ffi.NULL)
    return values


@kernel
def _p1_entries(x, geometry, cells, indptr, indices, centroid_values):
    """The CSR data of the P1 stiffness matrix on the pattern (indptr, indices) of
    `_vertex_neighbours` and the vector of (ψ_a, 1), for the `cells` (their dofs, (c, 3)) with
    vertex coordinates x[geometry] (`p1_assembly`): every cell's element matrix and vector
    added in, in the cells' order; `centroid_values`: ψ_0, ψ_1, ψ_2 at the Gauss point, as
    the kernel of D has them."""
    n = indptr.size - 1
    data = np.zeros(indptr[n])
    weights = np.zeros(n)
    d10 = np.array([-1.0, 1.0, 0.0])           # FFCx's reference gradients of ψ_0, ψ_1, ψ_2
    d01 = np.array([-1.0, 0.0, 1.0])
    t0, t1 = np.empty(3), np.empty(3)
    for c in range(cells.shape[0]):
        j0, j1, j2, j3 = 0.0, 0.0, 0.0, 0.0
        for k in range(3):
            g = geometry[c, k]
            j0 += x[g, 0] * d10[k]
            j3 += x[g, 1] * d01[k]
            j1 += x[g, 0] * d01[k]
            j2 += x[g, 1] * d10[k]
        det = j0 * j3 + -1.0 * (j1 * j2)
        k00, k01 = j0 / det, (-1.0 * j1) / det
        k10, k11 = j3 / det, (-1.0 * j2) / det
        size = abs(det)
        fw0 = ((k10 * k10) + (k01 * k01)) * size * 0.5
        fw1 = ((k00 * k01) + (k10 * k11)) * size * 0.5
        fw2 = ((k00 * k00) + (k11 * k11)) * size * 0.5
        for i in range(3):
            t0[i] = fw0 * d10[i] + fw1 * d01[i]
            t1[i] = fw1 * d10[i] + fw2 * d01[i]
        w = size * 0.5
        for i in range(3):
            a = cells[c, i]
            weights[a] += w * centroid_values[i]
            for j in range(3):
                b = cells[c, j]
                q = indptr[a]
                while indices[q] != b:
                    q += 1
                data[q] += d10[j] * t0[i] + d01[j] * t1[i]
    return data, weights


def release_memory():
    """Hand freed heap memory back to the system (glibc malloc_trim), so that the transient
    PETSc and sparsity-pattern buffers of one assembly do not add to the next phase's peak."""
    import ctypes
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


@contextlib.contextmanager
def plain_pages():
    """Large numpy arrays on ordinary pages inside the block. NumPy (1.20 and later, on Linux)
    advises the kernel to back every array of 4 MiB or more with transparent huge pages
    (madvise MADV_HUGEPAGE); where the kernel's THP defragmentation is "madvise", each fault on
    such an array may compact memory first. Measured on the machine of BENCHMARKS.md (THP
    enabled and defrag "madvise", a virtual machine): writing 1.5 GiB of fresh memory took
    3.2 s with the advice and 0.64 s without; the J = 6 disk run of bench_scaling.py (peak
    3.8 GiB) took 18.6-19.5 s without it (5 runs; a sixth, 25 s, slow in every phase, left
    out) against 19.4-20.1 s with it (5 runs). `membranes.solve` and
    report.run_peer (the PETSc peer) run inside this block (`as_one_run`);
    NUMPY_MADVISE_HUGEPAGE=0 does the same for a whole process. Restores numpy's setting on exit."""
    try:
        from numpy.core import multiarray
        before = multiarray._set_madvise_hugepage(False)
    except (ImportError, AttributeError):     # another numpy: its own default
        yield
        return
    try:
        yield
    finally:
        multiarray._set_madvise_hugepage(before)


def as_one_run(function):
    """`function` (a whole run: `membranes.solve`, report.run_peer) run on plain pages
    (`plain_pages`) with BLAS on one thread (parallel.one_blas_thread), its name, notes and
    signature kept. One BLAS thread makes a run's numbers independent of the machine's cores:
    PETSc's dot products and norms (GMRES, CG) and numpy's go to OpenBLAS, which splits long
    vectors among its threads and so sums in another order. Measured: the J = 3 disk run of
    bench_scaling.py (6.9e3 vertices) gave iterates 5.8e-14 apart (relative) on one process
    with OpenBLAS's two threads and with one, and so differed from the same run on two
    processes (each bound to one core), which it now equals bit for bit. The threads saved
    no time: the J = 6 run (9.3e5 vertices, one process) took 19.0 and 17.7 s with two
    OpenBLAS threads and 19.2, 18.0 and 18.7 s with one (alternating runs), GMRES on T_6
    1.73, 1.28, 1.11 and 1.58, 1.16, 1.28 s per Newton step against 1.70, 1.39, 1.32 /
    1.64, 1.21, 1.12 / 1.68, 1.18, 1.17 s; the idle threads' spinning took 6-8 s of system
    time on the other core."""
    from .parallel import one_blas_thread

    @functools.wraps(function)
    def run(*args, **kwargs):
        with plain_pages(), one_blas_thread():
            return function(*args, **kwargs)
    return run


def assemble_vector_array(L):
    """Assemble a linear form (UFL, or a dolfinx Form) into a numpy array of the owned
    entries (ghost contributions added to their owners)."""
    from dolfinx import fem, la
    L = form(L) if isinstance(L, ufl.Form) else L
    b = fem.assemble_vector(L)
    b.scatter_reverse(la.ScatterMode.add)
    V = L.function_spaces[0]
    return b.array[:V.dofmap.index_map.size_local * V.dofmap.index_map_bs].copy()


@dataclass
class Discretisation:
    problem: object
    V: object                 # P1 space on the computational mesh
    S1: sp.csr_matrix         # μ1 S
    S2: sp.csr_matrix         # μ2 S
    D: np.ndarray             # (ψ_a, 1)
    F1: np.ndarray            # (f1, ψ_a)
    F2: np.ndarray            # (f2, ψ_a)
    boundary: np.ndarray      # indices of boundary vertices (dofs)
    dx_data: list             # data measures (data_measures), integrals summed with over()

    @property
    def n(self):
        return self.D.size

    @property
    def interior(self):
        mask = np.ones(self.n, dtype=bool)
        mask[self.boundary] = False
        return mask

    def data_scales(self):
        """(u_data, λ_data): the sizes the data give a displacement and a pressure (DESIGN
        §11, tolerances relative to the data): λ_data = max_a,α |F_α,a| / D_a over interior
        vertices (a nodal load density), u_data = max(g, (C_PF h_Ω)² max_a,α |F_α,a| /
        (μ_α D_a)), the displacement those loads can make on their own."""
        p, inner = self.problem, self.interior
        F1, F2 = (np.abs(F)[inner] / self.D[inner] for F in (self.F1, self.F2))
        lam_data = max(F1.max(initial=0.0), F2.max(initial=0.0))
        u_data = max(p.g, p.poincare_constant() ** 2 * max(F1.max(initial=0.0) / p.mu1,
                                                           F2.max(initial=0.0) / p.mu2))
        return u_data, lam_data

    def functions(self, X):
        """P1 functions u1, u2, lambda from X = (X1, X2, X3) ∈ R^{3N}."""
        from dolfinx import fem
        out = []
        for k, name in enumerate(("u1", "u2", "lambda")):
            f = fem.Function(self.V, name=name)
            f.x.array[:self.n] = X[k * self.n:(k + 1) * self.n]
            f.x.scatter_forward()
            out.append(f)
        return out


def boundary_dofs(V):
    """The dofs of the P1 space V on the boundary of its mesh (Dirichlet vertices), increasing:
    the two vertices of every edge that lies in one cell only, counted over the cells of each
    vertex by compiled passes (`vertex_neighbours`), which need no mesh entities. dolfinx's exterior
    facets (locate_dofs_topological on exterior_facet_indices, still taken on a mesh shared by
    several processes, where an edge of a ghost cell may lie in one local cell) need the mesh's
    edges and their cells: 0.65 s at 9.3e5 vertices, the count 0.03 s (the flux equilibration,
    equilibration.PatchSpace, creates them where it sets up, as it reads dolfinx's exterior
    facets)."""
    from dolfinx import fem, mesh as dmesh
    mesh = V.mesh
    if mesh.comm.size > 1:
        mesh.topology.create_connectivity(1, 2)
        return fem.locate_dofs_topological(V, 1, dmesh.exterior_facet_indices(mesh.topology))
    cells = p1_cells(V)
    n = V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts
    return np.flatnonzero(vertex_neighbours(cells, n, False)[0]).astype(np.int32)


def vertex_neighbours(cells, n, columns):
    """(boundary, indptr, indices) of `_vertex_neighbours` for the n vertices of the `cells`
    (c, 3), from their cells grouped by vertex (`meshes.cells_by_vertex`)."""
    start, order = cells_by_vertex(cells, np.bincount(cells.reshape(-1), minlength=n))
    return _vertex_neighbours(cells, order // 3, start, columns)


@kernel
def _vertex_neighbours(cells, holding, start, columns):
    """(boundary, indptr, indices) for the n vertices of the `cells` (c, 3), vertex a in the
    cells holding[start[a]:start[a + 1]] (`meshes.cells_by_vertex`, positions // 3):
    a mask of those of an edge that only one cell has, and (with `columns`; else an empty
    `indices`) the CSR pattern of the P1 matrices, row a the vertices of a's cells, sorted
    (by insertion: a row has a handful). For each a the number of its cells that hold each
    neighbour b: the edge ab lies in one cell if that number is 1; the neighbours with a
    nonzero count are row a's columns."""
    n = start.size - 1
    count = np.zeros(n, dtype=np.int64)
    boundary = np.zeros(n, dtype=np.bool_)
    indptr = np.zeros(n + 1, dtype=np.int32)
    for a in range(n):
        m = 0
        for p in range(start[a], start[a + 1]):
            for k in range(3):
                b = cells[holding[p], k]
                if count[b] == 0:
                    m += 1
                count[b] += 1
        for p in range(start[a], start[a + 1]):
            for k in range(3):
                b = cells[holding[p], k]
                if b != a and count[b] == 1:
                    boundary[a] = True
                    boundary[b] = True
        for p in range(start[a], start[a + 1]):
            for k in range(3):
                count[cells[holding[p], k]] = 0
        indptr[a + 1] = indptr[a] + m
    indices = np.empty(indptr[n] if columns else 0, dtype=np.int32)
    if not columns:
        return boundary, indptr, indices
    for a in range(n):
        m = indptr[a]
        for p in range(start[a], start[a + 1]):
            for k in range(3):
                b = cells[holding[p], k]
                if count[b] == 0:
                    count[b] = 1
                    q = m                       # insertion into the sorted columns of row a
                    while q > indptr[a] and indices[q - 1] > b:
                        indices[q] = indices[q - 1]
                        q -= 1
                    indices[q] = b
                    m += 1
        for p in range(start[a], start[a + 1]):
            for k in range(3):
                count[cells[holding[p], k]] = 0
    return boundary, indptr, indices


def discretise(problem, stiffness=True, given=None):
    """Assemble S1, S2, D, F1, F2 and the boundary vertices of `problem` (DESIGN §2). The
    stiffness matrix S is assembled once and scaled: S_α = μ_α S, on S's own index arrays (S
    itself where μ_α = 1, S1 = S2 where μ1 = μ2: the same numbers, and no copies: two took
    0.33 s at 9.3e5 vertices; nothing changes the matrices in place). stiffness=False: no S
    (S1 = S2 = None), for the estimator processes of a run on several processes
    (membranes.pipeline), whose estimators read the loads, the space and the boundary;
    `given`: see `discretise_in_parts`."""
    return completed(discretise_in_parts(problem, stiffness, given))


SHIPMENT = "shipment"   # what `discretise_in_parts` yields while it waits for `given`'s arrays


def discretise_in_parts(problem, stiffness=True, given=None):
    """`discretise` as a generator that yields between its parts (S, D and the boundary; the
    data measures and loads; F1; F2: each 0.1-0.4 s at 9.3e5 vertices) and returns the
    Discretisation: in a run on several processes, process 0 discretises the finer levels of
    a nested run a part at a time while it waits for estimates (membranes.driver, `_Ahead`),
    and the estimator processes the level they serve next (membranes.pipeline).
    `given` (without stiffness): a call that returns (D, F1, F2, boundary) where another
    process made them already, else None. The estimator processes take them from process 0,
    which makes them anyway (the same code on the same mesh: the same numbers), and wait for
    them rather than make them again: after the space and the data measures the parts yield
    SHIPMENT while `given` has none (membranes.pipeline then runs no part of this level until
    they come), and resumed without them (a level process 0 does not ship, e.g. T_0) they make
    all four. Before, they made whichever had not come when their part began: in five of
    seven timelines (J = 6, 2 processes) the estimator process made D, F1 and F2 of the finest
    level itself (parts of 0.18-0.28 s at 9.3e5 vertices), some while level 5's iterates
    waited for their estimates. Waiting instead, the run took 10.25-10.83 s against
    10.70-11.27 s (seven alternating rounds, medians 10.41 and 11.04 s)."""
    from dolfinx import fem
    mesh = problem.mesh
    V = fem.FunctionSpace(mesh, ("Lagrange", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    arrays = dxd = None
    if given is not None and not stiffness:
        yield
        dxd = data_measures(mesh, problem.interface)
        arrays = given()
        if arrays is None:
            yield SHIPMENT
            arrays = given()
    if arrays is not None:
        S, (D, F1, F2, boundary) = None, arrays
    else:
        if mesh.comm.size == 1 and stiffness:
            S, D, boundary = p1_assembly(V)
        else:
            S = assemble_matrix_csr(membrane_bilinear(1.0, u, v)) if stiffness else None
            D = assemble_vector_array(contact_weight(v))
            boundary = boundary_dofs(V)
        yield
        if dxd is None:
            dxd = data_measures(mesh, problem.interface)
        f1, f2 = (load(f, mesh) for f in (problem.f1, problem.f2))
        yield
        F1 = assemble_vector_array(over(dxd, lambda dx: membrane_linear(f1, v, dx)))
        yield
        F2 = assemble_vector_array(over(dxd, lambda dx: membrane_linear(f2, v, dx)))
    n = V.dofmap.index_map.size_local
    S1 = S2 = None
    if S is not None:
        S1 = scaled(S, problem.mu1)
        S2 = S1 if problem.mu2 == problem.mu1 else scaled(S, problem.mu2)
    return Discretisation(problem, V, S1, S2, D[:n], F1[:n], F2[:n],
                          np.asarray(boundary[boundary < n], dtype=np.int32), dxd)


def completed(parts):
    """What the generator `parts` returns, all its parts run."""
    while True:
        try:
            next(parts)
        except StopIteration as done:
            return done.value


def scaled(S, mu):
    """μ S (CSR) on S's index arrays: S itself for μ = 1 (the same numbers)."""
    if mu == 1.0:
        return S
    return sp.csr_matrix((mu * S.data, S.indices, S.indptr), shape=S.shape, copy=False)


def _interpolant(V, u):
    """The P1 interpolant of the UFL expression u: its values at the vertices, each evaluated
    on one cell that has it (the same value on every such cell; half the cells, half the
    time of interpolating on all of them)."""
    from dolfinx import fem
    f = fem.Function(V)
    if u.ufl_domain() is None:                                  # a constant
        f.x.array[:] = float(u)
        return f
    cells = p1_cells(V)
    chosen = np.zeros(len(cells), dtype=bool)
    chosen[holding_cells(cells, len(f.x.array))] = True
    f.interpolate(fem.Expression(u, V.element.interpolation_points()),
                  np.flatnonzero(chosen).astype(np.int32))
    return f


class EnergyError:
    """|||u - u_h||| against the scene's exact solution (DESIGN §1), in total and per cell.

    Integrated with the data measures (the exact gradients are piecewise smooth across the
    scene's interface), on the computational polygon. The total costs no quadrature per
    evaluation: with I_h u the P1 interpolant of the exact solution, e = u - I_h u and
    d = u_h - I_h u (P1),

        |||u - u_h|||² = |||e - d|||² = Σ_a c_a - 2 (b1·d1 + b2·d2) + d1ᵀ S1 d1 + d2ᵀ S2 d2

    (forms.membrane.energy_error_expansion: b_α,a = μ_α (∇e_α, ∇ψ_a), Σ_a c_a = |||e|||²,
    with the data measures' rules, which are linear in the integrand and exact for the
    constant |∇d|² of a cell, so that the identity holds for the integrals as computed). The
    set-up interpolates u and assembles b1, b2, c once (one vector, one pass of quadrature);
    an evaluation is two products with the stiffness matrices. Expanded about I_h u, not
    about 0, the terms are of the size of the error, not of |||u|||, and so is their
    round-off. Serial, as the Discretisation. `per_cell` integrates |∇(u - u_h)|² cell by
    cell directly (DG0 test functions): a check of the expansion, and the actual error
    distribution.
    """

    def __init__(self, disc):
        from dolfinx import fem
        problem, V = disc.problem, disc.V
        mesh = V.mesh
        x = ufl.SpatialCoordinate(mesh)
        self.disc = disc
        self.exact = [ufl.as_ufl(problem.exact.u1(x)), ufl.as_ufl(problem.exact.u2(x))]
        self.mu = [fem.Constant(mesh, problem.mu1), fem.Constant(mesh, problem.mu2)]
        interpolant = [_interpolant(V, u) for u in self.exact]
        e1, e2 = (u - f for u, f in zip(self.exact, interpolant))
        W = fem.VectorFunctionSpace(mesh, ("Lagrange", 1), dim=3)
        w = ufl.TestFunction(W)
        terms = assemble_vector_array(over(disc.dx_data, lambda dx: energy_error_expansion(
            *self.mu, e1, e2, w, dx))).reshape(-1, 3)
        # W's vertex numbering may differ from V's: match them cell by cell
        ncells = mesh.topology.index_map(2).size_local
        to_w = np.empty(V.dofmap.index_map.size_local + V.dofmap.index_map.num_ghosts,
                        dtype=np.int64)
        to_w[V.dofmap.list.array[:3 * ncells]] = W.dofmap.list.array[:3 * ncells]
        terms = terms[to_w[:disc.n]]
        self.b1, self.b2 = terms[:, 0].copy(), terms[:, 1].copy()
        self.e_squared = float(terms[:, 2].sum())
        self.I1, self.I2 = (f.x.array[:disc.n].copy() for f in interpolant)

    def __call__(self, X):
        d = self.disc
        n = d.n
        d1, d2 = X[:n] - self.I1, X[n:2 * n] - self.I2
        value = self.e_squared + ((d1 @ (d.S1 @ d1) + d2 @ (d.S2 @ d2))
                                  - 2.0 * (self.b1 @ d1 + self.b2 @ d2))
        return float(np.sqrt(max(value, 0.0)))

    def per_cell(self, X):
        """|||u - u_h|||_K for every local cell K (the actual error distribution)."""
        from dolfinx import fem
        d = self.disc
        mesh = d.V.mesh
        DG0 = fem.FunctionSpace(mesh, ("DG", 0))
        uh = []
        for k in range(2):
            f = fem.Function(d.V)
            f.x.array[:d.n] = X[k * d.n:(k + 1) * d.n]
            f.x.scatter_forward()
            uh.append(f)
        e1, e2 = (u - f for u, f in zip(self.exact, uh))
        values = assemble_vector_array(over(d.dx_data, lambda dx: energy_norm_squared(
            *self.mu, e1, e2, dx, ufl.TestFunction(DG0))))
        ncells = mesh.topology.index_map(2).size_local
        return np.sqrt(np.maximum(values[DG0.dofmap.list.array[:ncells]], 0.0))
