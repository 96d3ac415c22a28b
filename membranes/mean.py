"""The mean of the two membranes: one Poisson solve per mesh instead of a part of every Newton
step (DESIGN §2–§3; used with ``pc_type vertex_amg`` on the eliminated system).

**The mean does not see the contact.** Weighted by W (1/μ_α on interior rows, newton_system),
the two membrane rows of a vertex (DESIGN §2) combine with θ = μ2/(μ1 + μ2) into

    (1 - θ) r1 + θ r2 = (F1 + F2)/(μ1 + μ2) - S m,    m = (μ1 u1 + μ2 u2)/(μ1 + μ2),

λ cancelling; on a boundary vertex the Dirichlet rows give m = μ1 g/(μ1 + μ2). So the mean of
the discrete solution, and of every iterate that satisfies the membrane rows, is the solution
M of one Poisson problem,

    (μ1 + μ2) S M = F1 + F2 (interior vertices),   M = μ1 g/(μ1 + μ2) (boundary),

whatever the C-function and the contact set. The C-functions read u1 - u2 and λ only (DESIGN
§3), and a change of the mean alone (u1 and u2 moved by the same s, λ kept: in the eliminated
system, u1 and z moved by s where z = u2, u1 alone where z = λ, since u2 = u1 + d λ + const
there) changes only that combination of the residual, by S s. A Newton step therefore
splits exactly: its gap u2 - u1 and λ do not depend on the mean of X^{k-1}, and its mean is
M. `solve_step` (membranes.newton) uses that: it solves the step's system with the mean part
ρ = (1 - θ) r1 + θ r2 of the initial residual taken out of the right side (the solve then
starts with its mean settled, and vertex_amg's mean/gap split leaves the mean's V-cycles out:
`preconditioner.MeanGapAMG.settle_mean`, whose AMG on S is then never set up), and gives the
result the mean M (`with_mean`); its residual is computed anew from the system's own right
side, so whatever M lacks shows in R_alg (DESIGN §4) and the estimators.

**Why.** The mean's AMG (a Laplacian on all N vertices) was the dearest single part of a
level's first Newton step: at 9.3e5 vertices 0.86 s of its 3.3 s. M is solved once per level
here (`MeanSolve`: conjugate gradients, from the mean of the initial guess, on T_j, j ≥ 1, of
a nested run from P M_{j-1}, which is the mean of the prolonged solution and needs no wait
for level j-1's Newton run (membranes.driver), until ‖ρ(M)‖ is MEAN_FRACTION of the bound
the Newton steps' linear solves meet, `mean_bound`), and the Newton steps solve for the gap
and λ only. A Poisson problem on a nested hierarchy needs no algebraic multigrid: on T_j,
j ≥ 1, of a nested run CG takes one V-cycle of geometric multigrid on T_0 ⊂ … ⊂ T_j with
T_0's BoomerAMG at the bottom, and nothing is set up on the new mesh (9.3e5 vertices: 0.7 s
for M instead of 1.8 s; the whole serial run 17.7 s instead of 18.6-19.2 s). On several
processes (membranes.pipeline) process 0 solves for M too, while the estimator processes set
up the level's estimators.

This is one of the choices DESIGN.md leaves open (README): the Newton iterates are those of
DESIGN §3 with the mean of every step solved exactly, not those of GMRES on the whole step
from X^{k-1} (§8), which reaches the same mean to its tolerance.
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

MEAN_FRACTION = 0.01    # ‖ρ(M)‖ ≤ MEAN_FRACTION · the Newton steps' tightest linear bound
GAP_SHARE = 1.0 - np.sqrt(2.0) * MEAN_FRACTION   # what a step's solve leaves the gap and λ:
# M adds (ρ, ρ) to the residual, of norm √2 ‖ρ‖, so the step still meets its bound
MEAN_MAX_ITS = 200
_prefixes = iter(range(1 << 62))


def theta(problem):
    """θ = μ2/(μ1 + μ2): m = (1 - θ) u1 + θ u2."""
    return problem.mu2 / (problem.mu1 + problem.mu2)


def mean_of(X, n, th):
    """m = (1 - θ) u1 + θ u2 of X = (u1, u2, λ) (N values)."""
    return (1.0 - th) * X[:n] + th * X[n:2 * n]


class MeanSolve:
    """The Poisson problem of the module notes on `disc` (which needs its stiffness matrices):
    the interior block K = ((μ1 + μ2) S)_II and its right side, and the preconditioner of its
    conjugate gradients; `solve(m0)` gives M from the guess m0 (N values).

    On a single mesh, and on T_0 of a nested run, the preconditioner is one BoomerAMG V-cycle
    (`preconditioner.InnerAMG`, `inner`: vertex_amg's inner options). On T_j, j ≥ 1, given
    `coarser` (the MeanSolve of T_{j-1}) and P (the prolongation T_{j-1} → T_j,
    membranes.nested) it is one V-cycle of geometric multigrid on T_0 ⊂ … ⊂ T_j (`_multigrid`):
    no set-up on the new mesh beyond its matrix. At 9.3e5 vertices (disk, J = 6) the AMG took
    0.75-0.83 s to set up and 0.98-1.01 s for 9 CG iterations; the multigrid 0.05 s and
    0.61-0.75 s for 10, to the same M (1.7e-14 apart)."""

    def __init__(self, disc, inner=None, coarser=None, P=None):
        from .preconditioner import InnerAMG, principal_submatrix
        p = disc.problem
        n = disc.n
        interior = disc.interior
        self.n, self.inner_index = n, np.flatnonzero(interior)
        self.mu = p.mu1 + p.mu2
        self.boundary_value = np.zeros(n)
        self.boundary_value[disc.boundary] = p.mu1 * p.g / self.mu
        # S1 + S2 = (μ1 + μ2) S; where S2 is S1 (μ1 = μ2), 2 S1 without a second matrix
        S, factor = (disc.S1, 2.0) if disc.S2 is disc.S1 else (disc.S1 + disc.S2, 1.0)
        rhs = disc.F1 + disc.F2 - factor * (S @ self.boundary_value)
        self.rhs = rhs[self.inner_index]
        K = principal_submatrix(S, self.inner_index)
        K.data *= factor
        if coarser is None:
            self.amg = InnerAMG(K, inner)
            self.mat, self.pc = self.amg.mat, self.amg.pc
            self.levels = [(K, self.mat, self.pc)]
        else:
            from .linear_solve import petsc_matrix
            P_II = interior_prolongation(P, self.inner_index, coarser.inner_index)
            self.mat, P_mat = petsc_matrix(K, copy=False), petsc_matrix(P_II, copy=False)
            # the levels' matrices (and the arrays PETSc works on) and T_0's AMG pass from
            # level to level; the coarser MeanSolve is done with (its multigrid freed)
            if len(coarser.levels) > 1:
                coarser.pc.destroy()
            self.levels = coarser.levels + [(K, self.mat, P_II, P_mat)]
            self.amg, coarser.levels = coarser.amg, None
            self.pc = _multigrid(self.levels)

    def solve(self, m0, bound):
        """M from the guess m0: CG preconditioned by one V-cycle (symmetric: forward and
        backward sweeps, preconditioner.DEFAULT_INNER) until ‖ρ‖ ≤ bound, ρ = (F1 + F2 -
        (μ1 + μ2) S M)/(μ1 + μ2) the mean part of the weighted residual (module notes), at most
        MEAN_MAX_ITS iterations (where round-off stops it earlier, M is what CG reached: the
        Newton steps then also correct the mean)."""
        ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        x = np.array(m0, dtype=float)[self.inner_index]
        b, xv = (PETSc.Vec().createWithArray(v, comm=PETSc.COMM_SELF) for v in (self.rhs, x))
        try:
            ksp.setType(PETSc.KSP.Type.CG)
            ksp.setOperators(self.mat)
            ksp.setPC(self.pc)
            ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
            ksp.setTolerances(rtol=1e-30, atol=bound * self.mu, max_it=MEAN_MAX_ITS)
            ksp.setInitialGuessNonzero(True)
            ksp.solve(b, xv)
            self.its = ksp.getIterationNumber()
        finally:
            for obj in (b, xv, ksp):
                obj.destroy()
        M = self.boundary_value.copy()
        M[self.inner_index] = x
        return M

    def destroy(self):
        """Free the PETSc objects: the multigrid and the matrices of every level, and T_0's
        AMG (a MeanSolve whose levels a finer one took has nothing left to free)."""
        if self.levels is None:
            return
        if len(self.levels) > 1:
            self.pc.destroy()
            for _, mat, _, P_mat in self.levels[1:]:
                mat.destroy()
                P_mat.destroy()
        self.amg.destroy()
        self.levels = None


def interior_prolongation(P, fine_inner, coarse_inner):
    """P[fine_inner][:, coarse_inner] (CSR): the prolongation between the interior vertices
    (a coarse function that vanishes on the boundary prolongs to one that does: the fine
    boundary vertices lie on the coarse boundary edges)."""
    rows = P[fine_inner]
    column = np.full(P.shape[1], -1, dtype=np.int64)
    column[coarse_inner] = np.arange(len(coarse_inner))
    new = column[rows.indices]
    keep = new >= 0
    row_of = np.repeat(np.arange(rows.shape[0]), np.diff(rows.indptr))
    indptr = np.zeros(rows.shape[0] + 1, dtype=np.int64)
    np.cumsum(np.bincount(row_of[keep], minlength=rows.shape[0]), out=indptr[1:])
    return sp.csr_matrix((rows.data[keep], new[keep], indptr),
                         shape=(len(fine_inner), len(coarse_inner)))


def _multigrid(levels):
    """One V-cycle of geometric multigrid (PETSc PCMG) on levels [(K_0, mat, pc), (K_1, mat,
    P, P_mat), …]: on each finer level one forward Gauss–Seidel sweep down and one backward
    sweep up (symmetric: a CG preconditioner), the interpolations P, the operators K_j
    rediscretised (P1 on nested meshes: P^T K_j P = K_{j-1}), and on T_0 level 0's own
    preconditioner (its BoomerAMG V-cycle)."""
    pc = PETSc.PC().create(PETSc.COMM_SELF)
    pc.setType(PETSc.PC.Type.MG)
    pc.setMGLevels(len(levels))
    pc.setMGType(PETSc.PC.MGType.MULTIPLICATIVE)
    pc.setMGCycleType(PETSc.PC.MGCycleType.V)
    coarse = pc.getMGCoarseSolve()
    coarse.setType(PETSc.KSP.Type.PREONLY)
    coarse.setPC(levels[0][2])
    coarse.setOperators(levels[0][1])
    database = PETSc.Options()
    for j, (_, mat, _, P_mat) in enumerate(levels[1:], start=1):
        pc.setMGInterpolation(j, P_mat)
        for sweep, ksp in (("forward", pc.getMGSmootherDown(j)),
                           ("backward", pc.getMGSmootherUp(j))):
            ksp.setType(PETSc.KSP.Type.RICHARDSON)
            ksp.setTolerances(max_it=1)
            ksp.setNormType(PETSc.KSP.NormType.NONE)
            ksp.setOperators(mat)
            sor = ksp.getPC()
            sor.setType(PETSc.PC.Type.SOR)
            prefix = f"membranes_mean_{next(_prefixes)}_"
            sor.setOptionsPrefix(prefix)
            database[prefix + "pc_sor_" + sweep] = None
            try:
                sor.setFromOptions()
            finally:
                database.delValue(prefix + "pc_sor_" + sweep)
    pc.setOperators(levels[-1][1])
    pc.setUp()
    return pc


def mean_bound(rows, linear_tol):
    """The bound MeanSolve.solve meets: MEAN_FRACTION · linear_tol · ‖W F‖, linear_tol the
    tightest ‖R_alg‖/‖B‖ the Newton steps solve to (‖B‖ ≥ ‖W F‖): ρ(M) is then far below
    what `MeanGapAMG.settle_mean` takes as settled (MEAN_SETTLED = 0.5 of a step's bound)."""
    return MEAN_FRACTION * linear_tol * rows.norm_F


def exact_mean(disc, X0, bound, inner=None):
    """M of the module notes on `disc`, from the mean of the guess X0 (3N values), to ‖ρ‖ ≤
    bound."""
    solver = MeanSolve(disc, inner)
    try:
        return solver.solve(mean_of(X0, disc.n, theta(disc.problem)), bound)
    finally:
        solver.destroy()


@dataclass
class LevelMean:
    """What a Newton run needs of the mean: θ and M (N values)."""
    theta: float
    M: np.ndarray


def without_mean_residual(A, b, guess, th):
    """b - (ρ, ρ), ρ = (1 - θ) r1 + θ r2 of r = b - A guess: the right side whose residual at
    the guess has no mean part (module notes)."""
    r = b - A @ guess
    n = r.size // 2
    rho = (1.0 - th) * r[:n] + th * r[n:]
    return b - np.concatenate([rho, rho])


def with_mean(y, M, th, expand, z_is_u2):
    """The eliminated unknowns y (u1, z) moved by the mean change s = M - m(y) (u1 by s, z by
    s where z = u2; λ and the gap unchanged, module notes)."""
    n = y.size // 2
    s = M - mean_of(expand(y), n, th)
    out = np.array(y, dtype=float)
    out[:n] += s
    out[n:] += np.where(z_is_u2, s, 0.0)
    return out
