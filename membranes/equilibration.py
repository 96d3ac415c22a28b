"""Residual liftings (DESIGN §4) and the discretisation flux σ_α,disc (DESIGN §5).

## Residual lifting

An algebraic residual R_α (nodal, zero at Dirichlet vertices) is lifted to r_αh, discontinuous
P1: on each cell K with vertices a_l, (r_αh, ψ_{a_l})_K = R_{α,l} / N_l, N_l the number of cells
sharing a_l. With the P1 mass matrix M_K = |K|/12 [[2,1,1],[1,2,1],[1,1,2]] this is
r_K = M_K⁻¹ (R_l / N_l)_l = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]] (R_l / N_l)_l, the sparse
operator `lifting` below (DG1 coefficients, in the cell's vertex order).

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

The patch matrices depend on the mesh only. They are the global RT_1 × DG1 matrices assembled
by dolfinx (forms.equilibration) restricted to each patch's dofs: every cell that touches a
retained dof of the patch lies in the patch, so the restriction is exact. Since σ_a is linear in
the data, the set-up solves every patch problem once for the *operators*

    σ_α,disc = μ_α G_u u_α ± G_λ λ + G_R R_α + σ_f,α

(G_u, G_λ, G_R sparse, σ_f,α a fixed vector): one evaluation is three sparse products, O(N).
Where many patches are translates of one another (a uniform refinement: all but a few, in about
#vertices + #edges + #cells of T_0 classes) the operators are not assembled: each class keeps
one dense operator from cell data (∇u_h, r_h, λ_a) to σ_a, computed for a representative, and
each patch its data indices and change of RT basis (entries 0, ±1; algebraic_flux); one
evaluation is then a gather, one batched product per stack of classes and one scatter. The other
patches keep the sparse operators.
The right-hand sides use exact integrals of P1 products on each cell; only (ψ_a f_α, q) needs
quadrature (the scene's data measures).
"""

import numpy as np
import scipy.sparse as sp
import ufl

from forms.equilibration import divergence, rt_mass, vector_moment, weighted_mass

from .discretisation import assemble_matrix_csr, load, over

# ∫_K φ_k φ_l φ_i / |K| for barycentric φ: 1/10 (k = l = i), 1/30 (two equal), 1/60 (distinct)
_C3 = np.empty((3, 3, 3))
for _k in range(3):
    for _l in range(3):
        for _i in range(3):
            _C3[_k, _l, _i] = {1: 1 / 10, 2: 1 / 30, 3: 1 / 60}[len({_k, _l, _i})]
_MINV_REF = np.array([[3.0, -1.0, -1.0], [-1.0, 3.0, -1.0], [-1.0, -1.0, 3.0]])


class Geometry:
    """Cells as P1 dof triples, areas, barycentric gradients, and vertex-to-cell incidence."""

    def __init__(self, V):
        mesh = V.mesh
        self.V = V
        self.ncells = mesh.topology.index_map(2).size_local
        self.cells = V.dofmap.list.array.reshape(-1, 3)[:self.ncells].astype(np.int64)
        self.n = V.dofmap.index_map.size_local
        self.x = x = V.tabulate_dof_coordinates()[:, :2]
        p = x[self.cells]                                     # (ncells, 3, 2)
        e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        self.area = 0.5 * np.abs(det)
        # ∇φ_k: rows of the inverse Jacobian transpose applied to reference gradients
        jinv = np.empty((self.ncells, 2, 2))
        jinv[:, 0, 0], jinv[:, 0, 1] = e2[:, 1] / det, -e2[:, 0] / det
        jinv[:, 1, 0], jinv[:, 1, 1] = -e1[:, 1] / det, e1[:, 0] / det
        ref = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
        self.grad = np.einsum("kr,crd->ckd", ref, jinv)       # (ncells, 3, 2)
        self.cells_per_vertex = np.bincount(self.cells.ravel(), minlength=self.n)
        order = np.argsort(self.cells.ravel(), kind="stable")
        self.vertex_cells = order // 3                         # cells sorted by vertex
        self.vertex_local = order % 3                          # local index of the vertex
        self.vertex_ptr = np.concatenate([[0], np.cumsum(self.cells_per_vertex)])

    def gradient(self, u):
        """∇u_h per cell, shape (ncells, 2), for nodal P1 values u."""
        return np.einsum("ck,ckd->cd", u[self.cells], self.grad)


