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

Set-up (once per hierarchy): the element blocks of every level (PatchSpace), the patch problems
factorised into their solution operators S_a = (σ rows of A_a⁻¹ on the divergence data), and
the tensors of exact P1 triple products that turn r_αh into the data moments (d_a, q)_K for
every cell K of T_j. One evaluation is a coarse solve, a few tensor contractions, one small
dense product per patch, and the prolongations RT_1(T_j) → RT_1(T_{j+1}) (interpolation of the
coarse function, exact since the spaces are nested): about one V-cycle.
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .discretisation import boundary_dofs
from .equilibration import (_C3, _MINV_REF, Geometry, PatchSpace, graph_colouring, lifting,
                            vertex_patches)


def _barycentric(points, corners):
    """Barycentric coordinates of points (c, m, 2) in triangles with corners (c, 3, 2):
    shape (c, m, 3)."""
    v0 = corners[:, 0]
    T = np.stack([corners[:, 1] - v0, corners[:, 2] - v0], axis=2)          # (c, 2, 2)
    xi = np.linalg.solve(T[:, None], (points - v0[:, None])[..., None])[..., 0]
    return np.concatenate([1.0 - xi.sum(axis=2, keepdims=True), xi], axis=2)


def _triple(area, left, right):
    """t[L, l, k, i] = ∫_L φ_l^L ψ_k q_i for P1 functions given by their values at the
    vertices of L: left (L, 3, k), right (L, 3, i); φ^L the barycentric basis of L."""
    return area[:, None, None, None] * np.einsum("lmn,Lmk,Lni->Llki", _C3, left, right)


def _descendants(anc, size):
    """The cells of T_J below each of the `size` cells of T_j: (size, 4^{J-j}) indices."""
    return np.argsort(anc, kind="stable").reshape(size, -1)


