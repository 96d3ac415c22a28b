"""The multilevel algebraic flux σ_α,alg (DESIGN §6; Papež, Rüde, Vohralík, Wohlmuth).

On the hierarchy T_0 ⊂ … ⊂ T_J = T_h, with Π_j the L² projection onto discontinuous P1 on T_j
(Π_0 := 0) and ψ_{j,a} the hat functions of T_j, for a residual lifting r_αh ∈ DG1(T_J):

1. coarse solve: ρ_0 ∈ P1(T_0) ∩ H¹_0 with (∇ρ_0, ∇v) = (r_αh, v) for all such v;
2. for j = 1..J and every vertex a of T_{j-1}: on the coarse patch ω^a_{j-1}, meshed by the
   cells of T_j inside it, the mixed RT_1 × P1 problem of DESIGN §5 (same boundary and mean
   conditions) with target 0 and divergence data
   d_a = (I - Π_{j-1})(r_αh ψ_{j-1,a} - ∇ρ_0·∇ψ_{j-1,a})  (the ρ_0 term matters at j = 1 only:
   ∇ρ_0·∇ψ_{j-1,a} is piecewise constant on T_{j-1}, which I - Π_{j-1} removes for j ≥ 2);
3. σ_alg = Σ_j Σ_a σ^a_j ∈ RT_1(T_J): the divergences telescope to Π_J r_αh = r_αh.

Set-up (once per hierarchy): the patch problems of every level, factorised into solution
operators S = (σ rows of A⁻¹ on the divergence data, by the Schur complement), one per class
of translated patches (a patch maps to its class representative by a change of RT basis with
entries 0, ±1), the classes shared across levels (a patch scaled by 2^j is a translate of
another level's: on a uniform refinement about one class per vertex, edge and cell of T_0 in
all), stacked by shape and class size. One evaluation: the exact P1 triple products
(r, φ_a φ_b)_K on T_J, restricted level by level to the coarser cells (O(N) in all); a coarse
solve; the data moments of every patch of every level (a gather), one batched product per
stack of operators, each patch's change of basis, one scatter; and the prolongations
RT_1(T_j) → RT_1(T_{j+1}) (interpolation of the coarse function, exact since the spaces are
nested; cell by cell with one reference block per kind of child): about one V-cycle.

Owner computes (several processes, each with the whole hierarchy): MultilevelFlux(...,
owned=...) sets up and evaluates the patches of the owned vertices only; every patch's data
are local given r_αh (replicated: its products on the patch's cells and the replicated coarse
solve), so the partial σ_alg of complementary ownerships sum to σ_alg, one Allreduce of the
RT_1(T_J) vector. (With r_αh distributed instead, the products restricted to T_0 and to the
coarse cells of patches that straddle owners would need a reduction first.)
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .compiled import kernel
from .discretisation import boundary_dofs
from .equilibration import (_C3, _MINV_REF, Geometry, Lifting, PatchSpace,
                            _local_index_type, _rt_element, change_of_basis_tables,
                            perm_number, rt_signs, translation_classes, vertex_patches)
from .hierarchy import barycentric
from .parallel import one_blas_thread


def _perm_code(pi):
    """`equilibration.perm_number` of each vertex map pi[..., :] (patch vertex i -> rep
    vertex pi[..., i]), for pi of shape (..., 3): int64 of shape pi.shape[:-1]."""
    pi = np.asarray(pi)
    out = np.empty(pi.shape[:-1], dtype=np.int64)
    _perm_numbers(np.ascontiguousarray(pi).reshape(-1, 3), out.reshape(-1))
    return out


@kernel
def _perm_numbers(pi, out):
    """out[r] = perm_number(pi[r]) for the rows r of pi (n, 3)."""
    for r in range(pi.shape[0]):
        out[r] = perm_number(pi[r, 0], pi[r, 1], pi[r, 2])


def _inverse_permutation(pi):
    """inv (..., 3) with inv[..., pi[..., i]] = i, for permutations pi of (0, 1, 2)."""
    inv = np.empty(pi.shape, dtype=np.int64)
    for v in range(3):
        inv[..., v] = (pi[..., 1] == v) + 2 * (pi[..., 2] == v)
    return inv


def _buckets(groups):
    """Stack the groups (S, G, RET, L, C) of classes of patches (one per class, see
    MultilevelFlux._translates) by (S.shape, number of patches): one batched product per
    bucket in an evaluation. Returns
    (buckets, RET): each bucket (S (g, nr, nq), G (g P, nq), L (g P, nr, 2), C (g P, nr, 2)),
    RET the global RT dofs of each bucket's patches, flat (a list, one array per bucket)."""
    keys = {}
    for k, g in enumerate(groups):
        keys.setdefault((g[0].shape, len(g[1])), []).append(k)
    buckets, ret = [], []
    for key in sorted(keys):
        members = [groups[k] for k in keys[key]]
        L = np.concatenate([g[3] for g in members])
        buckets.append((np.stack([g[0] for g in members]),
                        np.concatenate([g[1] for g in members]),
                        L.astype(_local_index_type(L.shape[1])),
                        np.concatenate([g[4] for g in members])))
        ret.append(np.concatenate([g[2].ravel() for g in members]))
    return buckets, ret