def lifting(geo):
    """The sparse operator R ↦ r_h (DG1 coefficients, 3 per cell in vertex order), DESIGN §4."""
    rows = np.repeat(np.arange(3 * geo.ncells), 3)
    cols = np.repeat(geo.cells, 3, axis=0).ravel()
    scale = (3.0 / geo.area)[:, None, None] * _MINV_REF[None] \
        / geo.cells_per_vertex[geo.cells][:, None, :]
    return sp.csr_matrix((scale.ravel(), (rows, cols)), shape=(3 * geo.ncells, geo.n))


def csr_lookup(A, rows, cols, chunk=1 << 22):
    """Entries A[rows[i], cols[i]] of a CSR matrix (0 where not stored), vectorised (queries
    are processed in chunks to bound the temporaries)."""
    A = A.tocsr()
    A.sort_indices()
    ncols = np.int64(A.shape[1])
    keys = np.repeat(np.arange(A.shape[0], dtype=np.int64), np.diff(A.indptr)) * ncols \
        + A.indices
    out = np.empty(len(rows))
    for s in range(0, len(rows), chunk):
        q = np.asarray(rows[s:s + chunk], dtype=np.int64) * ncols + cols[s:s + chunk]
        pos = np.minimum(np.searchsorted(keys, q), keys.size - 1)
        out[s:s + chunk] = np.where(keys[pos] == q, A.data[pos], 0.0)
    return out


def element_blocks(A, row_dofs, col_dofs):
    """Blocks A[row_dofs[K]][:, col_dofs[K]] for every cell K, shape (ncells, r, c)."""
    nc, r = row_dofs.shape
    c = col_dofs.shape[1]
    rows = np.broadcast_to(row_dofs[:, :, None], (nc, r, c)).ravel()
    cols = np.broadcast_to(col_dofs[:, None, :], (nc, r, c)).ravel()
    return csr_lookup(A, rows, cols).reshape(nc, r, c)


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


def cell_colouring(mesh, ncells, seed=0):
    """Colours of the cells such that cells sharing an edge differ (at most 4)."""
    mesh.topology.create_connectivity(1, 2)
    e2c = mesh.topology.connectivity(1, 2)
    counts = np.diff(e2c.offsets)
    pairs = e2c.array[np.repeat(counts == 2, counts)].reshape(-1, 2)
    return graph_colouring(pairs[(pairs < ncells).all(axis=1)].astype(np.int64), ncells, seed)


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


