"""The lifting of an algebraic residual into a discontinuous P1 function (§4), and the DG1
cell algebra it rests on.

A residual R (one value per P1 dof, zero at Dirichlet vertices) is lifted to r_h ∈ DG1: on each
cell K and each of its vertices a_l,

    (r_h, ψ_{a_l})_K = R_l / N_l,     N_l = number of cells sharing a_l (over all processes),

so that (r_h, ψ_l)_Ω = Σ_{K ∋ a_l} R_l / N_l = R_l and the linear rows of §2 at any iterate
read (§4) μ1 (∇u1h, ∇ψ_l) = (f1 + λ_l - r1h, ψ_l), μ2 (∇u2h, ∇ψ_l) = (f2 - λ_l - r2h, ψ_l).

On K the P1 mass matrix is M_K = |K|/12 (I + 1 1ᵀ) (vertex order), whose inverse is
M_K⁻¹ = (3/|K|) (4 I - 1 1ᵀ) = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]]; the DG1 coefficients of
r_h on K (Lagrange, the same vertex order as P1) are r_K = M_K⁻¹ (R_l / N_l)_{l ∈ K}. This is
cell-local algebra, vectorised over the owned cells (`mass_inverse`, which the cellwise
projections of §7, `dg1_projections`, the multilevel moments of §6 and the fluxes' defect
norms apply too). N_l counts the owned cells at each dof on every process, added up on the
owner by dolfinx's reverse scatter.
"""

import numpy as np

from ..fem.meshes import triangle_areas

MINV_REF = np.array([[3.0, -1.0, -1.0], [-1.0, 3.0, -1.0], [-1.0, -1.0, 3.0]])


def mass_inverse(area, b):
    """M_K⁻¹ b_K on every cell K: the inverse of the DG1 (and P1) cell mass matrix
    M_K = |K|/12 (I + 1 1ᵀ), M_K⁻¹ = (3/|K|) MINV_REF (module notes, §4), applied to the
    moments b_K,m = (v, φ_m)_K (m in the vertex order of the cell) gives the DG1 coefficients
    of v's L² projection on K. b: (c, 3), one row of moments per cell, or (c, k, 3), k rows
    per cell (identity rows give the blocks M_K⁻¹ themselves); `area`: |K| ((c,),
    `membranes.fem.meshes.triangle_areas`). MINV_REF is symmetric, so b_K MINV_REF is
    (MINV_REF b_Kᵀ)ᵀ."""
    scale = 3.0 / area
    return scale.reshape((-1,) + (1,) * (np.ndim(b) - 1)) * (b @ MINV_REF)


class Lifting:
    """R ↦ r_h for the P1 space V (set up once per mesh: cell areas, N_l), into the DG1 space
    Q (made if None; a caller that has one on the mesh passes it: each space costs a dofmap)."""

    def __init__(self, V, Q=None):
        from dolfinx import fem, la
        mesh = V.mesh
        self.V = V
        self.Q = Q if Q is not None else fem.FunctionSpace(mesh, ("DG", 1))
        self.ncells = nc = mesh.topology.index_map(mesh.topology.dim).size_local
        self.n = V.dofmap.index_map.size_local
        # (views of the dofmaps, which they keep alive)
        self.cells = V.dofmap.list.array.reshape(-1, 3)[:nc]                   # int32
        self.dg = self.Q.dofmap.list.array.reshape(-1, 3)[:nc]
        self.area = triangle_areas(V.tabulate_dof_coordinates()[:, :2][self.cells])
        # N_l over all processes: owned cells counted locally, ghosts added to their owners
        count = fem.Function(V)
        count.x.array[:] = np.bincount(self.cells.ravel(), minlength=count.x.array.size)
        count.x.scatter_reverse(la.ScatterMode.add)
        count.x.scatter_forward()
        self.count = count.x.array.copy()
        self._R = fem.Function(V)

    def __call__(self, R, out=None):
        """The DG1 Function r_h of the owned residual R (numpy array of length n, or a PETSc
        Vec of owned size n), written into `out` if given."""
        from dolfinx import fem
        R = R.array_r if hasattr(R, "array_r") else np.asarray(R)
        self._R.x.array[:self.n] = R[:self.n]
        self._R.x.scatter_forward()
        r = out if out is not None else fem.Function(self.Q)
        # r_K = M_K⁻¹ (R_l / N_l)_{l ∈ K}: R_l / N_l once per vertex (owned and ghost; a
        # vertex of no local cell, N_l = 0, is never read), then gathered by the cells
        scaled = self._R.x.array
        np.divide(scaled, self.count, out=scaled, where=self.count > 0)
        values = scaled[self.cells]                                                 # (nc, 3)
        r.x.array[self.dg] = mass_inverse(self.area, values)
        r.x.scatter_forward()
        return r


def dg1_projections(disc, fs, lifting, moments=None):
    """Π_P1 f for each f of `fs` (η_osc, §7): the L² projections onto discontinuous P1 (cell
    by cell), as Functions of `lifting.Q`. The loads (f, q) are assembled in one pass (vector
    DG1 with a component per f, the data measures), unless `moments` gives them ((owned cells,
    3, len(fs)), (f, q_m)_K with the same measures, e.g. from `FluxEquilibration.loads`); the
    DG1 mass matrix is block diagonal with the block
    M_K = |K|/12 (I + 1 1ᵀ), whose inverse (`mass_inverse`) is applied cell by cell
    on the owned cells."""
    import ufl
    from dolfinx import fem, la

    from ..fem.quadrature import over
    from ..forms.estimators import projection_load
    mesh, k = disc.mesh, len(fs)
    nc = lifting.ncells
    if moments is not None:
        blocks = moments                                                       # (nc, 3, k)
    else:
        Z = fem.VectorFunctionSpace(mesh, ("DG", 1), dim=k)
        q = ufl.TestFunction(Z)
        b = fem.assemble_vector(fem.form(over(disc.dx_data, lambda dx: sum(
            projection_load(f, q[i], dx) for i, f in enumerate(fs)))))
        b.scatter_reverse(la.ScatterMode.add)
        blocks = b.array.reshape(-1, k)[Z.dofmap.list.array.reshape(-1, 3)[:nc]]
    out = []
    for i in range(k):
        pf = fem.Function(lifting.Q)
        pf.x.array[lifting.dg] = mass_inverse(lifting.area, blocks[:, :, i])
        pf.x.scatter_forward()
        out.append(pf)
    return out