def _apply_buckets(level, flat, size, out=None, pool=None):
    """Σ_a σ^a over the patches of `level` (global RT coefficients, length `size`; for
    MultilevelFlux all levels' RT spaces one after the other) from the flat array of their
    data moments; with flat of shape (n, k), k fields at once (their data side by side, as
    FluxEquilibration.sigmas gives both membranes' data), returned as (size, k); added to
    `out` (size, k) if given (FluxEquilibration: its result, which holds σ_f, and σ_f,
    which holds the sums of the patches solved on their own), so that no array of size k
    entries is allocated per call. Per bucket, a
    few classes at a time (about ROWS patches: the temporaries stay in cache): the data of
    their patches, all fields (`_gather`, compiled: one read of the indices, one cache line
    for the fields of a datum), one product per class and field with its representative's
    operator (BLAS: the same products for one field or several), then each patch's change of
    basis (at most two representative dofs times 0, ±1) added to its RT dofs, all fields
    side by side, by `_scatter_products` (compiled). Every RT dof receives its terms in the
    order of the patches and, within a patch, of the representative's dofs: the sums of the
    sparse matrix that did the change of basis and the scatter before (its rows' entries in
    column order), to the bit, for each field the same as alone.

    With `pool` (an executor with a thread to spare) the chunks' gathers and products run on
    the pool, one chunk ahead of the scatters on this thread (two chunks' products at most in
    flight, each with its own buffer): the scatters keep their order, so the sums are the same
    to the bit."""
    buckets, rets = level
    one = flat.ndim == 1
    flat = flat.reshape(len(flat), -1)
    k = flat.shape[1]
    if out is None:
        out = np.zeros((size, k))

    def chunks():
        for (S, G, L, C), ret in zip(buckets, rets):
            g, nr, nq = S.shape
            per = G.shape[0] // g                          # the patches of each class
            step = max(1, _ROWS // per)
            F = [np.empty(k * min(step, g) * per * nq) for _ in range(1 if pool is None else 2)]
            for i, a in enumerate(range(0, g, step)):
                yield S, G, L, C, ret, F[i % len(F)], a, min(a + step, g), per

    def products(S, G, L, C, ret, F, a, b, per):
        nq = S.shape[2]
        # the leading part of one buffer: C-contiguous for a short last chunk too (one
        # argument type for _gather at every mesh size, so one compiled version of it)
        Fb = F[:k * (b - a) * per * nq].reshape(k, (b - a) * per, nq)
        _gather(flat, G[a * per:b * per], Fb)
        return np.matmul(Fb.reshape(k, b - a, per, nq), S[a:b].transpose(0, 2, 1)[None])

    def scatter(SR, S, G, L, C, ret, F, a, b, per):
        nr = S.shape[1]
        _scatter_products(SR.reshape(k, -1, nr), L[a * per:b * per], C[a * per:b * per],
                          ret[a * per * nr:b * per * nr], out)

    if pool is None:
        for chunk in chunks():
            scatter(products(*chunk), *chunk)
    else:
        before = None
        for chunk in chunks():
            made = pool.submit(products, *chunk)
            if before is not None:
                scatter(before[0].result(), *before[1])
            before = made, chunk
        if before is not None:
            scatter(before[0].result(), *before[1])
    return out[:, 0] if one else out


_ROWS = 1 << 14     # patches per product and scatter of `_apply_buckets`


@kernel
def _gather(flat, G, F):
    """F[f, p, i] = flat[G[p, i], f] for the fields f of flat (n, k) (one field and two
    written out: a loop over the fields per datum costs twice as much)."""
    k = flat.shape[1]
    for p in range(G.shape[0]):
        for i in range(G.shape[1]):
            j = G[p, i]
            if k == 1:
                F[0, p, i] = flat[j, 0]
            elif k == 2:
                F[0, p, i] = flat[j, 0]
                F[1, p, i] = flat[j, 1]
            else:
                for f in range(k):
                    F[f, p, i] = flat[j, f]


@kernel
def _scatter_products(SR, L, C, ret, out):
    """out[ret[p nr + i], f] += C[p, i, t] SR[f, p, L[p, i, t]] for the patches p of SR
    (k, P, nr) (their representatives' σ, k fields) and t = 0, 1 (the second where
    C[p, i, 1] ≠ 0), the two terms of a dof in the order of L (the first field, then the
    others: the same sums)."""
    k, P, nr = SR.shape
    for p in range(P):
        for i in range(nr):
            r = ret[p * nr + i]
            l0, l1 = L[p, i, 0], L[p, i, 1]
            c0, c1 = C[p, i, 0], C[p, i, 1]
            if c1 != 0 and l1 < l0:
                l0, l1, c0, c1 = l1, l0, c1, c0
            out[r, 0] += c0 * SR[0, p, l0]
            if c1 != 0:
                out[r, 0] += c1 * SR[0, p, l1]
            for f in range(1, k):
                out[r, f] += c0 * SR[f, p, l0]
                if c1 != 0:
                    out[r, f] += c1 * SR[f, p, l1]


def local_numbering(space, CF, boundary):
    """The retained RT dofs of patches of cells CF (P, m) (boundary flags (P,) or one):
    glob (P, 8 m) per cell (-1 dropped), RET (P, nr) the sorted retained dofs of each patch
    (padded with -1 where a patch retains fewer than the most, nr), loc (P, m, 8) their local
    numbers (-1 dropped) and count (P,) the number each patch retains."""
    P, m = CF.shape
    glob = space.retained_dofs(CF, np.broadcast_to(np.asarray(boundary, dtype=bool), (P,)))
    pad = np.int64(glob.max() + 1)
    key = np.where(glob < 0, pad, glob)
    order = np.argsort(key, axis=1)
    S = np.take_along_axis(key, order, axis=1)
    new = np.ones_like(S, dtype=bool)
    new[:, 1:] = S[:, 1:] != S[:, :-1]
    new &= S != pad
    rank = np.cumsum(new, axis=1) - 1                # local number of each sorted entry
    count = rank[:, -1] + 1
    loc = np.empty_like(rank)
    np.put_along_axis(loc, order, np.where(S == pad, -1, rank), axis=1)
    RET = np.full((P, count.max()), -1, dtype=np.int64)
    RET[np.nonzero(new)[0], rank[new]] = S[new]
    return glob, RET, loc.reshape(P, m, 8), count


def basis_change(refl, loc, pi, rep_refl, rep_loc, nr):
    """L, C (P, nr, 2) of patches (reflection codes refl (P, m), local numbers loc (P, m, 8),
    vertex matches pi (P, m, 3)) as translates of their representatives (rep_refl, rep_loc of
    the same shapes, or one row for all): σ_p[i] = Σ_t C[p, i, t] σ_r[L[p, i, t]] in the
    representative's local numbering.

    With F_K the affine map of a cell K in its dolfinx vertex order and R_K its edge
    reflections (basix base transformations), the local RT basis is R_K F_K*ψ̂. The
    representative's cell K' = K + shift has F_K' = shift ∘ F_K ∘ P_π (P_π the reference map
    that permutes the vertices), hence its basis is W_K = R_K' M_π R_K times K's, with M_π the
    reference basis expressed through its pull-back (entries 0, ±1). The patch systems are
    then related by the congruence Q A_p Qᵀ = A_r, and σ_p = Tᵀ σ_r for T the σ block of Q.
    (The same holds for K' = shift + t K, a homothety: the RT mass and divergence blocks of
    the contravariant Piola basis do not change under it; MultilevelFlux uses that.)"""
    P, m = refl.shape
    code = ((rep_refl.astype(np.int64) * 6 + _perm_code(pi)) * 8 + refl).ravel()  # per cell
    # σ_p[i] = Σ_k T[k, i] σ_r[k]: for the patch dof i at (c, k) the rows l with
    # W[c, l, k] ≠ 0, at the representative's local numbers; retained dofs only
    ok = np.flatnonzero(loc.reshape(-1) >= 0)                            # (p m + c) 8 + k
    cell, k = ok >> 3, ok & 7
    _, W_top, W_coef = change_of_basis_tables()
    top = W_top[code[cell], k]                                          # (n, 2)
    coef = W_coef[code[cell], k]
    base = cell if rep_loc.shape[0] == P else cell % m                    # one rep for all
    tgt = np.ascontiguousarray(rep_loc).reshape(-1)[(base * 8)[:, None] + top]
    if (tgt[coef != 0] < 0).any():
        raise RuntimeError("a retained dof of a translate maps to a dropped one")
    rows = (cell // m) * nr + loc.reshape(-1)[ok]
    L = np.zeros((P * nr, 2), dtype=_local_index_type(nr))
    C = np.zeros((P * nr, 2), dtype=np.int8)
    L[rows] = np.maximum(tgt, 0)
    C[rows] = coef
    return L.reshape(P, nr, 2), C.reshape(P, nr, 2)


def class_members(rep):
    """The patches of each class of `rep` (one index array per class, ascending)."""
    order = np.argsort(rep, kind="stable")
    cuts = np.flatnonzero(np.diff(rep[order])) + 1
    return np.split(order, cuts)


def _solution_operators(A, nr, nq):
    """S (g, nr, nq): the σ rows of A⁻¹ on the divergence rows, for patch systems A (g, N, N)
    = [[M, -Bᵀ, 0], [B, 0, c], [0, cᵀ, 0]] (the last row and column for interior patches only,
    N = nr + nq (+ 1)), by the Schur complement: σ = M⁻¹Bᵀγ, and with K = B M⁻¹ Bᵀ,
    K γ + c λ = d, cᵀγ = 0; so S = M⁻¹Bᵀ Γ, Γ the γ rows of [[K, c], [cᵀ, 0]]⁻¹ on d."""
    g, N = A.shape[:2]
    M, B = A[:, :nr, :nr], A[:, nr:nr + nq, :nr]
    X = np.linalg.solve(M, B.transpose(0, 2, 1))                              # (g, nr, nq)
    K = np.zeros((g, N - nr, N - nr))
    K[:, :nq, :nq] = B @ X
    K[:, :nq, nq:] = A[:, nr:nr + nq, nr + nq:]
    K[:, nq:, :nq] = A[:, nr + nq:, nr:nr + nq]
    E = np.zeros((N - nr, nq))
    E[:nq] = np.eye(nq)
    return X @ np.linalg.solve(K, np.broadcast_to(E, (g,) + E.shape))[:, :nq]


class MultilevelFlux:
    """σ_alg of DESIGN §6 for the discretisation `disc` on `hierarchy` (levels ≥ 1).

    Classes of patches are shared across the levels: a patch of level j whose cells, scaled
    by 2^j about its vertex, are a translate of another level's scaled patch has the same
    RT mass and divergence blocks (contravariant Piola), hence the same solution operator
    from data moments to σ (the zero-mean row only scales). On a uniform refinement of T_0
    that leaves about one class per vertex, edge and cell of T_0 for all levels together.

    `owned` (optional, for "owner computes" across processes that each hold the whole
    hierarchy): a list of J boolean arrays, owned[j - 1] over the vertices of T_{j-1} (its P1
    dofs, the numbering of Geometry); only those vertices' patches of level j are set up and
    evaluated. The σ_alg of complementary ownerships sum to the full σ_alg (to round-off: the
    classes' representatives may differ): every patch's data are local (products of r on its
    cells, ρ_0 replicated), so the only reduction is the sum of the partial σ_alg (an
    Allreduce by the caller)."""

    TRANSLATES = True   # False: every patch its own representative (for comparisons)
    CHUNK = 4096        # patches numbered at once in the set-up (bounds its temporaries)
    SOLVE_CHUNK = 256   # representatives' systems solved at once

    def __init__(self, disc, hierarchy, owned=None):
        from dolfinx import fem
        J = hierarchy.levels
        if J < 1:
            raise ValueError("the multilevel algebraic flux needs a mesh hierarchy with "
                             "levels >= 1 (--levels J)")
        self.disc, self.J = disc, J
        V = [fem.FunctionSpace(m, ("Lagrange", 1)) for m in hierarchy.meshes[:-1]] + [disc.V]
        self.geo = [Geometry(v) for v in V]
        self.lift = Lifting(self.geo[J])
        # vertices of each T_j cell in its parent's barycentric basis (multiples of 1/2, kept
        # as 2 Bp in int8: exact), and the four children of each T_{j-1} cell
        corners = [g.x[g.cells] for g in self.geo]
        self.Bp2 = [None] + [np.round(2.0 * barycentric(
            corners[j], corners[j - 1][hierarchy.parent_cells[j - 1]])).astype(np.int8)
            for j in range(1, J + 1)]
        del corners
        self._parents = [None] + [np.asarray(p, dtype=np.int32)
                                  for p in hierarchy.parent_cells]   # T_j cell -> T_{j-1} cell
        self.children = [None] + [np.argsort(p, kind="stable").reshape(-1, 4).astype(np.int32)
                                  for p in hierarchy.parent_cells]
        self.kinds = [None]
        for j in range(1, J + 1):
            cells, Bp = child_kinds(self.Bp2[j])
            self.kinds.append(([c.astype(np.int32) for c in cells],
                               [_kind_matrices(b) for b in Bp]))
        self._coarse_solver(V[0])
        spaces = [None] + [PatchSpace(V[j], blocks=False) for j in range(1, J + 1)]
        # every level's RT coefficients and data moments in one flat array each: level j at
        # rt_offset[j - 1], flat_offset[j - 1]
        self.nrt = [None] + [spaces[j].nrt for j in range(1, J + 1)]
        self.rt_offset = np.concatenate([[0], np.cumsum(self.nrt[1:])]).astype(np.int64)
        self.flat_offset = np.concatenate(
            [[0], np.cumsum([9 * spaces[j].geo.ncells for j in range(1, J + 1)])]).astype(
            np.int64)
        self.classes = self._classes(spaces, owned)
        self.prolong = [None, None] + [
            Prolongation(spaces[j - 1], spaces[j], self._parents[j], self.Bp2[j])
            for j in range(2, J + 1)]
        # what an evaluation needs: the coarse geometry, the fine areas, the RT dimensions
        self.RT = spaces[J].RT
        self.areas = [g.area for g in self.geo]
        self.geo = [self.geo[0]]

    def _coarse_solver(self, V0):
        import ufl
        from forms.membrane import membrane_bilinear
        from .discretisation import assemble_matrix_csr, boundary_dofs
        u, v = ufl.TrialFunction(V0), ufl.TestFunction(V0)
        S = assemble_matrix_csr(membrane_bilinear(1.0, u, v))
        bdofs = boundary_dofs(V0)
        keep = np.ones(S.shape[0])
        keep[bdofs] = 0.0
        S = sp.diags(keep) @ S + sp.diags(1.0 - keep)
        self._coarse = spla.splu(S.tocsc())
        self._coarse_boundary = bdofs

    def _classes(self, spaces, owned):
        """The patch problems of all levels: level j has one per vertex of T_{j-1}, on the T_j
        cells of its patch. The patches of every level, in coordinates scaled by 2^j / h_0
        (h_0² the mean area of T_0: T_j's cells are T_0's halved j times), are sorted into
        classes of translates (`translation_classes` on one virtual mesh of all levels' cells);
        each class shares the solution operator of its representative (`_translates`).
        Returns the buckets of all levels' patches (`_buckets`; None if there are none)."""
        from types import SimpleNamespace
        J = self.J
        scale = [np.sqrt(self.geo[0].area.mean()) / 2.0 ** j for j in range(J + 1)]
        fine = [spaces[j].geo for j in range(1, J + 1)]
        cell_off = np.concatenate([[0], np.cumsum([g.ncells for g in fine])])
        vert_off = np.concatenate([[0], np.cumsum([g.n for g in fine])])
        virtual = SimpleNamespace(
            x=np.concatenate([g.x / scale[j + 1] for j, g in enumerate(fine)]),
            cells=np.concatenate([g.cells + vert_off[j] for j, g in enumerate(fine)]))
        exterior = np.concatenate([spaces[j].exterior_edge for j in range(1, J + 1)])
        cent = virtual.x[virtual.cells].mean(axis=1)
        parts = {}   # number of cells m -> the patches (level, CF, KF, boundary, vertex)
        for j in range(1, J + 1):
            coarse = self.geo[j - 1]
            on_boundary = np.zeros(coarse.n, dtype=bool)
            on_boundary[boundary_dofs(coarse.V)] = True
            for verts, CS, KA in vertex_patches(coarse):
                if owned is not None:
                    keep = np.asarray(owned[j - 1], dtype=bool)[verts]
                    verts, CS, KA = verts[keep], CS[keep], KA[keep]
                P = len(verts)
                if P == 0:
                    continue
                CF = self.children[j][CS].reshape(P, -1) + cell_off[j - 1]
                parts.setdefault(CF.shape[1], []).append(
                    (np.full(P, j, dtype=np.int8), CF, np.repeat(KA, 4, axis=1),
                     on_boundary[verts], coarse.x[verts] / scale[j]))
        found = []
        for m in sorted(parts):
            lev, CF, KF, bnd, xa = (np.concatenate(z) for z in zip(*parts.pop(m)))
            CF, KF, rep, pi = translation_classes(xa, CF, KF, bnd, virtual, cent, 1.0,
                                                  self.TRANSLATES, exterior)
            found.append((lev, CF - cell_off[lev - 1][:, None], KF, bnd, rep, pi))
        del virtual, cent, exterior
        # the element blocks of all representatives' cells, one pass per level
        blocks = {}
        reps = [np.unique(f[4]) for f in found]
        for j in range(1, J + 1):
            cells = np.unique(np.concatenate([f[1][r[f[0][r] == j]].ravel()
                                              for f, r in zip(found, reps)]))
            if len(cells):
                blocks[j] = (cells,) + spaces[j].element_blocks(cells)
        groups = []
        while found:
            groups += self._translates(spaces, *found.pop(0), blocks)
        return _buckets(groups) if groups else None

    def _translates(self, spaces, lev, CF, KF, bnd, rep, pi, blocks):
        """Patches of m cells from any levels (level lev (P,), cells CF (P, m) of their level
        in canonical order, the local index KF of a in each cell's parent, boundary flags,
        representatives rep and vertex matches pi to them): the local numbering of every
        patch, its change of basis to its representative (`basis_change`), the
        representatives' solution operators S (σ rows of A⁻¹ on the data moments; batched
        solves by shape), and the data indices (the DG1 moments permuted by π). Returns
        the groups (S, G, RET, L, C) of `_buckets`, one per class, G and RET in the flat
        arrays of all levels."""
        P, m = CF.shape
        nq = 3 * m
        loc = np.empty((P, m, 8), dtype=np.int16)
        count = np.empty(P, dtype=np.int64)
        refl = np.empty((P, m), dtype=np.int8)
        chunks = []
        for j in np.unique(lev):
            at = np.flatnonzero(lev == j)
            for s in range(0, len(at), self.CHUNK):
                idx = at[s:s + self.CHUNK]
                _, R, loc[idx], count[idx] = local_numbering(spaces[j], CF[idx], bnd[idx])
                chunks.append((idx, (R + self.rt_offset[j - 1]).astype(np.int32)))
                refl[idx] = spaces[j].reflections[CF[idx]]
        nr = int(count.max())
        RET = np.empty((P, nr), dtype=np.int32)      # the global RT dofs, padded
        for idx, R in chunks:
            RET[idx, :R.shape[1]] = R
        del chunks
        L = np.empty((P, nr, 2), dtype=_local_index_type(nr))
        C = np.empty((P, nr, 2), dtype=np.int8)
        for s in range(0, P, self.CHUNK):
            sl = slice(s, s + self.CHUNK)
            r = rep[sl]
            L[sl], C[sl] = basis_change(refl[sl], loc[sl], pi[sl], refl[r], loc[r], nr)
        S = self._operators(spaces, lev, CF, bnd, count, np.unique(rep), blocks)
        # the patches in class order (each class a slice); data: the rep's moment i' of cell
        # c is the patch's moment at i with pi[c, i] = i'
        order = np.argsort(rep, kind="stable")
        RET, L, C = RET[order], L[order], C[order]
        G = np.empty((P, nq), dtype=np.int32 if self.flat_offset[-1] < 2 ** 31 else np.int64)
        for s in range(0, P, self.CHUNK):
            o = order[s:s + self.CHUNK]
            G[s:s + self.CHUNK] = (self.flat_offset[lev[o] - 1][:, None, None] + (
                CF[o][:, :, None] * 3 + KF[o][:, :, None]) * 3
                + _inverse_permutation(pi[o])).reshape(len(o), nq)
        cuts = np.flatnonzero(np.diff(rep[order])) + 1
        groups = []
        for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [P]])):
            r = rep[order[a]]
            n = count[r]
            groups.append((S[r], G[a:b], RET[a:b, :n], L[a:b, :n], C[a:b, :n]))
        return groups

    def _operators(self, spaces, lev, CF, bnd, count, reps, blocks):
        """{rep: S (nr, nq)}: the solution operators of the representatives' patch problems
        (DESIGN §5 with target 0), batched by level and shape; blocks[j] = (cells, Me, Be):
        the element blocks of level j's representatives' cells (the lowest level where a
        class occurs: the patches are listed level by level, the first member represents)."""
        nq = 3 * CF.shape[1]
        out = {}
        for j in np.unique(lev[reps]):
            rj = reps[lev[reps] == j]
            cells, Me, Be = blocks[j]
            inverse = np.searchsorted(cells, CF[rj])
            for b, n in sorted(set(zip(bnd[rj].tolist(), count[rj].tolist()))):
                sel = np.flatnonzero((bnd[rj] == b) & (count[rj] == n))
                for s in range(0, len(sel), self.SOLVE_CHUNK):
                    k = sel[s:s + self.SOLVE_CHUNK]
                    cs = CF[rj[k]]
                    glob = spaces[j].retained_dofs(cs, np.full(len(k), b))
                    _, _, A = spaces[j].saddle_point_systems(
                        cs, glob, b, blocks=(Me[inverse[k]], Be[inverse[k]]))
                    with one_blas_thread():
                        out.update(zip(rj[k].tolist(), _solution_operators(A, n, nq)))
        return out

    def _by_kind(self, j, X, which):
        """Y (nc_j, 3, 3) with Y[K] = X[K] (flattened) times the 9 × 9 matrix `which` of K's
        kind of child (see `_kind_matrices`): one product per kind."""
        Y = np.empty((len(X), 9))
        X = X.reshape(len(X), 9)
        for cells, mats in zip(*self.kinds[j]):
            Y[cells] = X[cells] @ mats[which]
        return Y.reshape(-1, 3, 3)

    def _products(self, r):
        """Mom[j][K, a, b] = (r φ^K_a, φ^K_b)_K for every cell K of every level T_j, r ∈ DG1(T_J)
        (ncells, 3): exact P1 triple products on T_J, then restricted level by level with the
        children's vertices in their parent's barycentric basis (φ^{K'}_{a'} = Σ_v Bp[K, v, a']
        φ^K_v on a child K of K': Bpᵀ Mom Bp), O(N) in all."""
        J = self.J
        mom = [None] * (J + 1)
        mom[J] = ((r @ _C3.reshape(3, 9)) * self.areas[J][:, None]).reshape(-1, 3, 3)
        for j in range(J, 0, -1):
            mom[j - 1] = self._by_kind(j, mom[j], 0)[self.children[j]].sum(axis=1)
        return mom

    def _moments(self, j, mom, grad_rho0):
        """(d_a, q_i)_{K_j} for every cell K_j of T_j and every local vertex k of its parent
        (the vertex a): shape (nc_j, 3 (k), 3 (i))."""
        m = self._by_kind(j, mom[j], 1)                                       # Bpᵀ Mom
        parent = self._parents[j]
        area = self.areas[j]
        if j == 1:   # - ∇ρ_0·∇ψ_{0,k} (constant on K_0) times (1, q_i)_{K_1} = |K_1|/3
            g0 = self.geo[0]
            dot = np.einsum("cd,ckd->ck", grad_rho0, g0.grad)[parent]         # (nc_1, 3)
            m -= (area / 3.0)[:, None, None] * dot[:, :, None]
        else:        # - (Π_{j-1}(r ψ_k), q_i)_{K_j}
            coef = (3.0 / self.areas[j - 1])[:, None, None] * (mom[j - 1] @ _MINV_REF.T)
            p = self._by_kind(j, coef[parent], 2)                # coef Bpᵀ: at K_j's vertices
            m -= (area / 12.0)[:, None, None] * (p + p.sum(axis=2, keepdims=True))
        return m

    def sigma(self, R):
        """[σ_1,alg, σ_2,alg] (RT_1(T_J) coefficients) for the algebraic residual R (3N)."""
        n = self.disc.n
        return [self.flux_of_lifting((self.lift @ Ra).reshape(-1, 3))
                for Ra in (R[:n], R[n:2 * n])]

    def flux_of_lifting(self, r):
        """σ_alg with ∇·σ_alg = r for r ∈ DG1(T_J) given per cell (ncells, 3)."""
        g0 = self.geo[0]
        mom = self._products(r)
        b = np.bincount(g0.cells.ravel(), mom[0].sum(axis=1).ravel(), minlength=g0.n)
        b[self._coarse_boundary] = 0.0
        grad_rho0 = g0.gradient(self._coarse.solve(b))
        flat = np.concatenate([self._moments(j, mom, grad_rho0).ravel()
                               for j in range(1, self.J + 1)])
        del mom
        off = self.rt_offset
        if self.classes is None:
            sigma = np.zeros(off[-1])
        else:
            sigma = _apply_buckets(self.classes, flat, off[-1])
        total = sigma[off[0]:off[1]]
        for j in range(2, self.J + 1):
            total = sigma[off[j - 1]:off[j]] + self.prolong[j] @ total
        return total