class PatchSpace:
    """RT_1 × DG1 on one mesh, with the per-cell blocks that every patch problem is made of:
    Me[K] = (φ_j, φ_i)_K (RT mass) and Be[K] = (∇·φ_j, q_i)_K, in the global RT basis (dof
    transformations applied by dolfinx). B has cell-owned rows, so its blocks are entries of
    one assembly; M is assembled colour by colour over cells that share no edge, so that each
    entry of one colour's assembly belongs to one cell (integrating over one colour only also
    keeps each sparsity pattern small). The assembled matrices are temporaries."""

    def __init__(self, V, blocks=True):
        from dolfinx import fem, mesh as dmesh
        mesh = V.mesh
        self.V = V
        self.geo = geo = Geometry(V)
        nc = geo.ncells
        self.RT = fem.FunctionSpace(mesh, ("RT", 2))
        self.DG = fem.FunctionSpace(mesh, ("DG", 1))
        self.rt_cells = self.RT.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        self.dg_cells = dg = self.DG.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        _check_vertex_order(self.DG, dg, V, geo.cells)
        if blocks:
            self.Me, self.Be = self.element_blocks(np.arange(nc))
        # edge e of a cell is opposite its vertex e (basix); which RT dofs sit on which edge
        layout = self.RT.dofmap.dof_layout
        self.edge_of_dof = np.full(8, -1)
        for e in range(3):
            self.edge_of_dof[layout.entity_dofs(1, e)] = e
        mesh.topology.create_connectivity(2, 1)
        self.c2e = mesh.topology.connectivity(2, 1).array.reshape(nc, 3).astype(np.int64)
        nedges = mesh.topology.index_map(1).size_local + mesh.topology.index_map(1).num_ghosts
        exterior = np.zeros(nedges, dtype=bool)
        exterior[dmesh.exterior_facet_indices(mesh.topology)] = True
        self.exterior_edge = exterior[self.c2e]
        self.nrt = self.RT.dofmap.index_map.size_local
        # the edge reflections of every cell (bit e: edge e), which the RT basis carries
        mesh.topology.create_entity_permutations()
        self.reflections = (np.asarray(mesh.topology.get_cell_permutation_info())[:nc]
                            & 7).astype(np.int64)

    def element_blocks(self, cells):
        """(Me, Be) of the given cells (distinct indices): Me (c, 8, 8), Be (c, 3, 8). Only
        these cells are integrated (a cell tag per colour of cells sharing no edge), so a
        subset costs in proportion to its size."""
        from dolfinx import mesh as dmesh
        mesh = self.V.mesh
        cells = np.asarray(cells, dtype=np.int64)
        sig, tau = ufl.TrialFunction(self.RT), ufl.TestFunction(self.RT)
        q = ufl.TestFunction(self.DG)
        Me, Be = np.empty((len(cells), 8, 8)), np.empty((len(cells), 3, 8))
        if len(cells) == 0:
            return Me, Be
        colour = self._colour()[cells]
        for c in np.unique(colour):
            sel = np.flatnonzero(colour == c)
            tagged = cells[sel].astype(np.int32)
            order = np.argsort(tagged)
            tags = dmesh.meshtags(mesh, 2, tagged[order], np.ones_like(tagged))
            dxc = ufl.Measure("dx", domain=mesh, subdomain_data=tags)(1)
            rt, dg = self.rt_cells[cells[sel]], self.dg_cells[cells[sel]]
            Me[sel] = element_blocks(assemble_matrix_csr(rt_mass(sig, tau, dxc)), rt, rt)
            Be[sel] = element_blocks(assemble_matrix_csr(divergence(sig, q, dxc)), dg, rt)
        return Me, Be

    def _colour(self):
        if getattr(self, "_cell_colour", None) is None:
            self._cell_colour = cell_colouring(self.V.mesh, self.geo.ncells)
        return self._cell_colour

    def retained_dofs(self, CS, boundary):
        """Global RT dofs of P patches of the cells CS (P, n) (-1 where dropped): V_h^a has zero
        normal component on the patch boundary (edges in one patch cell only), except on ∂Ω
        for a patch of a boundary vertex (DESIGN §5; `boundary` (P,) flags those)."""
        P, n = CS.shape
        edges = self.c2e[CS].reshape(P, -1)
        big = np.int64(edges.max() + 1)
        keys = edges + np.arange(P, dtype=np.int64)[:, None] * big
        srt = np.sort(keys, axis=1)
        twice = srt[:, 1:][srt[:, 1:] == srt[:, :-1]]
        inside = np.isin(keys, twice).reshape(P, n, 3)
        keep_edge = inside | (self.exterior_edge[CS] & boundary[:, None, None])
        e = self.edge_of_dof
        keep = np.where(e[None, None, :] >= 0, np.take(keep_edge, np.maximum(e, 0), axis=2),
                        True)
        return np.where(keep, self.rt_cells[CS], -1).reshape(P, -1)

    def saddle_point_systems(self, CS, glob, boundary, blocks=None):
        """Local numbering and matrices of P patch problems of one shape (DESIGN §5):
        A = [[M, -Bᵀ, 0], [B, 0, c], [0, cᵀ, 0]] with the zero-mean multiplier row (c = (1, q))
        for interior patches only. Returns RET (P, nr) the global RT dofs, loc (P, n, 8) their
        local numbers (-1 dropped) and A (P, N, N), N = nr + 3n (+ 1). `blocks`: (Me, Be) of
        the cells CS, shapes (P, n, 8, 8) and (P, n, 3, 8), where the space keeps none."""
        geo = self.geo
        P, n = CS.shape
        sentinel = np.iinfo(np.int64).max
        RET, _ = _row_unique(np.where(glob < 0, sentinel, glob), sentinel)    # (P, nr)
        nr = RET.shape[1]
        loc = np.where(glob < 0, -1, _row_index(RET, np.maximum(glob, 0))).reshape(P, n, 8)
        nq = 3 * n
        N = nr + nq + (0 if boundary else 1)
        A = np.zeros((P, N, N))
        li, lj = loc[:, :, :, None], loc[:, :, None, :]
        ok = (li >= 0) & (lj >= 0)
        lin = (np.arange(P)[:, None, None, None] * N + li) * N + lj
        Me, Be = (self.Me[CS], self.Be[CS]) if blocks is None else blocks
        A.ravel()[:] += np.bincount(lin[ok], weights=Me[ok], minlength=P * N * N)
        qrow = nr + 3 * np.arange(n)[None, :, None] + np.arange(3)[None, None, :]
        okb = np.broadcast_to(loc[:, :, None, :] >= 0, Be.shape)
        pb = np.broadcast_to(np.arange(P)[:, None, None, None], Be.shape)
        rb = np.broadcast_to(qrow[..., None], Be.shape)
        cb = np.broadcast_to(loc[:, :, None, :], Be.shape)
        A[pb[okb], rb[okb], cb[okb]] = Be[okb]
        A[pb[okb], cb[okb], rb[okb]] = -Be[okb]
        if not boundary:
            c = np.repeat(geo.area[CS] / 3.0, 3, axis=1)                     # (P, nq)
            A[:, nr:nr + nq, -1] = c
            A[:, -1, nr:nr + nq] = c
        return RET, loc, A

    def patch_groups(self, CS, boundary, chunk):
        """Patches (cells CS (P, n), boundary flags) in batches of one shape: yields
        (indices into the P patches, RET, loc, A)."""
        glob = self.retained_dofs(CS, boundary)
        S = np.sort(np.where(glob < 0, np.iinfo(np.int64).max, glob), axis=1)
        nr = ((S[:, 1:] != S[:, :-1]) & (S[:, 1:] != np.iinfo(np.int64).max)).sum(axis=1) + 1
        for b, r in sorted(set(zip(boundary.tolist(), nr.tolist()))):
            idx = np.flatnonzero((boundary == b) & (nr == r))
            for s in range(0, len(idx), chunk):
                sel = idx[s:s + chunk]
                yield (sel,) + self.saddle_point_systems(CS[sel], glob[sel], b)


