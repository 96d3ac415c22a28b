"""Residual liftings (DESIGN §4) and the discretisation flux σ_α,disc (DESIGN §5).

## Residual lifting

An algebraic residual R_α (nodal, zero at Dirichlet vertices) is lifted to r_αh, discontinuous
P1: on each cell K with vertices a_l, (r_αh, ψ_{a_l})_K = R_{α,l} / N_l, N_l the number of cells
sharing a_l. With the P1 mass matrix M_K = |K|/12 [[2,1,1],[1,2,1],[1,1,2]] this is
r_K = M_K⁻¹ (R_l / N_l)_l = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]] (R_l / N_l)_l, the
operator `Lifting` below (DG1 coefficients, in the cell's vertex order; tests/
test_equilibration checks it against the sparse matrix of the formula and against R).

## Patchwise equilibration

For every vertex a and membrane α, on the patch ω_a (cells sharing a), with RT_1 (basix "RT",
degree 2) × discontinuous P1:

    (σ_a, v) - (γ_a, ∇·v) = -(ψ_a μ_α ∇u_αh, v)       ∀ v ∈ V_h^a
    (∇·σ_a, q)            = (g̃_a, q)                    ∀ q ∈ Q_h^a
    g̃_a = ψ_a (f_α ± λ_a - r_αh) - μ_α ∇u_αh·∇ψ_a

V_h^a has zero normal component on the patch boundary except, for a vertex a on ∂Ω, on the
patch edges that lie on ∂Ω; for an interior vertex the normal component vanishes on all of ∂ω_a
(ψ_a vanishes there; Ern & Vohralík's choice) and Q_h^a has zero mean, imposed by a Lagrange
multiplier. σ_α,disc = Σ_a σ_a lies in H(div) and ∇·σ_α,disc = Π_P1 f_α ± λ_h - r_αh.

The patch matrices depend on the mesh only. They are made of per-cell blocks of the RT_1 × DG1
mass, divergence and moment forms in dolfinx's global RT basis: reference integrals of basix's
RT_1 basis (exact quadrature), mapped to each cell by the contravariant Piola map, times the
edge reflections that dolfinx applies (for RT_1, a sign per edge); tests/test_equilibration
checks them against matrices assembled by dolfinx. A patch keeps the dofs of its cells except
those its boundary drops, so its matrices are sums of these blocks. Since σ_a is linear in the
data, the set-up solves every patch problem once for the *operators*

    σ_α,disc = μ_α G_u u_α ± G_λ λ + G_R R_α + σ_f,α

(G_u, G_λ, G_R sparse, σ_f,α a fixed vector): one evaluation is three sparse products, O(N).
Where many patches are translates of one another (a uniform refinement: all but a few, in about
#vertices + #edges + #cells of T_0 classes) the operators are not assembled: each class keeps
one dense operator from the patch's data (∇u_h per cell, R_l / N_l at its vertices, λ_a) to
σ_a, computed for a representative (its r_h columns composed with the local lifting), and
each patch its data indices and change of RT basis (entries 0, ±1; `_translates`); one
evaluation is then a gather, one batched product per stack of classes and one compiled pass
for the change of basis and the scatter (algebraic_flux._apply_buckets). The other patches keep
the sparse operators, restricted to the RT dofs they touch. The set-up handles all the
patches of one size at once (classes, changes of basis, the representatives' systems in
batches of one shape), so that its cost is a few passes over arrays of O(N) entries. The
passes whose per-item work is a few dozen table look-ups are compiled loops (`compiled.kernel`)
that touch each item once, where numpy made many temporaries of O(N) entries each (DESIGN
§5): the cells' areas and gradients (`_cell_geometry`), the patches' cells
(`meshes.cells_by_vertex`, `_patch_cells`), the patch matrices (`_assemble_patches`: each cell's
blocks added where its retained dofs sit, no index arrays of P n 64 entries), the cells'
centroids and ∂Ω edges (`_class_cell_data`), the classes from the patches' rounded centroid
offsets (`_signatures`: a sort of each patch's m keys; a hash and numpy's sort of the hashes;
`_match`: a check of the vertices, each cell's canonical vertex order computed at its first
use), and each member's change of basis and data indices from tables per representative dof
(`_member_maps`, in the patches' order). The arrays of O(N) entries that the set-up keeps are
made in populated pages (`populated_empty`): where a page's first write is dear (this machine's
virtual machine), one mapping call for all of them instead of a fault per page.

The right-hand sides use exact integrals of P1 products on each cell; only (ψ_a f_α, q) needs
quadrature (the scene's data measures; `load_moments`: f_α evaluated once at the points of
their rules, and one compiled pass that gives the moments (f_α φ_k, φ_i)_K (symmetric in
i, k: six per cell, both membranes side by side) and the squares
‖f_α - Π_P1 f_α‖_K² of the data oscillation, DESIGN §7).

With a mask `owned` over the vertices, only the patches of the owned vertices are set up: σ is
then their part of the sum, and the parts of a partition of the vertices add up to σ_α,disc
(each process of a distributed run sets up its own vertices and the parts are summed).
"""

import functools
import itertools

import numpy as np
import scipy.sparse as sp

from .compiled import kernel, part
from .discretisation import load
from .kept import KeptArrays
from .meshes import cells_by_vertex, p1_cells

# ∫_K φ_k φ_l φ_i / |K| for barycentric φ: 1/10 (k = l = i), 1/30 (two equal), 1/60 (distinct)
_C3 = np.empty((3, 3, 3))
for _k in range(3):
    for _l in range(3):
        for _i in range(3):
            _C3[_k, _l, _i] = {1: 1 / 10, 2: 1 / 30, 3: 1 / 60}[len({_k, _l, _i})]
_MINV_REF = np.array([[3.0, -1.0, -1.0], [-1.0, 3.0, -1.0], [-1.0, -1.0, 3.0]])


@part
def p1_mass_solve(area, l0, l1, l2):
    """The P1 coefficients (p_0, p_1, p_2) on a cell of area |K| with (p, φ_i)_K = l_i:
    p = (3/|K|) _MINV_REF l (the inverse of the cell's P1 mass matrix |K|/12 (I + 1 1ᵀ)), for
    the compiled passes (the L² projection of the loads, `_data_moments`, and the lifting's
    cell values, estimators._lifted_squares; `Lifting` is the same map for numpy)."""
    scale = 3.0 / area
    # the terms in column order, as the product with _MINV_REF adds them
    return (scale * (3.0 * l0 - l1 - l2), scale * (-l0 + 3.0 * l1 - l2),
            scale * (-l0 - l1 + 3.0 * l2))


# the symmetric pairs (i, k) of a cell's 3 × 3 load moments, numbered as ik = 00, 01, 02, 11,
# 12, 22 (load_moments keeps these six)
_SYM = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])


class Geometry:
    """Cells as P1 dof triples, areas, barycentric gradients, and the number of cells at each
    vertex."""

    def __init__(self, V):
        mesh = V.mesh
        self.V = V
        self.ncells = mesh.topology.index_map(2).size_local
        self.cells = p1_cells(V).astype(np.int64)
        self.n = V.dofmap.index_map.size_local
        self.x = x = np.ascontiguousarray(V.tabulate_dof_coordinates()[:, :2])
        self.area = np.empty(self.ncells)
        self.grad = populated_empty((self.ncells, 3, 2), float)  # (ncells, 3, 2)
        _cell_geometry(x, self.cells, self.area, self.grad)
        self.cells_per_vertex = np.bincount(self.cells.ravel(), minlength=self.n)

    def gradient(self, u):
        """∇u_h per cell, shape (ncells, 2), for nodal P1 values u (numpy; compiled passes
        take `cell_gradient`)."""
        return np.einsum("ck,ckd->cd", u[self.cells], self.grad)

    def jacobians(self, cells):
        """J = [x_1 - x_0, x_2 - x_0] (columns) of the affine maps of the given cells from the
        reference triangle, shape (c, 2, 2)."""
        p = self.x[self.cells[cells]]
        return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=2)


@part
def cell_gradient(grad, K, v0, v1, v2):
    """∇v_h on the cell K for the P1 values v0, v1, v2 at its vertices: Σ_k v_k ∇φ_k (grad:
    the cells' hat gradients, Geometry.grad), the terms added in the order k = 0, 1, 2 (the
    one formula of the compiled passes: the classes' data of `sigmas`, the flux norms and the
    constraint parts of membranes.estimators)."""
    g0 = 0.0
    g1 = 0.0
    g0 += v0 * grad[K, 0, 0]
    g1 += v0 * grad[K, 0, 1]
    g0 += v1 * grad[K, 1, 0]
    g1 += v1 * grad[K, 1, 1]
    g0 += v2 * grad[K, 2, 0]
    g1 += v2 * grad[K, 2, 1]
    return g0, g1


@kernel
def _cell_geometry(x, cells, area, grad):
    """Into area (ncells,) and grad (ncells, 3, 2): |K| and the barycentric gradients ∇φ_k of
    each cell, the rows of the inverse Jacobian transpose applied to the reference gradients
    (-1, -1), (1, 0), (0, 1): with e1 = x_1 - x_0, e2 = x_2 - x_0 and det = e1 × e2,
    ∇φ_1 = (e2_y, -e2_x) / det, ∇φ_2 = (-e1_y, e1_x) / det, ∇φ_0 = -(∇φ_1 + ∇φ_2)."""
    for c in range(area.shape[0]):
        a, b, d = cells[c, 0], cells[c, 1], cells[c, 2]
        e1x, e1y = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1]
        e2x, e2y = x[d, 0] - x[a, 0], x[d, 1] - x[a, 1]
        det = e1x * e2y - e1y * e2x
        area[c] = 0.5 * abs(det)
        grad[c, 1, 0], grad[c, 1, 1] = e2y / det, -e2x / det
        grad[c, 2, 0], grad[c, 2, 1] = -e1y / det, e1x / det
        grad[c, 0, 0] = -(grad[c, 1, 0] + grad[c, 2, 0])
        grad[c, 0, 1] = -(grad[c, 1, 1] + grad[c, 2, 1])