def _child_block(beta):
    """B̂ (8, 8): the reference RT_1 dofs of a child cell K applied to the reference basis
    functions of its parent P, for the child's vertices l at barycentric coordinates beta[l]
    in P (both bases unreflected). With G = F_P⁻¹ ∘ F_K: X ↦ X_0 + A X (A = F_P⁻¹ F_K' exact
    in multiples of 1/2), a function pushed forward from P by the contravariant Piola map
    pulls back to K as adj(A) ψ̂ ∘ G (det J_K / det J_P = det A); B̂ = its interpolation by the
    element's interpolation matrix (exact: RT_1(K) ⊃ RT_1(P)|_K)."""
    e = _rt_element()
    Xl = np.asarray(beta, dtype=float)[:, 1:]                                 # (3, 2) in P
    A = np.stack([Xl[1] - Xl[0], Xl[2] - Xl[0]], axis=1)
    adj = np.array([[A[1, 1], -A[0, 1]], [-A[1, 0], A[0, 0]]])
    X = e.points                                                             # (npts, 2)
    psi = e.tabulate(0, Xl[0] + X @ A.T)[0]                                  # (npts, 8, 2)
    pulled = np.einsum("cd,pkd->cpk", adj, psi).reshape(-1, 8)               # (2 npts, 8)
    return e.interpolation_matrix @ pulled


