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
The right-hand sides use exact integrals of P1 products on each cell; only (ψ_a f_α, q) needs
quadrature (the scene's data measures).
"""

import numpy as np
import scipy.sparse as sp
import ufl

from forms.equilibration import divergence, rt_mass, vector_moment, weighted_mass

from .discretisation import assemble_matrix_csr, over

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
        self.ncells = mesh.topology.index_map(2).size_local
        self.cells = V.dofmap.list.array.reshape(-1, 3)[:self.ncells].astype(np.int64)
        self.n = V.dofmap.index_map.size_local
        x = V.tabulate_dof_coordinates()[:, :2]
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


def _dense_block(A, rows, cols):
    """A[rows][:, cols] as a dense array (rows, cols: index arrays; cols unique)."""
    return A[rows][:, cols].toarray()


class FluxEquilibration:
    """Set-up (once per mesh) and evaluation of σ_α,disc (DESIGN §5)."""

    def __init__(self, disc):
        from dolfinx import fem
        self.disc = disc
        mesh = disc.V.mesh
        geo = self.geo = Geometry(disc.V)
        self.RT = fem.FunctionSpace(mesh, ("RT", 2))
        DG = fem.FunctionSpace(mesh, ("DG", 1))
        W = fem.VectorFunctionSpace(mesh, ("DG", 1))
        sig, tau = ufl.TrialFunction(self.RT), ufl.TestFunction(self.RT)
        p, q = ufl.TrialFunction(DG), ufl.TestFunction(DG)
        M = assemble_matrix_csr(rt_mass(sig, tau))
        B = assemble_matrix_csr(divergence(sig, q))                 # DG1 × RT
        C = assemble_matrix_csr(vector_moment(ufl.TrialFunction(W), tau))   # RT × W
        x = ufl.SpatialCoordinate(mesh)
        from .problem import as_builder
        problem = disc.problem
        f_blocks = []
        for f in (problem.f1, problem.f2):
            fx = as_builder(f)(x)
            Wf = assemble_matrix_csr(over(disc.dx_data, lambda dx: weighted_mass(fx, p, q, dx)))
            f_blocks.append(Wf)
        self.lift = lifting(geo)
        nc = geo.ncells
        rt_cells = self.RT.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        dg_cells = DG.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        w_cells = W.dofmap.list.array.reshape(nc, -1).astype(np.int64)
        self._check_vertex_order(DG, dg_cells, disc.V, geo.cells)
        # Wf_α[K][i, k] = (f_α φ_k, φ_i)_K
        ii, kk = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        wf = self.wf = [np.asarray(Wf[dg_cells[:, ii].ravel(), dg_cells[:, kk].ravel()]).reshape(nc, 3, 3)
              for Wf in f_blocks]
        layout = self.RT.dofmap.dof_layout
        edge_dofs = [np.array(layout.entity_dofs(1, e)) for e in range(3)]
        interior_dofs = np.array(layout.entity_dofs(2, 0))
        mesh.topology.create_connectivity(2, 1)
        mesh.topology.create_connectivity(1, 2)
        c2e = mesh.topology.connectivity(2, 1).array.reshape(nc, 3)
        from dolfinx import mesh as dmesh
        exterior = np.zeros(mesh.topology.index_map(1).size_local
                            + mesh.topology.index_map(1).num_ghosts, dtype=bool)
        exterior[dmesh.exterior_facet_indices(mesh.topology)] = True
        on_boundary = np.zeros(geo.n, dtype=bool)
        on_boundary[disc.boundary] = True

        u_rows, u_cols, u_vals = [], [], []
        r_rows, r_cols, r_vals = [], [], []
        l_rows, l_vals = [], []
        sigma_f = np.zeros((2, self.RT.dofmap.index_map.size_local))
        lift = self.lift
        for a in range(geo.n):
            sl = slice(geo.vertex_ptr[a], geo.vertex_ptr[a + 1])
            cs, ka = geo.vertex_cells[sl], geo.vertex_local[sl]
            nK = cs.size
            boundary_patch = on_boundary[a]
            # retained RT dofs: the two edges through a, the cell interiors, and (boundary
            # patch only) the opposite edge when it lies on ∂Ω
            keep = [interior_dofs]
            ret = []
            for K, k in zip(cs, ka):
                local = [edge_dofs[e] for e in range(3) if e != k]
                if boundary_patch and exterior[c2e[K, k]]:
                    local.append(edge_dofs[k])
                ret.append(rt_cells[K, np.concatenate(local + keep)])
            ret = np.unique(np.concatenate(ret))
            dg = dg_cells[cs].ravel()
            verts = np.unique(geo.cells[cs])
            vloc = {v: i for i, v in enumerate(verts)}
            m = verts.size
            nr, nq = ret.size, 3 * nK
            nmean = 0 if boundary_patch else 1
            # local saddle-point matrix
            A = np.zeros((nr + nq + nmean, nr + nq + nmean))
            Bl = _dense_block(B, dg, ret)
            A[:nr, :nr] = _dense_block(M, ret, ret)
            A[:nr, nr:nr + nq] = -Bl.T
            A[nr:nr + nq, :nr] = Bl
            area = geo.area[cs]
            if nmean:
                c = np.repeat(area / 3.0, 3)
                A[nr:nr + nq, -1] = c
                A[-1, nr:nr + nq] = c
            # local gradient (2nK × m) and lifting (3nK × m) operators
            Gd = np.zeros((2 * nK, m))
            Lr = np.zeros((3 * nK, m))
            lift_rows = lift[(3 * cs[:, None] + np.arange(3)).ravel()]
            lift_dense = lift_rows[:, verts].toarray()
            Lr[:] = lift_dense
            for j, K in enumerate(cs):
                for k in range(3):
                    Gd[2 * j:2 * j + 2, vloc[geo.cells[K, k]]] += geo.grad[K, k]
            # right-hand side columns: u (m) | λ_a (1) | R (m) | f1 | f2
            rhs = np.zeros((nr + nq + nmean, 2 * m + 3))
            wcols = (2 * w_cells[cs, ka][:, None] + np.arange(2)).ravel()   # (K, k_a, d)
            rhs[:nr, :m] = -_dense_block(C, ret, wcols) @ Gd
            Qg = np.zeros((nq, 2 * nK))
            Qr = np.zeros((nq, nq))
            for j, (K, k) in enumerate(zip(cs, ka)):
                rows = slice(3 * j, 3 * j + 3)
                Qg[rows, 2 * j:2 * j + 2] = -(geo.area[K] / 3.0) * geo.grad[K, k]
                Qr[rows, rows] = -geo.area[K] * _C3[k].T          # [i, l] = -|K| c3[k, l, i]
                rhs[nr + 3 * j:nr + 3 * j + 3, m] = geo.area[K] / 12.0 * (1.0 + (np.arange(3) == k))
                rhs[nr + 3 * j:nr + 3 * j + 3, 2 * m + 1] = wf[0][K][:, k]
                rhs[nr + 3 * j:nr + 3 * j + 3, 2 * m + 2] = wf[1][K][:, k]
            rhs[nr:nr + nq, :m] = Qg @ Gd
            rhs[nr:nr + nq, m + 1:2 * m + 1] = Qr @ Lr
            sol = np.linalg.solve(A, rhs)[:nr]
            u_rows.append(np.repeat(ret, m))
            u_cols.append(np.tile(verts, nr))
            u_vals.append(sol[:, :m].ravel())
            r_rows.append(np.repeat(ret, m))
            r_cols.append(np.tile(verts, nr))
            r_vals.append(sol[:, m + 1:2 * m + 1].ravel())
            l_rows.append(ret)
            l_vals.append(sol[:, m])
            sigma_f[0, ret] += sol[:, 2 * m + 1]
            sigma_f[1, ret] += sol[:, 2 * m + 2]
        nrt = sigma_f.shape[1]
        self.G_u = sp.csr_matrix((np.concatenate(u_vals),
                                  (np.concatenate(u_rows), np.concatenate(u_cols))),
                                 shape=(nrt, geo.n))
        self.G_R = sp.csr_matrix((np.concatenate(r_vals),
                                  (np.concatenate(r_rows), np.concatenate(r_cols))),
                                 shape=(nrt, geo.n))
        lam_cols = np.concatenate([np.full(len(r), a) for a, r in enumerate(l_rows)])
        self.G_lam = sp.csr_matrix((np.concatenate(l_vals), (np.concatenate(l_rows), lam_cols)),
                                   shape=(nrt, geo.n))
        self.sigma_f = sigma_f

    @staticmethod
    def _check_vertex_order(DG, dg_cells, V, p1_cells):
        """The local formulas assume the DG1 and P1 dofs of a cell sit at its vertices in the
        same order (basix's reference vertex order); check it rather than trust it."""
        xd = DG.tabulate_dof_coordinates()[:, :2][dg_cells]
        xp = V.tabulate_dof_coordinates()[:, :2][p1_cells]
        if not np.allclose(xd, xp, rtol=0, atol=1e-12 * max(1.0, np.abs(xp).max())):
            raise RuntimeError("DG1 and P1 dofs are not in the same cell vertex order")

    def sigma(self, alpha, u, lam, R):
        """RT_1 coefficients of σ_α,disc for membrane α ∈ {1, 2} (DESIGN §5)."""
        mu = self.disc.problem.mu1 if alpha == 1 else self.disc.problem.mu2
        sign = 1.0 if alpha == 1 else -1.0
        out = mu * (self.G_u @ u) + sign * (self.G_lam @ lam) + self.sigma_f[alpha - 1]
        if R is not None:
            out += self.G_R @ R
        return out