class Lifting:
    """`Lifting(geo) @ R`: the lifting R ↦ r_h of DESIGN §4 (DG1 coefficients, 3 per cell in
    vertex order), applied without storing its matrix: per cell
    r_K = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]] (R_l / N_l)_l, the quotients R_l / N_l
    formed once per vertex and the factors 3/|K| kept."""

    def __init__(self, geo):
        self.geo = geo
        self.scale = (3.0 / geo.area)[:, None]

    def __matmul__(self, R):
        v = (R / self.geo.cells_per_vertex)[self.geo.cells]
        return (self.scale * (v @ _MINV_REF.T)).ravel()


def populated_empty(shape, dtype, zero=False):
    """np.empty(shape, dtype) (np.zeros with zero=True), for a large array (16 MB or more) in
    pages that the kernel maps at once (an anonymous private mmap with MAP_POPULATE: zero
    pages) instead of at the first write to each: where page faults are dear (this machine's
    virtual machine: 0.5-0.7 s per 360 MB of fresh pages written, against 0.14 s populated),
    for the arrays of O(N) entries that the set-up and the evaluation make (the members' maps
    that `_member_maps` writes in a scattered order, the cells' gradients, σ_f, the classes'
    data that `sigmas` keeps; not the σ that each call returns, whose arrays are kept for
    the calls after: membranes.kept)."""
    import mmap
    dtype = np.dtype(dtype)
    size = int(np.prod(shape)) * dtype.itemsize
    if size < 1 << 24 or not hasattr(mmap, "MAP_POPULATE"):
        return (np.zeros if zero else np.empty)(shape, dtype)
    buf = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | mmap.MAP_POPULATE)
    return np.frombuffer(buf, dtype=dtype).reshape(shape)


def _local_index_type(n):
    """The smallest integer type for local numbers 0 .. n - 1."""
    return np.uint8 if n <= 256 else np.int16 if n <= 2 ** 15 else np.int32


def _rt_element():
    """basix's element of dolfinx's ("RT", 2): RT_1, Legendre variant."""
    import basix
    return basix.create_element(basix.ElementFamily.RT, basix.CellType.triangle, 2,
                                basix.LagrangeVariant.legendre)


def cell_reflections(mesh, ncells):
    """The edge reflections of the first ncells cells of `mesh` (bit e: edge e), which the RT
    basis carries (dolfinx's dof transformations)."""
    mesh.topology.create_entity_permutations()
    return np.asarray(mesh.topology.get_cell_permutation_info())[:ncells] & 7


def rt_signs(reflections):
    """The RT_1 dof signs (..., 8), ±1 as int8, of cells with these edge reflections (the
    dof transformations of `_rt_reference`)."""
    return _rt_reference()[3].astype(np.int8)[reflections]


@functools.lru_cache(maxsize=None)
def _rt_reference():
    """Integrals over the reference triangle of dolfinx's ("RT", 2) basis ψ̂ (basix's RT of
    degree 2, Legendre variant), with an exact quadrature (degree 4): mass[a, b, i, j] =
    ∫ ψ̂_i^a ψ̂_j^b, div[i, j] = ∫ φ̂_i ∇̂·ψ̂_j and moment[a, j, k] = ∫ ψ̂_j^a φ̂_k (φ̂ the P1 hats),
    and sign[ρ] (8, 8): the dof transformation of a cell whose edges with a bit set in ρ are
    reflected (basix's base transformations; for this element a sign on one dof per edge)."""
    import basix
    e = _rt_element()
    X, w = basix.make_quadrature(basix.CellType.triangle, 4)
    tab = e.tabulate(1, X)                                    # (3, npts, 8, 2)
    psi, div = tab[0], tab[1][:, :, 0] + tab[2][:, :, 1]
    hat = np.stack([1.0 - X[:, 0] - X[:, 1], X[:, 0], X[:, 1]], axis=1)
    mass = np.einsum("q,qia,qjb->abij", w, psi, psi)
    div = np.einsum("q,qi,qj->ij", w, hat, div)
    moment = np.einsum("q,qja,qk->ajk", w, psi, hat)
    T = e.base_transformations()                  # exact to round-off: ±1 on the diagonal
    sign = np.ones((8, 8))
    for edge in range(3):
        if np.abs(np.abs(T[edge]) - np.eye(8)).max() > 1e-12:
            raise RuntimeError("RT_1 edge transformations are not sign changes")
        sign[[rho for rho in range(8) if rho >> edge & 1]] *= np.round(np.diag(T[edge]))
    return mass, div, moment, sign