def vertex_patches(geo):
    """For every vertex a: its cells (grouped by count) and a's local index in each.
    Yields (vertices (P,), CS (P, n), KA (P, n))."""
    for n in np.unique(geo.cells_per_vertex):
        verts = np.flatnonzero(geo.cells_per_vertex == n)
        idx = geo.vertex_ptr[verts][:, None] + np.arange(n)
        yield verts, geo.vertex_cells[idx], geo.vertex_local[idx]


def _check_vertex_order(DG, dg_cells, V, p1_cells):
    """The local formulas assume the DG1 and P1 dofs of a cell sit at its vertices in the same
    order (basix's reference vertex order); check it rather than trust it."""
    xd = DG.tabulate_dof_coordinates()[:, :2][dg_cells]
    xp = V.tabulate_dof_coordinates()[:, :2][p1_cells]
    if not np.allclose(xd, xp, rtol=0, atol=1e-12 * max(1.0, np.abs(xp).max())):
        raise RuntimeError("DG1 and P1 dofs are not in the same cell vertex order")


class FluxEquilibration:
    """Set-up (once per mesh) and evaluation of σ_α,disc (DESIGN §5)."""

    CHUNK = 8000     # patches solved at once (bounds the set-up's memory)
    MIN_CLASS = 3    # translated patches sharing one operator (fewer: each its own, sparse)
    TRANSLATES = True

    def __init__(self, disc):
        from dolfinx import fem
        self.disc = disc
        mesh = disc.V.mesh
        space = self.space = PatchSpace(disc.V)
        self.geo, self.RT = space.geo, space.RT
        nc = self.geo.ncells
        self.lift = lifting(self.geo)
        tau = ufl.TestFunction(self.RT)
        W = fem.VectorFunctionSpace(mesh, ("DG", 1))
        wc = W.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        wcols = (2 * wc[:, :, None] + np.arange(2)).reshape(nc, 6)          # (k, d) -> 2k + d
        self.Ce = element_blocks(assemble_matrix_csr(vector_moment(ufl.TrialFunction(W), tau)),
                                 space.rt_cells, wcols)                     # ∫_K φ_k e_d · τ_j
        # Wf_α[K][i, k] = (f_α φ_k, φ_i)_K
        p, q = ufl.TrialFunction(space.DG), ufl.TestFunction(space.DG)
        self.wf = [element_blocks(assemble_matrix_csr(over(
            disc.dx_data, lambda dx: weighted_mass(load(f, mesh), p, q, dx))),
            space.dg_cells, space.dg_cells) for f in (disc.problem.f1, disc.problem.f2)]
        on_boundary = np.zeros(self.geo.n, dtype=bool)
        on_boundary[disc.boundary] = True
        shape = (space.nrt, self.geo.n)
        self.G_u, self.G_R, self.G_lam = (sp.csr_matrix(shape) for _ in range(3))
        self.sigma_f = np.zeros((2, space.nrt))
        groups = []
        for verts, CS, KA in vertex_patches(self.geo):
            own = self._classes(verts, CS, KA, on_boundary[verts], groups)
            if len(own) == 0:
                continue
            verts, CS, KA = verts[own], CS[own], KA[own]
            for sel, RET, loc, A in space.patch_groups(CS, on_boundary[verts], self.CHUNK):
                self._solve_patches(verts[sel], CS[sel], KA[sel], RET, loc, A)
        from .algebraic_flux import _buckets
        self.classes = _buckets(groups) if groups else None
        # what the evaluation does not need goes: the element blocks and the load moments
        # (kept summed, (f_α, φ_i)_K, for the oscillation estimator)
        self.load = [wf.sum(axis=2) for wf in self.wf]
        del self.Ce, self.wf
        space.Me = space.Be = None

    def _classes(self, verts, CS, KA, boundary, groups):
        """The patches of P vertices (cells CS (P, n), a's local index KA) that are translates
        of one another in classes of at least MIN_CLASS (as on a uniform refinement: all but a
        few): one operator per class, from the representative's patch problem, appended to
        `groups` as (S, G, RET, L, C) (see algebraic_flux._buckets), their σ_f added. Returns
        the indices of the other patches (each solved on its own into G_u, G_R, G_lam).

        The representative's right-hand side is a linear map of cell data that a translation
        carries over: ∇u_h per cell (2), r_h per cell (3, its vertices permuted by π), λ_a, and
        (set-up only) the load moments (f φ_a, φ_i)_K; so S = (σ rows of A_r⁻¹ times that map)
        and σ_p = Tᵀ S d_p for the patch's data d_p (change_of_basis)."""
        from .algebraic_flux import change_of_basis, class_members, translation_classes
        geo, space = self.geo, self.space
        P, n = CS.shape
        cent = geo.x[geo.cells].mean(axis=1)
        scale = np.sqrt(geo.area.mean())
        CF, KF, rep, pi = translation_classes(geo.x[verts], CS, KA, boundary, geo, cent, scale,
                                              self.TRANSLATES, space.exterior_edge)
        own = []
        nc = geo.ncells
        for members in class_members(rep):
            if len(members) < self.MIN_CLASS:
                own.append(members)
                continue
            cf, kf, pc = CF[members], KF[members], pi[members]
            b = bool(boundary[members[0]])
            r = int(np.flatnonzero(rep[members] == members)[0])
            glob, RET, loc, L, C = change_of_basis(space, cf, pc, r, b)
            nr, nq = RET.shape[1], 3 * n
            _, _, A = space.saddle_point_systems(cf[r:r + 1], glob[r:r + 1], b)
            # the representative's right-hand side: columns ∇u (2n) | r (3n) | λ_a | f (3n)
            cr, ka, lr = cf[r], kf[r], loc[r]
            area = geo.area[cr]
            rhs = np.zeros((A.shape[1], 8 * n + 1))
            cols = 2 * np.arange(n)[:, None] + np.arange(2)                   # (n, 2)
            Cka = np.take_along_axis(self.Ce[cr], (2 * ka[:, None] + np.arange(2))[:, None, :],
                                     axis=2)                                  # (n, 8, 2)
            ok = lr >= 0
            cc = np.broadcast_to(cols[:, None, :], Cka.shape)
            rr = np.broadcast_to(lr[:, :, None], Cka.shape)
            okc = np.broadcast_to(ok[:, :, None], Cka.shape)
            rhs[rr[okc], cc[okc]] = -Cka[okc]
            qrow = nr + 3 * np.arange(n)[:, None] + np.arange(3)              # (n, 3)
            gka = geo.grad[cr, ka]                                            # ∇ψ_a (n, 2)
            rhs[qrow[:, :, None], cols[:, None, :]] = \
                -(area / 3.0)[:, None, None] * gka[:, None, :]
            rcols = 2 * n + 3 * np.arange(n)[:, None] + np.arange(3)          # (n, 3)
            rhs[qrow[:, :, None], rcols[:, None, :]] = \
                -area[:, None, None] * _C3[ka].transpose(0, 2, 1)             # [i, l]
            rhs[qrow, 5 * n] = area[:, None] / 12.0 * (1.0 + (np.arange(3) == ka[:, None]))
            rhs[qrow, 5 * n + 1 + qrow - nr] = 1.0
            S = np.linalg.solve(A[0], rhs)[:nr]
            # data of every patch, in the representative's cell and vertex order
            inv = np.argsort(pc, axis=2)                                      # i for each i'
            pm = len(members)
            G = np.concatenate([(2 * cf[:, :, None] + np.arange(2)).reshape(pm, -1),
                                2 * nc + (3 * cf[:, :, None] + inv).reshape(pm, -1),
                                5 * nc + verts[members][:, None]], axis=1)
            G = G.astype(np.int32 if G.max() < 2 ** 31 else np.int64)
            for alpha in range(2):
                wf = self.wf[alpha][cf[:, :, None], inv, kf[:, :, None]]      # (pm, n, 3)
                level = ([(S[None, :, 5 * n + 1:], np.arange(pm * nq).reshape(pm, nq), L,
                           C)], RET.ravel())
                self.sigma_f[alpha] += _apply_class(level, wf.ravel(), space.nrt)
            groups.append((np.ascontiguousarray(S[:, :5 * n + 1]), G, RET.astype(np.int32),
                           L, C))
        return np.concatenate(own) if own else np.zeros(0, dtype=np.int64)

    def _solve_patches(self, verts, CS, KA, RET, loc, A):
        """The right-hand sides of P patch problems of one shape as linear maps of the data,
        and their solution (batched LAPACK): adds the patches' σ_a to the operators."""
        geo = self.geo
        P, n = CS.shape
        nr, N = RET.shape[1], A.shape[1]
        VERTS, _ = _row_unique(geo.cells[CS].reshape(P, -1), -1)              # (P, m)
        m = VERTS.shape[1]
        vloc = _row_index(VERTS, geo.cells[CS].reshape(P, -1)).reshape(P, n, 3)
        nq = 3 * n
        pp = np.arange(P)[:, None, None]
        jj = np.arange(n)[None, :, None]
        area = geo.area[CS]                                                   # (P, n)
        qloc = 3 * jj + np.arange(3)[None, None, :]                           # (1, n, 3)
        # local gradient (P, 2n, m) and lifting (P, 3n, m) operators
        grad = geo.grad[CS]                                                   # (P, n, 3, 2)
        Gd = np.zeros((P, 2 * n, m))
        rows = 2 * jj[..., None] + np.arange(2)                               # (1, n, 1, 2)
        Gd[pp[..., None], rows, vloc[..., None]] = grad
        Lr = np.zeros((P, nq, m))
        liftK = (3.0 / area)[..., None, None] * _MINV_REF \
            / geo.cells_per_vertex[geo.cells[CS]][:, :, None, :]              # (P, n, 3, 3)
        Lr[pp[..., None], qloc[..., None], vloc[:, :, None, :]] = liftK
        # right-hand sides: columns u (m) | λ_a (1) | R (m) | f1 | f2
        rhs = np.zeros((P, N, 2 * m + 3))
        kcols = 2 * KA[..., None] + np.arange(2)                              # (P, n, 2)
        Cka = np.take_along_axis(self.Ce[CS], kcols[:, :, None, :], axis=3)   # (P, n, 8, 2)
        Cl = np.zeros((P, nr, 2 * n))
        okc = np.broadcast_to(loc[..., None] >= 0, Cka.shape)
        pc = np.broadcast_to(pp[..., None], Cka.shape)
        rc = np.broadcast_to(loc[..., None], Cka.shape)
        cc = np.broadcast_to((2 * jj[..., None] + np.arange(2)), Cka.shape)
        Cl[pc[okc], rc[okc], cc[okc]] = Cka[okc]
        rhs[:, :nr, :m] = -Cl @ Gd
        gka = np.take_along_axis(grad, KA[:, :, None, None], axis=2)[:, :, 0]  # ∇ψ_a (P, n, 2)
        Qg = np.zeros((P, nq, 2 * n))
        Qg[pp[..., None], qloc[..., None], rows[:, :, 0][:, :, None, :]] = \
            -(area / 3.0)[..., None, None] * gka[:, :, None, :]
        Qr = np.zeros((P, nq, nq))
        Qr[pp[..., None], qloc[..., None], qloc[:, :, None, :]] = \
            -area[..., None, None] * _C3[KA].transpose(0, 1, 3, 2)            # [i, l]
        rhs[:, nr:nr + nq, :m] = Qg @ Gd
        rhs[:, nr:nr + nq, m + 1:2 * m + 1] = Qr @ Lr
        delta = (np.arange(3)[None, None, :] == KA[..., None])
        rhs[:, nr:nr + nq, m] = (area[..., None] / 12.0 * (1.0 + delta)).reshape(P, nq)
        for alpha in range(2):
            wf = self.wf[alpha][CS]                                           # (P, n, 3, 3)
            rhs[:, nr:nr + nq, 2 * m + 1 + alpha] = np.take_along_axis(
                wf, KA[:, :, None, None], axis=3)[..., 0].reshape(P, nq)
        sol = np.linalg.solve(A, rhs)[:, :nr]                                 # σ rows
        # σ = Σ_a σ_a: add this batch's operators (summed batch by batch to bound memory)
        shape = self.G_u.shape
        rows = np.broadcast_to(RET[:, :, None], (P, nr, m)).ravel().astype(np.int32)
        cols = np.broadcast_to(VERTS[:, None, :], (P, nr, m)).ravel().astype(np.int32)
        self.G_u = self.G_u + sp.csr_matrix((sol[:, :, :m].ravel(), (rows, cols)), shape=shape)
        self.G_R = self.G_R + sp.csr_matrix((sol[:, :, m + 1:2 * m + 1].ravel(), (rows, cols)),
                                            shape=shape)
        self.G_lam = self.G_lam + sp.csr_matrix(
            (sol[:, :, m].ravel(), (RET.ravel(), np.repeat(verts, nr))), shape=shape)
        for alpha in range(2):
            self.sigma_f[alpha] += np.bincount(RET.ravel(), sol[:, :, 2 * m + 1 + alpha].ravel(),
                                               minlength=shape[0])

    def sigma(self, alpha, u, lam, R):
        """RT_1 coefficients of σ_α,disc for membrane α ∈ {1, 2} (DESIGN §5)."""
        mu = self.disc.problem.mu1 if alpha == 1 else self.disc.problem.mu2
        sign = 1.0 if alpha == 1 else -1.0
        out = mu * (self.G_u @ u) + sign * (self.G_lam @ lam) + self.sigma_f[alpha - 1]
        if R is not None:
            out += self.G_R @ R
        if self.classes is not None:
            r = np.zeros(3 * self.geo.ncells) if R is None else self.lift @ R
            data = np.concatenate([mu * self.geo.gradient(u).ravel(), r, sign * lam])
            out += _apply_class(self.classes, data, len(out))
        return out


def _apply_class(level, data, size):
    from .algebraic_flux import _apply_buckets
    return _apply_buckets(level, data, size)
