"""The decoupled form of the discrete problem, solved by PETSc SNES VI (DESIGN §10).

With z = μ1 u1 + μ2 u2 and w = u1 - u2 the discrete system of DESIGN §2 splits exactly into

    S z = F1 + F2,                             z = μ1 g on ∂Ω,
    κ S w - D λ = (μ2 F1 - μ1 F2)/(μ1 + μ2),    w = g on ∂Ω,   κ = μ1 μ2/(μ1 + μ2),
    w ≥ 0, λ ≥ 0, λ w = 0,

S the unit stiffness matrix. The second line is the nonlinear complementarity problem
Φ(w) = κ S w - G ⊥ w ≥ 0 (λ = D^{-1} Φ(w) at interior vertices), which PETSc's
`vinewtonrsls` solves with bounds w ≥ 0. This is a second solver of the same discrete problem,
independent of our Newton: used by the tests, and as the peer in benchmarks and in the report
(which follows its iterates through `monitor`).
"""

from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .linear_solve import petsc_matrix, solve_direct
from .newton import Stopwatch

DIRECT = {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
AMG = {"ksp_type": "cg", "pc_type": "hypre", "pc_hypre_type": "boomeramg", "ksp_rtol": 1e-12}


@dataclass
class DecoupledResult:
    u1: np.ndarray
    u2: np.ndarray
    lam: np.ndarray
    converged: bool
    reason: str
    newton_iterations: int
    linear_iterations: int
    wall_time_s: float


def _dirichlet_rows(S, boundary):
    """S with the rows of boundary vertices replaced by identity rows."""
    import scipy.sparse as sp
    n = S.shape[0]
    bmask = np.zeros(n)
    bmask[boundary] = 1.0
    return (sp.diags(1.0 - bmask) @ S + sp.diags(bmask)).tocsr()


def solve_decoupled(disc, ksp_options=None, rtol=1e-14, atol=None, max_it=500, monitor=None):
    """Solve the decoupled problem of `disc` with SNES vinewtonrsls; returns u1, u2, λ nodal.

    ksp_options: PETSc options of the inner linear solves (default: MUMPS LU); AMG gives
    CG with hypre BoomerAMG. Convergence: ‖Φ‖ ≤ max(atol, rtol ‖Φ(w⁰)‖) on the VI-reduced
    residual, atol defaulting to 1e-13 ‖G‖. monitor(its, seconds, u1, u2, λ), if given, sees
    every SNES iterate (its = 0: the initial guess) with the wall time so far; building the
    iterate's u1, u2, λ and the monitor itself are not counted, there nor in `wall_time_s`.
    """
    clock = Stopwatch()
    p = disc.problem
    mu1, mu2, g = p.mu1, p.mu2, p.g
    kappa = mu1 * mu2 / (mu1 + mu2)
    S = disc.S1 / mu1
    n, boundary = disc.n, disc.boundary
    interior = disc.interior
    S_dir = _dirichlet_rows(S, boundary)

    # z: one linear solve
    rhs_z = disc.F1 + disc.F2
    rhs_z[boundary] = mu1 * g
    z, _ = solve_direct(S_dir, rhs_z)

    # w: the complementarity problem Φ(w) = κ S w - G ⊥ w ≥ 0, Dirichlet rows w - g
    G = (mu2 * disc.F1 - mu1 * disc.F2) / (mu1 + mu2)
    G[boundary] = g
    K = (kappa * S).tocsr()
    K = _dirichlet_rows(K, boundary)
    J = petsc_matrix(K)

    def residual(snes, w, f):
        f.array[:] = K @ w.array_r - G

    def jacobian(snes, w, A, P):
        return True  # constant

    snes = PETSc.SNES().create(PETSc.COMM_SELF)
    prefix = "membranes_vi_"
    snes.setOptionsPrefix(prefix)
    opts = PETSc.Options()
    options = {"snes_linesearch_type": "basic", **(DIRECT if ksp_options is None else ksp_options)}
    for k, v in options.items():
        opts[prefix + k] = v
    f = J.createVecLeft()
    snes.setFunction(residual, f)
    snes.setJacobian(jacobian, J, J)
    snes.setType("vinewtonrsls")
    lower = J.createVecRight()
    lower.array[:] = 0.0
    upper = J.createVecRight()
    upper.array[:] = PETSc.INFINITY
    snes.setVariableBounds(lower, upper)
    atol = 1e-13 * float(np.linalg.norm(G)) if atol is None else atol
    snes.setTolerances(rtol=rtol, atol=atol, stol=0.0, max_it=max_it)
    snes.setFromOptions()

    def fields(w):
        """u1, u2, λ (nodal) from w and z."""
        lam = np.zeros(n)
        lam[interior] = (K @ w - G)[interior] / disc.D[interior]
        return (z + mu2 * w) / (mu1 + mu2), (z - mu1 * w) / (mu1 + mu2), lam

    def snes_monitor(snes, its, fnorm):
        seconds = clock.pause()
        monitor(its, seconds, *fields(snes.getSolution().array_r))
        clock.resume()

    if monitor is not None:
        snes.setMonitor(snes_monitor)
    w = J.createVecRight()
    w.array[:] = g                       # the paper's start: u1 = g, u2 = 0
    try:
        snes.solve(None, w)
        reason_code = snes.getConvergedReason()
        its, lin = snes.getIterationNumber(), snes.getLinearSolveIterations()
        wv = w.array.copy()
    finally:
        for k in options:
            del opts[prefix + k]
        snes.destroy()
        J.destroy()
    wall_time = clock.pause()
    u1, u2, lam = fields(wv)
    converged = reason_code > 0
    reason = f"SNES converged reason {reason_code}" if converged else \
        f"SNES diverged (reason {reason_code})"
    return DecoupledResult(u1, u2, lam, converged, reason, its, lin, wall_time)