def graph_colouring(pairs, n, seed=0):
    """Colours of n nodes such that the two ends of every pair (m, 2) differ (Jones–Plassmann:
    in each round the nodes whose random priority beats their uncoloured neighbours take the
    smallest colour their neighbours do not use; at most max degree + 1 colours)."""
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    both = np.vstack([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    rank = np.arange(both.shape[0]) - np.searchsorted(both[:, 0], both[:, 0])
    degree = int(rank.max()) + 1 if len(rank) else 0
    nb = np.full((n, max(degree, 1)), -1, dtype=np.int64)
    nb[both[:, 0], rank] = both[:, 1]
    has = nb >= 0
    prio = np.random.default_rng(seed).permutation(n)
    colour = np.full(n, -1)
    while (colour < 0).any():
        unc = colour < 0
        rival = np.where(has & unc[nb], prio[nb], -1).max(axis=1)
        pick = unc & (prio > rival)
        used = np.where(has, colour[nb], -1)[pick]
        choice = np.full(used.shape[0], -1)
        for c in range(degree + 1):
            free = (choice < 0) & ~(used == c).any(axis=1)
            choice[free] = c
        colour[pick] = choice
    return colour


def _row_unique(values, sentinel):
    """Sorted distinct entries of each row (sentinel dropped); all rows must have as many."""
    S = np.sort(values, axis=1)
    new = np.ones_like(S, dtype=bool)
    new[:, 1:] = S[:, 1:] != S[:, :-1]
    new &= S != sentinel
    count = new.sum(axis=1)
    return S[new].reshape(values.shape[0], count[0]), count


def _row_index(table, values):
    """Position of each entry of `values` (P, L) in the sorted rows of `table` (P, k)."""
    P, k = table.shape
    big = np.int64(max(table.max(), values.max()) + 2)
    off = np.arange(P, dtype=np.int64)[:, None] * big
    idx = np.searchsorted((table + off).ravel(), (values + off).ravel()).reshape(values.shape)
    return idx - np.arange(P)[:, None] * k


def patch_vertices(geo, CS):
    """The vertices of P patches of one shape (cells CS (P, n), m vertices each): VERTS (P, m)
    ascending and their local numbers vloc (P, n, 3) in the cells' vertex order."""
    P, n = CS.shape
    VERTS, _ = _row_unique(geo.cells[CS].reshape(P, -1), -1)
    return VERTS, _row_index(VERTS, geo.cells[CS].reshape(P, -1)).reshape(P, n, 3)


def local_lifting(geo, CS, vloc, m, divide=True):
    """(P, 3n, m): the lifting of DESIGN §4 (`Lifting`) on P patches (cells CS (P, n), local
    vertex numbers vloc, m vertices), from nodal values at the patch's vertices to r_h on its
    cells (3 per cell, vertex order): (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]] (R_l / N_l)_l;
    with divide=False the values are R_l / N_l already (no division)."""
    P, n = CS.shape
    liftK = (3.0 / geo.area[CS])[..., None, None] * _MINV_REF                 # (P, n, 3, 3)
    if divide:
        liftK = liftK / geo.cells_per_vertex[geo.cells[CS]][:, :, None, :]
    Lr = np.zeros((P, 3 * n, m))
    qloc = 3 * np.arange(n)[None, :, None] + np.arange(3)[None, None, :]      # (1, n, 3)
    Lr[np.arange(P)[:, None, None, None], qloc[..., None], vloc[:, :, None, :]] = liftK
    return Lr


class PatchSpace:
    """RT_1 × DG1 on one mesh, with the per-cell blocks that every patch problem is made of:
    Me[K] = (φ_j, φ_i)_K (RT mass), Be[K] = (∇·φ_j, q_i)_K and Ce[K] = (φ_k e_d, φ_j)_K, in
    the global RT basis (dof transformations applied as dolfinx does), computed from the
    cells' geometry (`element_blocks`, `vector_moments`) for the cells asked for."""

    def __init__(self, V, blocks=True):
        from dolfinx import fem, mesh as dmesh
        mesh = V.mesh
        self.V = V
        self.geo = geo = Geometry(V)
        nc = geo.ncells
        self.RT = fem.FunctionSpace(mesh, ("RT", 2))
        # dolfinx's int32 arrays as they are (no int64 copies of O(ncells) entries; the
        # products that need 64 bits are formed in int64 where they are made)
        self.rt_cells = self.RT.dofmap.list.array.reshape(nc, -1)
        _check_vertex_order(V)
        # edge e of a cell is opposite its vertex e (basix); which RT dofs sit on which edge
        layout = self.RT.dofmap.dof_layout
        self.edge_of_dof = np.full(8, -1)
        for e in range(3):
            self.edge_of_dof[layout.entity_dofs(1, e)] = e
        # slot[e] (3 edges, then the interior): the entity's dofs in their order; a dof's
        # slot is the same in every cell that has the entity (dolfinx numbers the dofs of an
        # entity once and carries orientations in the dof transformations)
        self.slots = np.array([layout.entity_dofs(1, e) for e in range(3)]
                              + [layout.entity_dofs(2, 0)])
        mesh.topology.create_connectivity(2, 1)
        self.c2e = mesh.topology.connectivity(2, 1).array.reshape(nc, 3)
        nedges = mesh.topology.index_map(1).size_local + mesh.topology.index_map(1).num_ghosts
        exterior = np.zeros(nedges, dtype=bool)
        mesh.topology.create_connectivity(1, 2)          # the exterior facets read it
        exterior[dmesh.exterior_facet_indices(mesh.topology)] = True
        self.exterior_edge = exterior[self.c2e]
        self.nrt = self.RT.dofmap.index_map.size_local
        self.reflections = cell_reflections(mesh, nc).astype(np.int64)
        self.Me = self.Be = None
        if blocks:
            self.Me, self.Be = self.element_blocks(np.arange(nc))

    @functools.cached_property
    def DG(self):
        """dolfinx's discontinuous P1 on the mesh, made at first use (the set-up works with DG1
        coefficients in each cell's P1 vertex order and needs no space; tests and pictures
        make functions of it), its dofs checked to be in that order."""
        from dolfinx import fem
        DG = fem.FunctionSpace(self.V.mesh, ("DG", 1))
        _check_vertex_order(self.V, DG)
        return DG

    @functools.cached_property
    def dg_cells(self):
        """The DG1 dofs of each cell (ncells, 3), in its P1 vertex order."""
        return self.DG.dofmap.list.array.reshape(self.geo.ncells, -1).astype(np.int32)

    def _mapped(self, cells):
        """Jacobians, sign of det J, and the dof signs of the given cells."""
        cells = np.asarray(cells, dtype=np.int64)
        J = self.geo.jacobians(cells)
        det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
        return J, det, rt_signs(self.reflections[cells])

    def element_blocks(self, cells):
        """(Me, Be) of the given cells: Me (c, 8, 8), Be (c, 3, 8). With the contravariant
        Piola map φ = J ψ̂ / det J and dx = |det J| dx̂: Me = s sᵀ ⊙ Σ_ab (JᵀJ)_ab mass_ab /
        |det J| and Be = sign(det J) div ⊙ sᵀ (s the cell's dof signs)."""
        mass, div, _, _ = _rt_reference()
        J, det, s = self._mapped(cells)
        JtJ = np.einsum("cda,cdb->cab", J, J).reshape(-1, 4) / np.abs(det)[:, None]
        Me = (JtJ @ mass.reshape(4, 64)).reshape(-1, 8, 8) * s[:, :, None] * s[:, None, :]
        Be = np.sign(det)[:, None, None] * div[None] * s[:, None, :]
        return Me, Be

    def vector_moments(self, cells):
        """Ce (c, 8, 6) of the given cells: Ce[K][j, 2k + d] = (φ_k e_d, φ_j)_K (φ_k the P1 hat
        of vertex k) = sign(det J) s_j Σ_a J_da moment[a, j, k]."""
        _, _, moment, _ = _rt_reference()
        J, det, s = self._mapped(cells)
        Ce = np.einsum("cda,ajk->cjkd", J, moment) * (np.sign(det)[:, None] * s)[:, :, None,
                                                                                   None]
        return Ce.reshape(-1, 8, 6)

    def retained_dofs(self, CS, boundary, vertex_local=None):
        """Global RT dofs of P patches of the cells CS (P, n) (-1 where dropped): V_h^a has zero
        normal component on the patch boundary (edges in one patch cell only), except on ∂Ω
        for a patch of a boundary vertex (DESIGN §5; `boundary` (P,) flags those). For vertex
        patches, `vertex_local` (P, n) the vertex's local index in each cell: an edge is then
        in two patch cells iff it contains the vertex (is not opposite it) and is not on ∂Ω."""
        P, n = CS.shape
        exterior = self.exterior_edge[CS]
        if vertex_local is None:
            edges = self.c2e[CS].reshape(P, -1)
            big = np.int64(edges.max() + 1)
            keys = edges + np.arange(P, dtype=np.int64)[:, None] * big
            srt = np.sort(keys, axis=1)
            twice = srt[:, 1:][srt[:, 1:] == srt[:, :-1]]
            inside = np.isin(keys, twice).reshape(P, n, 3)
        else:
            inside = (np.arange(3) != vertex_local[:, :, None]) & ~exterior
        keep_edge = inside | (exterior & np.asarray(boundary, dtype=bool)[:, None, None])
        e = self.edge_of_dof
        keep = np.where(e[None, None, :] >= 0, np.take(keep_edge, np.maximum(e, 0), axis=2),
                        True)
        return np.where(keep, self.rt_cells[CS], -1).reshape(P, -1)

    def saddle_point_systems(self, CS, glob, boundary, blocks=None):
        """Local numbering and matrices of P patch problems of one shape (DESIGN §5):
        A = [[M, -Bᵀ, 0], [B, 0, c], [0, cᵀ, 0]] with the zero-mean multiplier row (c = (1, q))
        for interior patches only. Returns RET (P, nr) the global RT dofs, loc (P, n, 8) their
        local numbers (-1 dropped) and A (P, N, N), N = nr + 3n (+ 1). `blocks`: (Me, Be) of
        the cells CS, shapes (P, n, 8, 8) and (P, n, 3, 8); by default those the space keeps,
        or else computed from the geometry."""
        geo = self.geo
        P, n = CS.shape
        sentinel = np.iinfo(np.int64).max
        RET, _ = _row_unique(np.where(glob < 0, sentinel, glob), sentinel)    # (P, nr)
        nr = RET.shape[1]
        loc = np.where(glob < 0, -1, _row_index(RET, np.maximum(glob, 0))).reshape(P, n, 8)
        nq = 3 * n
        N = nr + nq + (0 if boundary else 1)
        A = np.zeros((P, N, N))
        if blocks is not None:
            Me, Be = blocks
        elif self.Me is not None:
            Me, Be = self.Me[CS], self.Be[CS]
        else:
            Me, Be = self.element_blocks(CS.ravel())
        _assemble_patches(loc, np.ascontiguousarray(Me).reshape(P, n, 8, 8),
                          np.ascontiguousarray(Be).reshape(P, n, 3, 8), nr, A)
        if not boundary:
            c = np.repeat(geo.area[CS] / 3.0, 3, axis=1)                     # (P, nq)
            A[:, nr:nr + nq, -1] = c
            A[:, -1, nr:nr + nq] = c
        return RET, loc, A

    def patch_groups(self, CS, boundary, chunk, glob=None):
        """Patches (cells CS (P, n), boundary flags, their retained dofs glob if known) in
        batches of one shape: yields (indices into the P patches, RET, loc, A)."""
        glob = self.retained_dofs(CS, boundary) if glob is None else glob
        S = np.sort(np.where(glob < 0, np.iinfo(np.int64).max, glob), axis=1)
        nr = ((S[:, 1:] != S[:, :-1]) & (S[:, 1:] != np.iinfo(np.int64).max)).sum(axis=1) + 1
        del S
        for b, r in sorted(set(zip(boundary.tolist(), nr.tolist()))):
            idx = np.flatnonzero((boundary == b) & (nr == r))
            for s in range(0, len(idx), chunk):
                sel = idx[s:s + chunk]
                yield (sel,) + self.saddle_point_systems(CS[sel], glob[sel], b)


@kernel
def _assemble_patches(loc, Me, Be, nr, A):
    """Into A (P, N, N), zero: the blocks M and ±B of `PatchSpace.saddle_point_systems` of P
    patches of n cells (local numbers loc (P, n, 8) of their RT dofs, -1 dropped; Me
    (P, n, 8, 8), Be (P, n, 3, 8)): M[loc_i, loc_l] += Me[j, i, l] in the order of the cells
    j, then i, l (the sums of the sparse assembly, term by term), and the rows nr + 3 j + i
    of B = Be, with -Bᵀ in the columns (each entry set once). One pass over the cells' blocks
    where numpy made index arrays of P n 64 entries."""
    P, n = loc.shape[0], loc.shape[1]
    for p in range(P):
        for j in range(n):
            for i in range(8):
                li = loc[p, j, i]
                if li < 0:
                    continue
                for l in range(8):
                    lj = loc[p, j, l]
                    if lj >= 0:
                        A[p, li, lj] += Me[p, j, i, l]
            for i in range(3):
                q = nr + 3 * j + i
                for l in range(8):
                    lj = loc[p, j, l]
                    if lj >= 0:
                        A[p, q, lj] = Be[p, j, i, l]
                        A[p, lj, q] = -Be[p, j, i, l]


def vertex_patches(geo, owned=None):
    """For every vertex a (or every vertex of the mask `owned`): its cells (grouped by count)
    and a's local index in each. Yields (vertices (P,), CS (P, n), KA (P, n))."""
    ptr, order = cells_by_vertex(geo.cells, geo.cells_per_vertex)
    count = geo.cells_per_vertex if owned is None else np.where(owned, geo.cells_per_vertex, 0)
    for n in np.unique(count[count > 0]):
        verts = np.flatnonzero(count == n)
        yield (verts,) + _patch_cells(order, ptr, verts, n)


@kernel
def _patch_cells(order, ptr, verts, n):
    """The cells CS (P, n) and local indices KA (P, n) of the vertices verts, each in n cells,
    from the positions in the cells' array grouped by vertex (`meshes.cells_by_vertex`)."""
    CS = np.empty((len(verts), n), dtype=np.int64)
    KA = np.empty((len(verts), n), dtype=np.int64)
    for p in range(len(verts)):
        for j in range(n):
            i = order[ptr[verts[p]] + j]
            CS[p, j] = i // 3
            KA[p, j] = i - 3 * CS[p, j]
    return CS, KA


_KEY_RANGE = 2 ** 30


@part
def _grid_key(d0, d1, unit):
    """The key of the point (d0, d1) on a grid of 1/unit (1e-6 scale): its coordinates in
    those units, rounded, each shifted by 2^30 and the pair combined into one int64 (> 0);
    -1 if a coordinate reaches 2^30 units (patches larger than 1000 scale: then no classes
    are formed)."""
    k0, k1 = np.rint(d0 * unit), np.rint(d1 * unit)
    if max(abs(k0), abs(k1)) >= _KEY_RANGE:
        return np.int64(-1)
    return (np.int64(k0) + _KEY_RANGE) * 2 ** 31 + (np.int64(k1) + _KEY_RANGE)


def _hash_multipliers(k, seed):
    """The fixed random odd c_i (k of them, uint64) of the row hash Σ_i keys[i] c_i mod 2^64
    (equal rows, equal hashes; different rows collide with probability about 2^-63, and
    every class is checked against its representative anyway)."""
    return (np.random.default_rng(seed).integers(1, 2 ** 62, size=k) | 1).astype(np.uint64)


def _row_hash(keys, seed):
    """One int64 per row of the integer array `keys` (n, k): the hash of `_hash_multipliers`."""
    keys = np.ascontiguousarray(keys, dtype=np.int64).view(np.uint64)    # wraps, as defined
    return (keys @ _hash_multipliers(keys.shape[1], seed)).view(np.int64)


# the permutations of (0, 1, 2) as itertools lists them; s is number 2 s[0] + (s[1] > s[2])
_PERMS = np.array(list(itertools.permutations(range(3))), dtype=np.int8)
# _MATCH[a, b] = t ∘ s⁻¹ for s = _PERMS[a], t = _PERMS[b]: the vertex i of a cell whose
# canonical order is s sits where vertex (t ∘ s⁻¹)[i] of a cell with canonical order t does
_MATCH = np.array([[t[np.argsort(s)] for t in _PERMS] for s in _PERMS], dtype=np.int8)


def _sort_code(le01, le02, le12):
    """The number among _PERMS of the stable sorting order of three keys, from k0 <= k1,
    k0 <= k2, k1 <= k2 (bits 0, 1, 2 of the index)."""
    ranks = [2 - le01 - le02, le01 + 1 - le12, le02 + le12]      # keys before each (ties: index)
    order = np.argsort(ranks)
    return 2 * order[0] + (order[1] > order[2])


_SORT3 = np.array([_sort_code(i & 1, i >> 1 & 1, i >> 2 & 1) for i in range(8)], dtype=np.int8)


@kernel
def _signatures(x, cells, cent, xa, CF, KF, boundary, exterior, unit, mult, h):
    """The hashes h (P,) of the signatures of P patches (`translation_classes`; the row hash
    of `_hash_multipliers`, multipliers mult, accumulated entry by entry), their cells CF, KF
    put in canonical order in place; False if a key overflows (the rows before it already
    reordered). The signature of a patch: its boundary flag, the keys of its m cells'
    centroid offsets from xa (rounded in units of 1/unit), sorted stably by insertion (ties
    keep the patch's order; the cells with them), then if exterior is given ((ncells, 3) ∂Ω
    flags of the cells' edges, edge e opposite vertex e), for a boundary patch the key of
    Σ_e [e on ∂Ω] (midpoint of e - xa) per cell, for the others the key of (0, 0)."""
    P, m = CF.shape
    key = np.empty(m, dtype=np.int64)
    order = np.empty(m, dtype=np.int64)
    cf, kf = CF[0].copy(), KF[0].copy()
    none = _grid_key(0.0, 0.0, unit)
    for p in range(P):
        for j in range(m):
            c = CF[p, j]
            key[j] = _grid_key(cent[c, 0] - xa[p, 0], cent[c, 1] - xa[p, 1], unit)
            if key[j] < 0:
                return False
            order[j] = j
            i = j                                                   # stable insertion sort
            while i > 0 and key[order[i - 1]] > key[j]:
                order[i] = order[i - 1]
                i -= 1
            order[i] = j
        acc = mult[0] if boundary[p] else np.uint64(0)
        cf[:] = CF[p]
        kf[:] = KF[p]
        for j in range(m):
            CF[p, j] = cf[order[j]]
            KF[p, j] = kf[order[j]]
            acc += np.uint64(key[order[j]]) * mult[1 + j]
        h[p] = acc
        if exterior.shape[0] == 0:
            continue
        for j in range(m):
            if not boundary[p]:
                acc += np.uint64(none) * mult[1 + m + j]
                continue
            c = CF[p, j]
            s0 = 0.0
            s1 = 0.0
            for e in range(3):
                a, b = cells[c, (e + 1) % 3], cells[c, (e + 2) % 3]
                f = 1.0 if exterior[c, e] else 0.0
                s0 += 0.5 * ((x[a, 0] - xa[p, 0]) + (x[b, 0] - xa[p, 0])) * f
                s1 += 0.5 * ((x[a, 1] - xa[p, 1]) + (x[b, 1] - xa[p, 1])) * f
            where = _grid_key(s0, s1, unit)
            if where < 0:
                return False
            acc += np.uint64(where) * mult[1 + m + j]
        h[p] = acc
    return True


@kernel
def _match(p, r, x, cells, cent, xa, boundary, exterior, CF, unit, tol, code, PERMS, SORT3,
           MATCH, ok, pi):
    """Whether patches p (cells CF in canonical order) are translates of the patches r, into
    ok: the same boundary flag, the vertices relative to xa within tol and, for boundary
    patches (exterior given), the same ∂Ω edges (edge e of a cell, opposite vertex e, matched
    to the edge opposite the matched vertex); and the vertex matches into pi[p] (_MATCH of
    the two cells' canonical vertex orders); False if a key overflows. The
    cells' canonical vertex orders (by the vertices' offsets from the centroid, keyed as in
    `_signatures`, ties by local number: the same order in translated cells) are computed at
    a cell's first use into code (-1: not yet)."""
    m = CF.shape[1]
    k = np.empty(3, dtype=np.int64)
    for q in range(len(p)):
        a, b = p[q], r[q]
        same = boundary[a] == boundary[b]
        edges = boundary[a] and exterior.shape[0] > 0
        for j in range(m):
            for t in range(2):
                c = CF[b, j] if t == 0 else CF[a, j]
                if code[c] < 0:
                    for i in range(3):
                        k[i] = _grid_key(x[cells[c, i], 0] - cent[c, 0],
                                         x[cells[c, i], 1] - cent[c, 1], unit)
                        if k[i] < 0:
                            return False
                    code[c] = SORT3[(k[0] <= k[1]) + 2 * (k[0] <= k[2]) + 4 * (k[1] <= k[2])]
            ca, cb = CF[a, j], CF[b, j]
            sa, sb = code[ca], code[cb]
            for i in range(3):
                va, vb = cells[ca, PERMS[sa, i]], cells[cb, PERMS[sb, i]]
                for d in range(2):
                    if not abs((x[va, d] - xa[a, d]) - (x[vb, d] - xa[b, d])) <= tol:
                        same = False
                pi[a, j, i] = MATCH[sa, sb, i]
            for i in range(3):
                if edges and exterior[ca, i] != exterior[cb, pi[a, j, i]]:
                    same = False
        ok[q] = same
    return True


def translation_classes(xa, CF, KF, boundary, geo, cent, scale, translates=True,
                        exterior=None):
    """Classes of translated patches: patch p around the point xa[p] (P, 2), made of the cells
    CF (P, m) of the mesh `geo` (centroids cent), KF (P, m) a per-cell label carried along, and
    boundary (P,) flags. Returns CF, KF put in a canonical order in place (by the offset of
    the cell centroid from xa), rep (P,) the representative of each patch and pi (P, m, 3): vertex
    pi[p, c, i] of the representative's cell c sits where vertex i of the patch's cell c does
    (relative to xa). Patches are classed by their offsets rounded to 1e-6 scale (through a
    64-bit hash of the rounded signature; each patch is checked against its representative:
    boundary flag, vertices, ∂Ω edges), and are translates to round-off only: a patch whose
    vertices (relative to xa) do not match its representative's within 1e-13 of the largest
    coordinate (a coincidence of the rounded keys: a near-translate) is classed again among
    such patches.
    `exterior` (ncells, 3): the cells' edges on ∂Ω (edge e opposite vertex e); boundary
    patches are then told apart by where their ∂Ω edges sit (the midpoints' offsets, per
    cell): two patches of boundary vertices with the same cells keep different RT dofs when
    one of them has a patch edge on ∂Ω where the other's is inside Ω (next to a corner of a
    structured square).

    Two compiled loops over the patches (`_signatures`, `_match`), each touching a patch's m
    cells once, with a hash and numpy's sort of the P hashes between them: the signature
    sorts only the m keys of each patch, and a cell's vertices are put in a canonical order
    (once per cell), so that a vertex match is a table entry per cell (_MATCH) and the check
    compares the vertices in that order."""
    P, m = CF.shape
    boundary = np.asarray(boundary, dtype=bool)

    def identity():
        return CF, KF, np.arange(P), np.broadcast_to(np.arange(3, dtype=np.int8),
                                                     (P, m, 3)).copy()

    if not translates or P == 0:
        return identity()
    # signature: boundary flag | the cells' rounded centroid offsets, sorted (the canonical
    # cell order) | for boundary patches, their ∂Ω edges
    unit = 1e6 / scale
    ext = np.zeros((0, 3), dtype=bool) if exterior is None else exterior
    h = np.empty(P, dtype=np.uint64)
    if not _signatures(geo.x, geo.cells, cent, xa, CF, KF, boundary, ext, unit,
                       _hash_multipliers(1 + (2 if exterior is not None else 1) * m, 0), h):
        return identity()
    h = h.view(np.int64)
    # round-off: the offsets are differences of coordinates of size up to |x|max, a few ulps
    # of it; 1e-13 |x|max leaves a margin of several hundred, and near-translates (a gmsh mesh
    # has patches equal to 1e-8 of their size) do not pass
    tol = 1e-13 * max(np.abs(geo.x).max(), scale)

    def fine_hash(p):
        """A hash of the centroid offsets of patches p on a grid of 1e-10 scale (and of the
        signature): near-translates differ there, translates rarely (round-off straddling a
        grid line only sends a patch to one more round)."""
        k = np.round((cent[CF[p]] - xa[p, None, :]) * (1e10 / scale)).astype(np.int64)
        return _row_hash(np.column_stack([k.reshape(len(p), 2 * m), h[p]]), seed=1)

    # classes by the hash of the rounded signature, each represented by its first patch; the
    # patches that fail the check against it (near-translates: rounded keys that coincide)
    # are classed again among themselves, by a finer hash, until every patch has a
    # representative it matches (each round matches at least its new representatives).
    # Making them their own classes instead split the homothetic copies of one patch across
    # the levels of the multilevel flux: 1618 classes at J = 3 and 2741 at J = 4 on the disk,
    # h0 = 0.132, where 1419 do for every J.
    rep = np.empty(P, dtype=np.int64)
    pi = np.empty((P, m, 3), dtype=np.int8)
    code = np.full(len(geo.cells), -1, dtype=np.int8)
    pending, key = np.arange(P), h
    while pending.size:
        _, first, gid = np.unique(key, return_index=True, return_inverse=True)
        r = pending[first[gid.ravel()]]
        rep[pending] = r
        ok = np.empty(len(pending), dtype=bool)
        if not _match(pending, r, geo.x, geo.cells, cent, xa, boundary, ext, CF, unit, tol,
                      code, _PERMS, _SORT3, _MATCH, ok, pi):
            return identity()
        pending = pending[~ok]
        key = fine_hash(pending)
    return CF, KF, rep, pi


def _check_vertex_order(V, DG=None):
    """The local formulas assume that a cell's P1 dofs (Geometry.cells) sit at its vertices in
    basix's reference vertex order, that of the hats of the reference integrals (and, with DG,
    that the DG1 dofs sit there in the same order); check it rather than trust it: the
    elements have their dofs at the reference vertices in that order and no dof
    transformations, and the cells' one geometry map takes them to the same points of every
    cell."""
    import basix
    for e in (V.element,) + (() if DG is None else (DG.element,)):
        if e.needs_dof_transformations or not e.interpolation_ident:
            raise RuntimeError("P1 or DG1 dofs are not point values at fixed reference points")
        if not np.array_equal(e.interpolation_points(), basix.geometry(basix.CellType.triangle)):
            raise RuntimeError("P1 or DG1 dofs are not at the reference vertices in order")


def data_rules(disc):
    """The scene's data measures (disc.dx_data, summed with `over`) as cells and quadrature
    rules: for each measure, (cells, points X (q, 2), weights w (q,)), the rule FFCx builds
    for its integrals (the custom points and weights of its metadata, or
    ffcx.element_interface.create_quadrature of its degree and scheme) and the local cells
    it integrates over (those of its subdomain id in its mesh tags, or all). The measures
    must not share a cell (as `discretisation.data_measures` makes them: cut cells and the
    others)."""
    from ffcx.element_interface import create_quadrature
    mesh = disc.V.mesh
    nc = mesh.topology.index_map(2).size_local
    rules, count = [], np.zeros(nc, dtype=np.int64)
    for dx in disc.dx_data:
        md = dx.metadata()
        if "quadrature_points" in md:
            X = np.asarray(md["quadrature_points"], dtype=np.float64).reshape(-1, 2)
            w = np.asarray(md["quadrature_weights"], dtype=np.float64)
        else:
            X, w = create_quadrature("triangle", md["quadrature_degree"],
                                     md.get("quadrature_rule", "default"))
        sid = dx.subdomain_id()
        if sid == "everywhere":
            cells = np.arange(nc, dtype=np.int32)
        else:
            tags = dx.subdomain_data()
            cells = tags.indices[tags.values == sid].astype(np.int32)
            cells = cells[cells < nc]
        count[cells] += 1
        rules.append((cells, np.ascontiguousarray(X), np.ascontiguousarray(w)))
    if count.max(initial=0) > 1:
        raise RuntimeError("data measures that share cells")
    return rules


def load_moments(disc, geo):
    """Wf (ncells, 6, 2) with Wf[K, _SYM[i, k], α] = (f_α φ_k, φ_i)_K (symmetric in i, k:
    six per cell; the two membranes' moments side by side, as FluxEquilibration._class_load
    takes them), and the squares
    ‖f_α - Π_P1 f_α‖_K² (2, ncells) that the data oscillation takes (DESIGN §7), with the
    scene's data measures (`data_rules`): f_α at the points of each rule on its cells, a
    dolfinx Expression of the UFL load evaluated by blocks of cells, then one compiled pass
    over the block (`_data_moments`) forms a cell's moments |det J| Σ_q w_q f(x_q) φ_k φ_i,
    Π_P1 f_α = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]] ((f_α, φ_i)_K)_i (the L² projection;
    (f_α, φ_i)_K = Σ_k (f_α φ_k, φ_i)_K) and |det J| Σ_q w_q (f(x_q) - Π_P1 f(x_q))². One
    evaluation of f_α at each quadrature point serves both; the sums are those of the
    assembled forms (f_α, φ_i φ_k) and ((f_α - Π_P1 f_α)², 1_K) regrouped (equal to round-off:
    tests/test_equilibration, tests/test_estimators), with no function space or assembly."""
    import ufl
    from dolfinx import fem
    mesh = disc.V.mesh
    nc = geo.ncells
    W = np.zeros((nc, 6, 2))
    sq = np.zeros((2, nc))
    loads = ufl.as_vector([load(f, mesh) for f in (disc.problem.f1, disc.problem.f2)])
    for cells, X, w in data_rules(disc):
        hat = np.stack([1.0 - X[:, 0] - X[:, 1], X[:, 0], X[:, 1]], axis=1)     # φ_k(X_q)
        products = np.ascontiguousarray(hat[:, [0, 0, 0, 1, 1, 2]] * hat[:, [0, 1, 2, 1, 2, 2]])
        expr = fem.Expression(loads, X)                    # (f_1, f_2) at each point
        block = max(1, (1 << 18) // len(w))                # f values of a block: 4 MB
        values = np.empty((min(block, len(cells)), 2 * len(w)))
        for s in range(0, len(cells), block):
            c = cells[s:s + block]
            fv = values[:len(c)]
            expr.eval(c, fv)
            _data_moments(c, fv, w, np.ascontiguousarray(hat), products, geo.area, W, sq)
    return W, sq


@kernel
def _data_moments(cells, fv, w, hat, products, area, W, sq):
    """`load_moments` on the given cells, with f_α at the rule's points fv (c, 2 q) (point by
    point, f_1 then f_2; weights w, hat values φ_k(X_q) (q, 3), products (q, 6) φ_i φ_k for
    ik = 00, 01, 02, 11, 12, 22): for α = 1, 2, W[K, ik, α] = |det J| Σ_q w_q f_q φ_i φ_k
    (|det J| = 2 |K|), the loads l_i = Σ_k W[α, K, i, k] = (f, φ_i)_K, Π_P1 f = Σ_k p_k φ_k
    with p = `p1_mass_solve`(|K|, l), and sq[α, K] = |det J| Σ_q w_q (f_q - Π_P1 f(x_q))²."""
    nq = len(w)
    for j in range(len(cells)):
        K = cells[j]
        det = 2.0 * area[K]
        for a in range(2):
            m00 = m01 = m02 = m11 = m12 = m22 = 0.0
            for q in range(nq):
                wf = w[q] * fv[j, 2 * q + a]
                m00 += wf * products[q, 0]
                m01 += wf * products[q, 1]
                m02 += wf * products[q, 2]
                m11 += wf * products[q, 3]
                m12 += wf * products[q, 4]
                m22 += wf * products[q, 5]
            m00, m01, m02 = det * m00, det * m01, det * m02
            m11, m12, m22 = det * m11, det * m12, det * m22
            W[K, 0, a], W[K, 1, a], W[K, 2, a] = m00, m01, m02
            W[K, 3, a], W[K, 4, a], W[K, 5, a] = m11, m12, m22
            l0, l1, l2 = m00 + m01 + m02, m01 + m11 + m12, m02 + m12 + m22
            p0, p1, p2 = p1_mass_solve(area[K], l0, l1, l2)
            e2 = 0.0
            for q in range(nq):
                e = fv[j, 2 * q + a] - (p0 * hat[q, 0] + p1 * hat[q, 1] + p2 * hat[q, 2])
                e2 += w[q] * e * e
            sq[a, K] = det * e2


@kernel
def _class_cell_data(x, cells, exterior, cent, bits):
    """Into cent (ncells, 2) and bits (ncells,): each cell's centroid (x_0 + x_1 + x_2) / 3
    and its edges on ∂Ω (exterior (ncells, 3)) as bits (bit e: edge e), in one pass."""
    for c in range(len(bits)):
        a, b, d = cells[c, 0], cells[c, 1], cells[c, 2]
        cent[c, 0] = (x[a, 0] + x[b, 0] + x[d, 0]) / 3.0
        cent[c, 1] = (x[a, 1] + x[b, 1] + x[d, 1]) / 3.0
        bits[c] = (1 if exterior[c, 0] else 0) + (2 if exterior[c, 1] else 0) \
            + (4 if exterior[c, 2] else 0)


@part
def perm_number(p0, p1, p2):
    """The number 2 i_0 + (i_1 > i_2) (0 … 5) of the permutation P_π with P_π(ê_i') = ê_π(i')
    that maps a representative's vertex order onto a patch cell's, for the vertex map
    pi = (p0, p1, p2) (patch vertex i -> representative vertex p_i; π = pi⁻¹, i_v the i with
    p_i = v): the index of the change-of-basis tables (`change_of_basis_tables`), for the
    members' maps here and the multilevel flux's (algebraic_flux._perm_code)."""
    i0 = 0 if p0 == 0 else (1 if p1 == 0 else 2)
    i1 = 0 if p0 == 1 else (1 if p1 == 1 else 2)
    i2 = 0 if p0 == 2 else (1 if p1 == 2 else 2)
    return 2 * i0 + (1 if i1 > i2 else 0)


@kernel
def _member_maps(row, bi, CF, KF, pi, boundary, verts, ext_bits, reflections, rt_cells, cells,
                 cell, base, part, redges, lr, first, PATCH_DOF, TOP, COEF, EDGE_BITS, PERMS, SYM,
                 nc, nv, RET, L, C, G, GF):
    """The loop of `FluxEquilibration._translates` (its arguments, with row (P,) the row of
    each member patch in the outputs, -1 for the others, and the tables of `_representatives`
    and `_class_tables` unpacked): 0, or 1 if a member keeps other edges
    than its representative, 2 if a retained dof maps to a dropped one. Per member cell, the
    number π of the vertex permutation (`perm_number`) and
    the kept edges as bits (those not opposite a and not on ∂Ω, and for a boundary vertex
    those on ∂Ω); per retained dof i, in slot l of the representative's cell c with
    reflections ρ_r, the table entry u = 384 ρ_r + 64 π_c + 8 ρ_p + l (ρ_p the member cell's
    reflections) gives the patch dof and the (at most two) representative dofs of its
    column of W (64 π_c + 8 ρ_p formed once per cell)."""
    n = CF.shape[1]
    nr = cell.shape[1]
    m = first.shape[1]
    perm = np.empty(n, dtype=np.int64)
    cu = np.empty(n, dtype=np.int64)       # the part of u that depends on the cell only
    for p in range(len(row)):                 # in the patches' order: their cells are near
        q, b = row[p], bi[p]
        if q < 0:
            continue
        for j in range(n):
            perm[j] = perm_number(pi[p, j, 0], pi[p, j, 1], pi[p, j, 2])
            cu[j] = 64 * perm[j] + 8 * reflections[CF[p, j]]
            ext = ext_bits[CF[p, j]]
            bits = 7 & ~(1 << KF[p, j]) & ~ext
            if boundary[p]:
                bits |= ext
            if EDGE_BITS[perm[j], bits] != redges[b, j]:
                return 1
        for i in range(nr):
            c = cell[b, i]
            u = part[b, i] + cu[c]
            RET[q, i] = rt_cells[CF[p, c], PATCH_DOF[u]]
            c0, c1 = COEF[0, u], COEF[1, u]
            t0, t1 = lr[base[b, i] + TOP[0, u]], lr[base[b, i] + TOP[1, u]]
            if (c0 != 0 and t0 < 0) or (c1 != 0 and t1 < 0):
                return 2
            C[q, i, 0], C[q, i, 1] = c0, c1
            L[q, i, 0], L[q, i, 1] = max(t0, 0), max(t1, 0)
        for j in range(n):
            G[q, 2 * j] = 2 * CF[p, j]
            G[q, 2 * j + 1] = 2 * CF[p, j] + 1
            for k in range(3):
                GF[q, 3 * j + k] = 6 * CF[p, j] + SYM[PERMS[perm[j], k], KF[p, j]]
        for v in range(m):
            c, k = first[b, v] // 3, first[b, v] % 3
            G[q, 2 * n + v] = 2 * nc + cells[CF[p, c], PERMS[perm[c], k]]
        G[q, 2 * n + m] = 2 * nc + nv + verts[p]
    return 0


@functools.lru_cache(maxsize=None)
def change_of_basis_tables():
    """The changes of RT_1 basis between a cell and its image under a vertex permutation and
    edge reflections (DESIGN §5: the translation classes, and the multilevel flux's shared
    patch operators, algebraic_flux): W (384, 8, 8) int8 (`_reference_table`), and TOP, COEF
    (384, 8, 2) int8, the (at most two) nonzero rows of each column of W and their entries
    (`_top_tables`); computed at first use."""
    W = _reference_table()
    return (W, *_top_tables(W))


def _reference_table():
    """W[(ρ' * 6 + π) * 8 + ρ] = R_ρ' M_π R_ρ (8 × 8, entries 0, ±1): R_ρ the product of
    basix's base transformations of RT_1 (degree 2) for the edges whose bit is set in ρ (each
    swaps an edge's two dofs and flips their signs), M_π the reference basis pushed forward by
    the affine map P_π with P_π(ê_i) = ê_π(i) (contravariant Piola), written in the reference
    basis: P_π*ψ̂_k = Σ_l M_π[k, l] ψ̂_l. Permutations are numbered as itertools lists them."""
    import basix
    # tests/test_algebraic_flux checks the whole construction against patch problems assembled
    # by dolfinx
    e = _rt_element()
    X = basix.make_quadrature(basix.CellType.triangle, 4)[0]
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    base = e.tabulate(0, X)[0].transpose(1, 0, 2).reshape(8, -1)          # (8, npts * 2)
    M = []
    for perm in itertools.permutations(range(3)):
        o = corners[perm[0]]
        Jp = np.stack([corners[perm[1]] - o, corners[perm[2]] - o], axis=1)
        pulled = np.linalg.solve(Jp, (X - o).T).T
        vals = np.einsum("ij,pkj->kpi", Jp, e.tabulate(0, pulled)[0]) / np.linalg.det(Jp)
        Mp = np.linalg.lstsq(base.T, vals.reshape(8, -1).T, rcond=None)[0].T
        M.append(np.round(Mp))
        if np.abs(Mp - M[-1]).max() > 1e-10:
            raise RuntimeError("RT_1 reference basis not mapped to itself by a permutation")
    T = e.base_transformations()
    R = []
    for rho in range(8):
        Rr = np.eye(8)
        for edge in range(3):
            if rho >> edge & 1:
                Rr = Rr @ T[edge]
        R.append(np.round(Rr))
    table = np.array([R[a] @ M[p] @ R[b] for a in range(8) for p in range(6) for b in range(8)])
    return table.astype(np.int8)


def _top_tables(W):
    """For every code of the table W (`change_of_basis_tables`): the rows l with W[l, k] ≠ 0
    of each column k (at most two: the dofs of one entity) and their entries, (codes, 8 (k),
    2) each (entry 0: no second row)."""
    W = W.astype(np.int64)
    top = np.argsort(-np.abs(W), axis=1, kind="stable")[:, :2, :]
    coef = np.take_along_axis(W, top, axis=1)
    if np.abs(W).sum(axis=1).max() > 2 or not np.array_equal(
            np.abs(coef).sum(axis=1), np.abs(W).sum(axis=1)):
        raise RuntimeError("RT change of basis with more than two entries per column")
    return (np.ascontiguousarray(t.transpose(0, 2, 1)).astype(np.int8) for t in (top, coef))


@functools.lru_cache(maxsize=None)
def _class_tables(slots):
    """For the change of RT basis from a class representative to a translate (W of
    `change_of_basis_tables`, indexed by (ρ_r * 6 + perm) * 8 + ρ_p): TOP, COEF (384, 8, 2), the (at
    most two) representative dofs l of the cell with W[l, k] ≠ 0 for each patch dof k, and their
    coefficients; with the patch dof k in the slot of the entity that corresponds to the
    representative dof l's entity (edge e of the patch ↦ edge pi[e] of the representative; `slots`
    as in PatchSpace) these are tabulated by u = ((ρ_r * 6 + perm) * 8 + ρ_p) * 8 + l: PATCH_DOF
    (3072,) the k, TOP, COEF (2, 3072) the rows and coefficients of column k; and EDGE_BITS (6, 8):
    a set of patch cell edges (bit e: edge e) as the set of the corresponding representative's
    edges."""
    _, W_top, W_coef = change_of_basis_tables()
    slots = np.array(slots)
    anchor = np.empty((6, 8), dtype=np.int64)
    bits = np.zeros((6, 8), dtype=np.int8)
    for code, perm in enumerate(_PERMS):                                  # perm = π, pi = π⁻¹
        pi = np.argsort(perm)
        for e in range(3):
            anchor[code, slots[e]] = slots[pi[e]]
            bits[code] += (np.arange(8) >> e & 1) << pi[e]
        anchor[code, slots[3]] = slots[3]
    # indexed by u = ((ρ_r * 6 + perm) * 8 + ρ_p) * 8 + l for the representative's dof l:
    # the patch dof k, and TOP, COEF of its column
    u = np.arange(384 * 8)
    k = np.argsort(anchor, axis=1)[u // 64 % 6, u % 8]
    return (k, np.ascontiguousarray(W_top[u // 8, k].T.astype(np.int64)),
            np.ascontiguousarray(W_coef[u // 8, k].T), bits)


class FluxEquilibration:
    """Set-up (once per mesh) and evaluation of σ_α,disc (DESIGN §5); with `owned` (a boolean
    mask over the vertices), of the part of σ_α,disc from the owned vertices' patches."""

    CHUNK = 2000     # patches solved or mapped at once (bounds the set-up's memory)
    MIN_CLASS = 3    # translated patches sharing one operator (fewer: each its own, sparse)
    TRANSLATES = True

    def __init__(self, disc, owned=None):
        self.disc = disc
        space = self.space = PatchSpace(disc.V, blocks=False)
        self.geo = geo = space.geo
        self.RT = space.RT
        self.lift = Lifting(geo)
        on_boundary = np.zeros(geo.n, dtype=bool)
        on_boundary[disc.boundary] = True
        # G_u, G_R, G_λ on the RT dofs `touched` (ascending) only: the patches solved on
        # their own touch a few thousand where the classes take all others
        self.touched = np.zeros(0, dtype=np.int64)
        self.G_u, self.G_R, self.G_lam = (sp.csr_matrix((0, geo.n)) for _ in range(3))
        # σ_f,α in column α: the layout of `sigmas`' results, which start as a copy of it
        self.sigma_f = populated_empty((space.nrt, 2), float, zero=True)
        # the cells' centroids (translation_classes) and ∂Ω edges as bits (_translates)
        self._cent = np.empty((geo.ncells, 2))
        self._exterior_bits = np.empty(geo.ncells, dtype=np.int64)
        _class_cell_data(geo.x, geo.cells, space.exterior_edge, self._cent, self._exterior_bits)
        self._scale = np.sqrt(geo.area.mean())
        self._pending = []
        # the classes' data of `sigmas`, kept between calls, and the arrays of its results
        # (membranes.kept: Estimators.sigma_disc keeps two, or none without the ν flux)
        self._class_input = None
        self._sigmas = KeptArrays(3)
        # the classes first, then the load moments and the other patches (the moments and
        # the classes' temporaries are not held at once)
        level, alone = [], []
        for verts, CS, KA in vertex_patches(geo, owned):
            b = on_boundary[verts]
            CS, KA, own = self._classes(verts, CS, KA, b, level)
            if len(own):
                alone.append((verts[own], CS[own], KA[own], b[own]))
        del self._cent, self._exterior_bits   # the classes' only
        wf, sq = load_moments(disc, geo)
        # ‖f_α - Π_P1 f_α‖_K², kept for the oscillation estimator (Estimators)
        self.projection_squares = sq
        for verts, CS, KA, b in alone:
            glob = space.retained_dofs(CS, b, KA)
            for sel, RET, loc, A in space.patch_groups(CS, b, self.CHUNK, glob):
                self._solve_patches(verts[sel], CS[sel], KA[sel], RET, loc, A, wf)
        self._add_operators()
        self._keep_touched_rows()
        self.classes = None
        if level:
            self._class_load(level, wf)
        # what the evaluation does not need goes
        del self._pending
        space.rt_cells = space.c2e = space.exterior_edge = space.reflections = None

    def _classes(self, verts, CS, KA, boundary, level):
        """The patches of P vertices (cells CS (P, n), a's local index KA) that are translates
        of one another in classes of at least MIN_CLASS (as on a uniform refinement: all but a
        few): one operator per class from the representative's patch problem (the
        representatives of one shape in one batch), and every member's data indices and
        change of basis, appended to `level` as buckets of classes of one shape and size
        (bucket, its patches' RT dofs, its load part; see algebraic_flux._apply_buckets).
        Returns CS, KA in the classes' canonical cell order and the indices of the other
        patches (each solved on its own into G_u, G_R, G_lam).

        The representative's right-hand side is a linear map of data that a translation
        carries over: ∇u_h per cell (2), r_h per cell (3), λ_a, and (set-up only) the load
        moments (f φ_a, φ_i)_K; so S = (σ rows of A_r⁻¹ times that map) and σ_p = Tᵀ S d_p for
        the patch's data d_p (the change of basis). The r_h columns are composed with the
        representative's local lifting (`local_lifting`, a translation leaves |K| alone) and
        take the values R_l / N_l at the patch's m vertices (in the representative's vertex
        order; m < 3n): the data of a patch are 2n + m + 1 numbers. ∇u_h stays per cell,
        formed from the nodal values in the evaluation: composed into the operator, its
        columns would take values of the size of u_h and cancel down to the size of ∇u_h h
        (round-off amplified by about 1/h). The members are ordered by class size and class,
        so that a bucket is a slice of each array."""
        geo, space = self.geo, self.space
        P, n = CS.shape
        CF, KF, rep, pi = translation_classes(geo.x[verts], CS, KA, boundary, geo, self._cent,
                                              self._scale, self.TRANSLATES,
                                              space.exterior_edge)
        size = np.bincount(rep, minlength=P)
        member = size[rep] >= self.MIN_CLASS
        own = np.flatnonzero(~member)
        reps = np.flatnonzero(member & (rep == np.arange(P)))
        if len(reps) == 0:
            return CF, KF, own
        glob = space.retained_dofs(CF[reps], boundary[reps], KF[reps])
        for sel, RET, loc, A in space.patch_groups(CF[reps], boundary[reps], len(reps), glob):
            nr = RET.shape[1]
            CR = CF[reps[sel]]
            S = np.linalg.solve(A, self._right_hand_sides(CR, KF[reps[sel]], nr, loc,
                                                          A.shape[1]))[:, :nr]
            _, vloc = patch_vertices(geo, CR)
            m = int(vloc.max()) + 1
            Sd = np.concatenate([S[:, :, :2 * n],
                                 S[:, :, 2 * n:5 * n] @ local_lifting(geo, CR, vloc, m, False),
                                 S[:, :, 5 * n:5 * n + 1]], axis=2)         # (g, nr, 2n+m+1)
            # each representative's vertex v at its first (cell, slot) c_v, k_v
            first = np.empty((len(sel), m), dtype=np.int64)
            for j in range(3 * n - 1, -1, -1):
                first[np.arange(len(sel)), vloc.reshape(len(sel), -1)[:, j]] = j
            batch = np.full(P, -1)
            batch[reps[sel]] = np.arange(len(sel))
            mem = np.flatnonzero(member & (batch[rep] >= 0))
            mem = mem[np.lexsort((rep[mem], size[rep[mem]]))]
            Pm = len(mem)
            RETm = populated_empty((Pm, nr), np.int32)
            L = populated_empty((Pm, nr, 2), _local_index_type(nr))
            C = populated_empty((Pm, nr, 2), np.int8)
            G = populated_empty((Pm, 2 * n + m + 1), self._index_type())
            GF = populated_empty((Pm, 3 * n), G.dtype)
            tables = self._representatives(CR, loc)
            self._translates(mem, batch[rep], CF, KF, pi, boundary, verts, tables,
                             first, (RETm, L, C, G, GF))
            # buckets: the classes of one size, each its members in a row
            csize = size[rep[mem]]
            cuts = np.concatenate([[0], np.flatnonzero(np.diff(csize)) + 1, [Pm]])
            for s, e in zip(cuts[:-1], cuts[1:]):
                b = batch[rep[mem[s:e:csize[s]]]]
                level.append(((Sd[b], G[s:e], L[s:e], C[s:e]), RETm[s:e].ravel(),
                              (S[b, :, 5 * n + 1:], GF[s:e], L[s:e], C[s:e])))
        return CF, KF, own

    def _representatives(self, CR, loc):
        """What the members' changes of basis take from g representatives (cells CR (g, n),
        local numbers of their RT dofs loc (g, n, 8), -1 dropped): for each local dof i the
        (last) cell c and slot l that hold it, as c (g, nr), 8 (b n + c) (b the
        representative's number) and 384 ρ + l (ρ the cell's edge reflections); the kept
        edges of each cell as bits (g, n); and loc."""
        g, n = CR.shape
        flat = loc.reshape(g, -1)
        nr = int(flat.max()) + 1
        at = np.full((g, nr), -1, dtype=np.int64)
        rows, cols = np.nonzero(flat >= 0)
        np.maximum.at(at, (rows, flat[rows, cols]), cols)
        cell = at // 8
        edges = sum((loc[:, :, self.space.slots[e][0]] >= 0).astype(np.int8) << e
                    for e in range(3))
        refl = self.space.reflections[np.take_along_axis(CR, cell, axis=1)]
        return (cell, 8 * (np.arange(g)[:, None] * n + cell), 384 * refl + at % 8, edges,
                loc.reshape(-1))

    def _translates(self, mem, bi, CF, KF, pi, boundary, verts, tables, first, out):
        """For the members mem of classes (cells CF in canonical order, KF a's local index,
        pi the vertex matches from `translation_classes`; patch p's representative is number
        bi[p] in the representatives' `tables`, `_representatives`), with first (g, m) the first
        (cell, slot) 3 c + k of each representative vertex: into out = (RET, L, C, G, GF),
        row q for member mem[q], the retained global dofs RET (nr,) in the representative's
        local order, the change of basis L, C (nr, 2): σ_p[i] = Σ_t C[i, t] σ_r[L[i, t]], and
        where the patch's data sit (in the representative's cell and vertex order) in the
        flat array [∇u_h (2 per cell) | R_l / N_l (per vertex) | λ (per vertex)], G
        (2n + m + 1,), then in the flat array of (f φ_k, φ_i)_K (6 per cell, `load_moments`),
        GF (3n,).

        With F_K the affine map of a cell K in its dolfinx vertex order and R_K its edge
        reflections, the local RT basis is R_K F_K*ψ̂; the representative's cell K' = K + shift
        has F_K' = shift ∘ F_K ∘ P_π, hence its basis is W = R_K' M_π R_K times K's
        (`change_of_basis_tables`, entries 0, ±1, at most two per column: the dofs of one
        entity). The representative's local dof i, in slot l of its cell c, is the patch's dof
        in the same slot of the corresponding entity of cell c (one number per global dof: a
        dof has one slot in every cell that has its entity); each cell's kept edges are checked
        against the representative's (the rule of `PatchSpace.retained_dofs`). Vertex i' of
        the representative's cell c is vertex _PERMS[π][i'] of the patch's. One compiled loop
        over the patches in their order (their cells are near one another in memory), each
        member's rows written where mem puts them (`_member_maps`)."""
        space = self.space
        PATCH_DOF, TOP, COEF, EDGE_BITS = _class_tables(tuple(map(tuple, space.slots)))
        row = np.full(len(CF), -1)
        row[mem] = np.arange(len(mem))
        status = _member_maps(row, bi, CF, KF, pi, boundary, verts, self._exterior_bits,
                              space.reflections, space.rt_cells, self.geo.cells, *tables,
                              first, PATCH_DOF, TOP, COEF, EDGE_BITS, _PERMS, _SYM,
                              self.geo.ncells, self.geo.n, *out)
        if status == 1:
            raise RuntimeError("a translate keeps other RT dofs than its representative")
        if status == 2:
            raise RuntimeError("a retained dof of a translate maps to a dropped one")

    def _index_type(self):
        return np.int32 if 14 * self.geo.ncells + self.geo.n < 2 ** 31 else np.int64

    def _class_load(self, level, wf):
        """Keep the classes' operators as the evaluation takes them (`classes`: buckets, RT
        dofs; algebraic_flux._apply_buckets applies them, their changes of basis and the
        scatter at every call), and add the classes' σ_f from the load columns the same way;
        the load columns are then dropped. Both membranes' loads in one pass (their moments
        side by side as `load_moments` keeps them: each σ_f,α the same to the bit as alone,
        `_apply_buckets`)."""
        from .algebraic_flux import _apply_buckets
        ret = [r for _, r, _ in level]                  # per bucket: no copy of them all
        self.classes = ([b for b, _, _ in level], ret)
        load = ([f for _, _, f in level], ret)
        level.clear()
        _apply_buckets(load, wf.reshape(-1, 2), len(self.sigma_f), self.sigma_f)

    def _right_hand_sides(self, CS, KA, nr, loc, N):
        """The right-hand sides of P patch problems of one shape (cells CS (P, n), a's local
        index KA, local numbers loc of the retained dofs, nr of them, N unknowns) as linear
        maps of cell data, (P, N, 8n + 1): columns ∇u_h on each cell (2n) | r_h on each cell
        (3n, in the cell's vertex order) | λ_a | (ψ_a f, q_i)_K (3n). Rows: -(ψ_a ∇u_h, τ)
        for the retained τ, then (g̃_a, q_i)_K = (ψ_a (f ± λ_a - r_h), q_i)_K
        - (∇u_h·∇ψ_a, q_i)_K with exact P1 products; μ_α and ± are applied to the data."""
        geo = self.geo
        P, n = CS.shape
        nq = 3 * n
        rhs = np.zeros((P, N, 8 * n + 1))
        pp = np.arange(P)[:, None, None]
        jj = np.arange(n)[None, :, None]
        area = geo.area[CS]                                                   # (P, n)
        dcols = 2 * jj[..., None] + np.arange(2)                              # (1, n, 1, 2)
        Ce = self.space.vector_moments(CS.ravel()).reshape(P, n, 8, 3, 2)
        Cka = np.take_along_axis(Ce, KA[:, :, None, None, None], axis=3)[:, :, :, 0]
        ok = np.broadcast_to(loc[..., None] >= 0, Cka.shape)
        rhs[np.broadcast_to(pp[..., None], Cka.shape)[ok],
            np.broadcast_to(loc[..., None], Cka.shape)[ok],
            np.broadcast_to(dcols, Cka.shape)[ok]] = -Cka[ok]
        qrow = nr + 3 * jj + np.arange(3)                                     # (1, n, 3)
        gka = geo.grad[CS, KA]                                                # ∇ψ_a (P, n, 2)
        rhs[pp[..., None], qrow[..., None], dcols] = \
            -(area / 3.0)[..., None, None] * gka[:, :, None, :]
        rcols = 2 * n + 3 * jj + np.arange(3)                                 # (1, n, 3)
        rhs[pp[..., None], qrow[..., None], rcols[:, :, None, :]] = \
            -area[..., None, None] * _C3[KA].transpose(0, 1, 3, 2)            # [i, l]
        delta = np.arange(3) == KA[..., None]
        rhs[pp, qrow, 5 * n] = area[..., None] / 12.0 * (1.0 + delta)
        rhs[:, nr:nr + nq, 5 * n + 1:] = np.eye(nq)
        return rhs

    def _solve_patches(self, verts, CS, KA, RET, loc, A, wf):
        """P patch problems of one shape, with their right-hand sides composed with the local
        gradient and lifting operators (vertex data), solved by batched LAPACK: adds the
        patches' σ_a to the operators."""
        geo = self.geo
        P, n = CS.shape
        nr, N = RET.shape[1], A.shape[1]
        VERTS, vloc = patch_vertices(geo, CS)                                  # (P, m)
        m = VERTS.shape[1]
        nq = 3 * n
        pp = np.arange(P)[:, None, None]
        # local gradient (P, 2n, m) and lifting (P, 3n, m) operators
        Gd = np.zeros((P, 2 * n, m))
        rows = 2 * np.arange(n)[None, :, None, None] + np.arange(2)           # (1, n, 1, 2)
        Gd[pp[..., None], rows, vloc[..., None]] = geo.grad[CS]
        Lr = local_lifting(geo, CS, vloc, m)
        cell = self._right_hand_sides(CS, KA, nr, loc, N)
        # columns u (m) | λ_a (1) | R (m) | f1 | f2
        ik = _SYM[np.arange(3), KA[:, :, None]]                               # (P, n, 3)
        load = [wf[CS[:, :, None], ik, alpha].reshape(P, nq, 1) for alpha in range(2)]
        rhs = np.concatenate([cell[:, :, :2 * n] @ Gd, cell[:, :, 5 * n:5 * n + 1],
                              cell[:, :, 2 * n:5 * n] @ Lr]
                             + [cell[:, :, 5 * n + 1:] @ w for w in load], axis=2)
        del cell
        sol = np.linalg.solve(A, rhs)[:, :nr]                                 # σ rows
        # σ = Σ_a σ_a: this batch's operator entries, added to G_u, G_R, G_λ a few batches
        # at a time (`_add_operators`: few sparse sums, bounded memory)
        rows = np.broadcast_to(RET[:, :, None], (P, nr, m)).ravel().astype(np.int32)
        cols = np.broadcast_to(VERTS[:, None, :], (P, nr, m)).ravel().astype(np.int32)
        self._pending.append((rows, cols, sol[:, :, :m].ravel(),
                              sol[:, :, m + 1:2 * m + 1].ravel(), RET.ravel().astype(np.int32),
                              np.repeat(verts, nr).astype(np.int32), sol[:, :, m].ravel()))
        if sum(len(z[0]) for z in self._pending) > 1 << 22:
            self._add_operators()
        # σ_f: the sums over this batch's patches of each RT dof they touch (numbered among
        # those: no pass over all RT dofs per batch)
        dofs, at = np.unique(RET, return_inverse=True)
        for alpha in range(2):
            self.sigma_f[dofs, alpha] += np.bincount(at.ravel(),
                                                     sol[:, :, 2 * m + 1 + alpha].ravel())

    def _add_operators(self):
        """Add the pending batches of `_solve_patches` to G_u, G_R, G_λ, kept on the rows of
        the RT dofs they touch (`touched`): the sums and the new batches are put on the union
        of their dofs (moving rows: no entry changes) and added as scipy adds them, row by
        row, so that no pass goes over all RT dofs (the same entries as sums of matrices of
        all RT dofs' rows)."""
        if not self._pending:
            return
        rows, cols, u, R, rows_lam, cols_lam, lam = (np.concatenate(z)
                                                     for z in zip(*self._pending))
        self._pending.clear()
        union = np.union1d(self.touched, np.union1d(rows, rows_lam))
        shape = (len(union), self.geo.n)

        def moved(G):
            indptr = np.zeros(len(union) + 1, dtype=G.indptr.dtype)
            indptr[1 + np.searchsorted(union, self.touched)] = np.diff(G.indptr)
            return sp.csr_matrix((G.data, G.indices, np.cumsum(indptr, out=indptr)),
                                 shape=shape)

        at, at_lam = np.searchsorted(union, rows), np.searchsorted(union, rows_lam)
        self.G_u = moved(self.G_u) + sp.csr_matrix((u, (at, cols)), shape=shape)
        self.G_R = moved(self.G_R) + sp.csr_matrix((R, (at, cols)), shape=shape)
        self.G_lam = moved(self.G_lam) + sp.csr_matrix((lam, (at_lam, cols_lam)), shape=shape)
        self.touched = union

    def _keep_touched_rows(self):
        """Keep of G_u, G_R, G_λ the rows with entries (the sums drop exact zeros), so that an
        evaluation makes no vectors of all RT dofs for them."""
        keep = np.zeros(len(self.touched), dtype=bool)
        for G in (self.G_u, self.G_R, self.G_lam):
            keep |= np.diff(G.indptr) > 0
        self.touched = self.touched[keep]
        self.G_u, self.G_R, self.G_lam = (G[keep] for G in (self.G_u, self.G_R, self.G_lam))

    def sigma(self, alpha, u, lam, R):
        """RT_1 coefficients of σ_α,disc for membrane α ∈ {1, 2} (DESIGN §5): `sigmas` for
        one membrane."""
        return self.sigmas([(alpha, u, R)], lam)[0]

    def sigmas(self, fields, lam, pool=None):
        """[σ_α,disc for (α, u, R) in fields] (RT_1 coefficients, DESIGN §5), the membranes
        together: σ_f,α, plus the classes' part: `algebraic_flux._apply_buckets` on the data
        [μ_α ∇u_h per cell | R_l / N_l per vertex | ±λ] of all fields side by side
        (`_class_data`, compiled, into a buffer kept between evaluations), with the changes of
        basis kept by the set-up, added to the result in place; plus μ_α G_u u ± G_λ λ + G_R R
        on the rows of the patches solved on their own. The σ are the columns of one array
        (RT dofs × fields, as the classes' scatter writes them: the fields of a dof side by
        side), which starts as a copy of σ_f (one pass; no array of all RT dofs besides the
        result is allocated or cleared per call); each σ the same to the bit as alone. With
        `pool` (an executor whose thread is spare) the classes' products and scatters run as
        a pipeline of two: the same numbers."""
        p = self.disc.problem
        mus = np.array([p.mu1 if alpha == 1 else p.mu2 for alpha, _, _ in fields])
        signs = np.array([1.0 if alpha == 1 else -1.0 for alpha, _, _ in fields])
        which = [alpha - 1 for alpha, _, _ in fields]
        k, size = len(fields), len(self.sigma_f)
        out = self._sigmas.empty((size, k))
        if which == [0, 1]:
            np.copyto(out, self.sigma_f)
        else:
            for f, alpha in enumerate(which):
                out[:, f] = self.sigma_f[:, alpha]
        if self.classes is not None:
            from .algebraic_flux import _apply_buckets
            geo = self.geo
            if self._class_input is None or self._class_input.shape[1] != k:
                self._class_input = populated_empty((2 * geo.ncells + 2 * len(lam), k), float)
            data = self._class_input                  # every entry written by _class_data
            given = any(R is not None for _, _, R in fields)
            Rs = np.array([np.zeros(len(lam)) if R is None else R for _, _, R in fields]
                          if given else np.zeros((len(fields), 0)))
            _class_data(geo.cells, geo.grad, geo.cells_per_vertex, mus, signs,
                        np.array([u for _, u, _ in fields]), lam, Rs, data)
            _apply_buckets(self.classes, data, size, out, pool)
        rows = self.touched
        for f, (alpha, u, R) in enumerate(fields):
            at = mus[f] * (self.G_u @ u) + signs[f] * (self.G_lam @ lam)
            if R is not None:
                at += self.G_R @ R
            out[rows, f] += at
        return [out[:, f] for f in range(k)]


@kernel
def _class_data(cells, grad, cpv, mus, signs, U, lam, R, data):
    """The classes' data of FluxEquilibration.sigmas, field f in column f of data: μ_f ∇u_h
    on every cell (two entries), R_l / N_l at every vertex (0 where R has no columns), ±λ."""
    nc, nv, k = cells.shape[0], len(lam), U.shape[0]
    for c in range(nc):
        for f in range(k):
            g0, g1 = cell_gradient(grad, c, U[f, cells[c, 0]], U[f, cells[c, 1]],
                                   U[f, cells[c, 2]])
            data[2 * c, f] = mus[f] * g0
            data[2 * c + 1, f] = mus[f] * g1
    for v in range(nv):
        for f in range(k):
            data[2 * nc + v, f] = R[f, v] / cpv[v] if R.shape[1] else 0.0
            data[2 * nc + nv + v, f] = signs[f] * lam[v]