class MultilevelFlux:
    """σ_alg of DESIGN §6 for the discretisation `disc` on `hierarchy` (levels ≥ 1)."""

    CHUNK = 500      # patches solved at once (the local systems have ~180 unknowns)

    def __init__(self, disc, hierarchy):
        from dolfinx import fem
        J = hierarchy.levels
        if J < 1:
            raise ValueError("the multilevel algebraic flux needs a mesh hierarchy with "
                             "levels >= 1 (--levels J)")
        self.disc, self.J = disc, J
        V = [fem.FunctionSpace(m, ("Lagrange", 1)) for m in hierarchy.meshes[:-1]] + [disc.V]
        self.geo = [Geometry(v) for v in V]
        fine = self.geo[J]
        self.lift = lifting(fine)
        # ancestors of the cells of T_J on every level, and the coordinates of their
        # vertices in the ancestor's barycentric basis
        anc = [None] * (J + 1)
        anc[J] = np.arange(fine.ncells)
        for j in range(J, 0, -1):
            anc[j - 1] = hierarchy.parent_cells[j - 1][anc[j]]
        self.anc = anc
        self.below = [_descendants(anc[j], self.geo[j].ncells) for j in range(J + 1)]
        xJ = self._corners(J)
        bary = [_barycentric(xJ, self._corners(j)[anc[j]]) for j in range(J + 1)]
        # data tensors: level j moments (r ψ_{j-1,k}, q_i)_{K_j} and, for j ≥ 2, the moments
        # (r ψ_{j-1,k}, φ_m)_{K_{j-1}} behind Π_{j-1}; (r, φ_k)_{K_0} for the coarse solve
        self.T = [None] + [_triple(fine.area, bary[j - 1], bary[j]) for j in range(1, J + 1)]
        self.Tproj = [None, None] + [_triple(fine.area, bary[j - 1], bary[j - 1])
                                     for j in range(2, J + 1)]
        mass_ref = (np.ones((3, 3)) + np.eye(3)) / 12.0
        self.T0 = fine.area[:, None, None] * np.einsum("lm,Lmk->Llk", mass_ref, bary[0])
        # vertices of each T_j cell in its parent's barycentric basis (for Π_{j-1} on K_j)
        self.Bp = [None] + [_barycentric(self._corners(j),
                                         self._corners(j - 1)[hierarchy.parent_cells[j - 1]])
                            for j in range(1, J + 1)]
        self._parents = [None] + list(hierarchy.parent_cells)   # T_j cell -> T_{j-1} cell
        self._coarse_solver(V[0])
        self.spaces = [None] + [PatchSpace(V[j]) for j in range(1, J + 1)]
        self.levels = [None] + [self._level(j, hierarchy) for j in range(1, J + 1)]
        self.prolong = [None, None] + [self._prolongation(j) for j in range(2, J + 1)]

    def _corners(self, j):
        """Vertex coordinates of the cells of T_j, (nc_j, 3, 2), in the cells' vertex order."""
        geo = self.geo[j]
        return geo.V.tabulate_dof_coordinates()[:, :2][geo.cells]

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

    def _level(self, j, hierarchy):
        """The patch problems of level j: one per vertex of T_{j-1}, on the T_j cells of its
        patch; returns the batches (RET, S, fine cells, local index of a in their parent)."""
        space = self.spaces[j]
        coarse = self.geo[j - 1]
        parents = hierarchy.parent_cells[j - 1]
        children = np.argsort(parents, kind="stable").reshape(-1, 4)          # (nc_{j-1}, 4)
        on_boundary = np.zeros(coarse.n, dtype=bool)
        on_boundary[boundary_dofs(coarse.V)] = True
        batches = []
        for verts, CS, KA in vertex_patches(coarse):
            CF = children[CS].reshape(len(verts), -1)                        # (P, 4n)
            KF = np.repeat(KA, 4, axis=1)
            for sel, RET, loc, A in space.patch_groups(CF, on_boundary[verts], self.CHUNK):
                nr, nq = RET.shape[1], 3 * CF.shape[1]
                E = np.zeros((A.shape[1], nq))
                E[nr:nr + nq] = np.eye(nq)
                S = np.linalg.solve(A, np.broadcast_to(E, (len(sel),) + E.shape))[:, :nr]
                batches.append((RET, S, CF[sel], KF[sel]))
        return batches

    def _moments(self, j, r, grad_rho0):
        """(d_a, q_i)_{K_j} for every cell K_j of T_j and every local vertex k of its parent
        (the vertex a): shape (nc_j, 3 (k), 3 (i))."""
        m = np.einsum("Ll,Llki->Lki", r, self.T[j])[self.below[j]].sum(axis=1)
        parent = self._parents[j]
        area = self.geo[j].area
        if j == 1:   # - ∇ρ_0·∇ψ_{0,k} (constant on K_0) times (1, q_i)_{K_1} = |K_1|/3
            g0 = self.geo[0]
            dot = np.einsum("cd,ckd->ck", grad_rho0, g0.grad)[parent]         # (nc_1, 3)
            m -= (area / 3.0)[:, None, None] * dot[:, :, None]
        else:        # - (Π_{j-1}(r ψ_k), q_i)_{K_j}
            mp = np.einsum("Ll,Llkm->Lkm", r, self.Tproj[j])[self.below[j - 1]].sum(axis=1)
            coef = (3.0 / self.geo[j - 1].area)[:, None, None] * (mp @ _MINV_REF.T)
            p = np.einsum("ckm,cvm->ckv", coef[parent], self.Bp[j])           # at K_j vertices
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
        b = np.zeros(g0.n)
        np.add.at(b, g0.cells, np.einsum("Ll,Llk->Lk", r, self.T0)[self.below[0]].sum(axis=1))
        b[self._coarse_boundary] = 0.0
        grad_rho0 = g0.gradient(self._coarse.solve(b))
        total = None
        for j in range(1, self.J + 1):
            space = self.spaces[j]
            m = self._moments(j, r, grad_rho0)
            sigma = np.zeros(space.nrt)
            for RET, S, CF, KF in self.levels[j]:
                rhs = np.take_along_axis(m[CF], KF[:, :, None, None], axis=2)[:, :, 0]
                local = np.einsum("prq,pq->pr", S, rhs.reshape(len(CF), -1))
                sigma += np.bincount(RET.ravel(), local.ravel(), minlength=space.nrt)
            if total is not None:
                sigma += self.prolong[j] @ total
            total = sigma
        return total

    def _prolongation(self, j):
        """The matrix of RT_1(T_{j-1}) → RT_1(T_j), interpolation of the coarse function (exact:
        the spaces are nested). Built by interpolating sums of coarse basis functions, one sum
        per colour of coarse dofs that share no cell: a fine dof then sees at most one basis
        function of the colour (a coarse dof of its parent cell; the dofs of a coarse edge are
        the only ones with a normal component on it), so each pass gives one column entry per
        fine dof."""
        from dolfinx import fem
        coarse, fine = self.spaces[j - 1], self.spaces[j]
        parent = self._parents[j]
        iu = np.triu_indices(8, 1)
        pairs = np.unique(np.stack([coarse.rt_cells[:, iu[0]].ravel(),
                                    coarse.rt_cells[:, iu[1]].ravel()], axis=1), axis=0)
        colour = graph_colouring(pairs, coarse.nrt)
        fc, ff = fem.Function(coarse.RT), fem.Function(fine.RT)

        def values(x):   # the interpolation points come cell by cell, for all cells of T_j
            cells = np.repeat(parent, x.shape[1] // len(parent)).astype(np.int32)
            return fc.eval(np.ascontiguousarray(x.T), cells).T

        rows, cols, vals = [], [], []
        for c in range(colour.max() + 1):
            fc.x.array[:] = (colour == c)
            ff.interpolate(values)
            # the coarse dof of colour c in each fine cell's parent, for each fine dof
            source = np.where(colour[coarse.rt_cells[parent]] == c,
                              coarse.rt_cells[parent], -1).max(axis=1)        # (nc_j,)
            f_dofs = fine.rt_cells.ravel()
            src = np.repeat(source, fine.rt_cells.shape[1])
            ok = (src >= 0) & (ff.x.array[f_dofs] != 0.0)
            rows.append(f_dofs[ok])
            cols.append(src[ok])
            vals.append(ff.x.array[f_dofs][ok])
        rows, cols, vals = (np.concatenate(z) for z in (rows, cols, vals))
        # each fine dof sits in one or two fine cells: keep one entry per (row, col)
        key = np.unique(rows.astype(np.int64) * coarse.nrt + cols, return_index=True)[1]
        return sp.csr_matrix((vals[key], (rows[key], cols[key])),
                             shape=(fine.nrt, coarse.nrt))