def child_kinds(Bp2):
    """The kinds of children on a level (how a cell's vertices sit in its parent: 2 Bp2 (nc, 3,
    3), barycentric coordinates in {0, 1/2, 1}; six kinds on a Plaza refinement): the cells of
    each kind and its Bp (3, 3)."""
    code = Bp2.reshape(len(Bp2), 9).astype(np.int64) @ 3 ** np.arange(9)   # digits 0, 1, 2
    _, first, kind = np.unique(code, return_index=True, return_inverse=True)
    return class_members(kind.ravel()), [Bp2[f] * 0.5 for f in first]


def _kind_matrices(Bp):
    """The 9 × 9 matrices, acting on row-major flattened 3 × 3 rows, of X ↦ Bpᵀ X Bp,
    X ↦ Bpᵀ X and X ↦ X Bpᵀ."""
    return np.kron(Bp, Bp), np.kron(Bp, np.eye(3)), np.kron(np.eye(3), Bp.T)


class Prolongation:
    """RT_1(T_{j-1}) → RT_1(T_j), the interpolation of a coarse function (exact: the spaces are
    nested), cell by cell: on a child K of P, the global dofs of K are s_K ⊙ B̂ (s_P ⊙ c_P),
    with c_P the global coefficients on P's dofs, s the edge signs of each cell's reflections
    (dolfinx's dof transformations: diagonal ±1 for RT_1, so their inverse transpose is
    themselves) and B̂ (`_child_block`) one of the few reference blocks given by how the
    child sits in its parent (the children's vertices in the parent's barycentric basis:
    six kinds on a Plaza refinement). A fine dof shared by two cells gets the same value from
    both (to round-off). Apply with `P @ c` (c of shape (n_{j-1},) or (n_{j-1}, k)).
    Kept: both levels' cell dofs and signs and the parent map, the fine cells in kind order
    (one product with a block per kind)."""

    def __init__(self, coarse, fine, parent, Bp2):
        self.shape = (fine.nrt, coarse.nrt)
        self.rt_c = coarse.rt_cells.astype(np.int32)
        self.s_c = rt_signs(coarse.reflections)                              # (nc_{j-1}, 8)
        # the fine cells in kind order, each kind a slice
        cells, Bp = child_kinds(Bp2)
        order = np.concatenate(cells)
        self.cuts = np.cumsum([0] + [len(c) for c in cells])
        self.rt_f = fine.rt_cells[order].astype(np.int32)
        self.s_f = rt_signs(fine.reflections[order])
        self.parent = np.asarray(parent, dtype=np.int32)[order]
        # exact zeros where the block is zero to round-off (its entries are O(1))
        self.blocks = [np.where(np.abs(b) < 1e-12, 0.0, b).T for b in map(_child_block, Bp)]

    def __matmul__(self, c):
        c = np.asarray(c)
        if c.ndim == 2:
            return np.stack([self @ c[:, i] for i in range(c.shape[1])], axis=1)
        ct = c[self.rt_c] * self.s_c
        out = np.zeros(self.shape[0])
        for Bt, a, b in zip(self.blocks, self.cuts[:-1], self.cuts[1:]):
            out[self.rt_f[a:b]] = (ct[self.parent[a:b]] @ Bt) * self.s_f[a:b]
        return out
