"""The SNES VI peer: PETSc's `vinewtonrsls` on the decoupled problem, distributed (§10).

With z = μ1 u1 + μ2 u2 and w = u1 - u2 the discrete system of §2 splits exactly into

    S z = F1 + F2,                                      z = μ1 g on ∂Ω,
    κ S w - D λ = b,  b = (μ2 F1 - μ1 F2)/(μ1 + μ2),    w = g on ∂Ω,   κ = μ1 μ2/(μ1 + μ2),
    w ≥ 0,  λ ≥ 0,  λ w = 0,

S the unit stiffness matrix and D the lumped contact weights (ψ_a, 1). The first line is a
Poisson problem (CG + BoomerAMG). The second is the complementarity problem

    Φ(w) = κ S w - b  ⊥  w ≥ 0,        λ = D⁻¹ Φ(w) on the active set, 0 elsewhere,

which PETSc's reduced-space active-set Newton (`vinewtonrsls`) solves with the bounds
0 ≤ w < ∞, its reduced linear systems by CG + BoomerAMG. Both BoomerAMGs take `AMG_OPTIONS`:
the smoothing sweeps of ours' inner preconditioners (membranes.linalg.preconditioners.SWEEPS)
and aggressive coarsening (HMIS with one aggressive level, extended+i interpolation of at most
4 entries a row), a cheaper set-up and V-cycle for more CG steps. With them the nested peer
is faster than with PETSc's defaults (BENCHMARKS.md): they are what a competent user tuning
BoomerAMG for these P1 Laplacians would choose. This is the peer to beat (§10): an independent
solver of the same discrete problem, run as a competent PETSc user would run it.

* **nested** (`nested_peer`): over the levels T_0, …, T_J of the problem's hierarchy, each
  level solved from the P1 prolongation of the last level's (z, w). PETSc's own
  `-snes_grid_sequence` needs a refinable DM, which dolfinx does not attach, so the loop over
  levels is written here with the hierarchy's prolongations.
* **plain** (`plain_peer`): the finest mesh only, from w = 0 at the interior vertices (and g on
  ∂Ω), z from zero. Kept for comparison. Its SNES steps grow roughly like 1/h, so it may
  take more than PETSc's default limit of 50 steps: its limit is PLAIN_MAX_IT.
* **certified** (`certify`): our estimators set up on a peer's finest mesh and evaluated once
  at its final iterate, so that its answer carries the guaranteed bound of §7 as well: what
  the report and the benchmarks compare ours with.

The nested and the plain peer stop SNES at PETSc's default relative tolerance 1e-8 (of the
VI-reduced residual norm, relative to its value at the level's initial guess) and leave every
other PETSc default but BoomerAMG's (backtracking line search, KSP rtol 1e-5 of the reduced
systems, stol 1e-8) unless `options` changes it; the z solve's KSP stops at rtol relative to
its preconditioned right side.

**Stopping** (`_converged`). PETSc's convergence test for VI solvers, unlike its Newton's,
ignores stol: a level whose initial guess is already the discrete solution (zero loads: the
prolongation is exact) starts at a round-off residual that it cannot reduce by rtol, and SNES
took all its steps to end DIVERGED_MAX_IT. The test here is PETSc's VI test plus its stol test,
the latter only where the residual is also below rtol times the largest initial residual of
the run's levels so far (a step that no longer moves w, at a residual the run's own tolerance
accepts: CONVERGED_SNORM_RELATIVE); a stagnating step at a larger residual does not stop SNES.

**Boundary rows.** The Dirichlet vertices keep their rows in the SNES unknown: the residual
there is κ (w_a - g), and the Jacobian is κ S with the rows *and columns* of ∂Ω replaced by
κ times the identity (`MatZeroRowsColumns`: symmetric, so CG applies). Every initial guess
is given w = g on ∂Ω (the prolongation of a level's w has these values already: it
reproduces constants, and new boundary vertices halve boundary edges), so the boundary
residual vanishes, the Newton step is zero there and the dropped columns do not change the
step: it is Newton's step for the interior unknowns.

**Back to the iterate of §2.** u1 = (z + μ2 w)/(μ1 + μ2), u2 = (z - μ1 w)/(μ1 + μ2) and λ give
the iterate layout [u1 | u2 | λ] of `Discretisation` (`to_iterate`): μ1 u1 + μ2 u2 = z and
u1 - u2 = w, and the boundary values g, 0 come out to round-off.

**Active set.** PETSc counts vertex a active at the lower bound when w_a ≤ 1e-8 and
Φ_a ≥ 0 (an absolute threshold in SNESVIGetActiveSetIS) and gives it a zero step; λ is
recovered on that set, where w = 0 after PETSc's projection onto the bounds in practice
(the tests check λ w = 0).

**Units.** Because that threshold is absolute, SNES solves for w / s, s = `gap_scale` (the size
the data give w: max(g, (C_PF h_Ω)² max b_a⁺/(κ D_a)), §11), with data b / s and g / s; the
problem is positively homogeneous, so this is the same problem, and w, λ are scaled back.
Without it a gap of g ≤ 1e-6 (the radial scene) put vertices with 0 < w_a ≤ 1e-8 into the
active set, frozen off the bound, and the nested peer reported convergence at an iterate far
from the discrete solution (BENCHMARKS.md, robustness: "the peer at small g"). PETSc options
that set absolute sizes (snes_atol) act on w / s.
"""

import time
from dataclasses import dataclass, field

import numpy as np

# The peer's BoomerAMG options (module notes), below a user's `options`; with ours' SWEEPS
AMG_OPTIONS = {"pc_hypre_boomeramg_coarsen_type": "HMIS", "pc_hypre_boomeramg_agg_nl": "1",
               "pc_hypre_boomeramg_interp_type": "ext+i", "pc_hypre_boomeramg_P_max": "4"}
# PETSc's threshold of SNESVIGetActiveSetIS: x_a ≤ lower_a + 1e-8 counts as at the bound.
PETSC_VI_ACTIVE_TOL = 1e-8
# The plain peer's SNES step limit. From zero, the active set moves by a few layers of
# vertices per step, so the steps grow roughly like 1/h: PETSc's default of 50 stops it before
# it converges on the disk beyond ~1e5 vertices.
PLAIN_MAX_IT = 10000


@dataclass
class LevelRecord:
    """One level of a peer run: its size, PETSc's counts and the times spent."""
    level: int
    vertices: int
    snes_iterations: int
    ksp_iterations: int         # CG steps of the reduced SNES systems
    z_iterations: int           # CG steps of the z solve
    reason: int                 # SNES converged reason (> 0 converged)
    z_reason: int               # KSP converged reason of the z solve
    active: int                 # vertices with λ > 0 at the end
    wall_time_s: float          # solver work: prolongation, operators, solves, λ
    setup_time_s: float         # discretisation of the level (dolfinx assembly)


@dataclass
class PeerResult:
    """A peer run. `X` is the finest level's (u1, u2, λ) in the iterate layout of `disc`;
    z, w, lam the decoupled unknowns (PETSc Vecs, owned entries)."""
    label: str                  # "nested" or "plain"
    disc: object                # the finest level's Discretisation
    X: object
    z: object
    w: object
    lam: object
    levels: list = field(default_factory=list)

    @property
    def snes_iterations(self):
        return sum(r.snes_iterations for r in self.levels)

    @property
    def ksp_iterations(self):
        """CG steps of all SNES systems and z solves."""
        return sum(r.ksp_iterations + r.z_iterations for r in self.levels)

    @property
    def wall_time_s(self):
        """Solver work over all levels (discretisation not included: `setup_time_s`)."""
        return sum(r.wall_time_s for r in self.levels)

    @property
    def setup_time_s(self):
        return sum(r.setup_time_s for r in self.levels)

    @property
    def converged(self):
        return all(r.reason > 0 and r.z_reason > 0 for r in self.levels)

    @property
    def reason(self):
        """PETSc's converged reason of the finest level's SNES, in words."""
        from petsc4py import PETSc
        code = self.levels[-1].reason
        names = {v: k for k, v in vars(PETSc.SNES.ConvergedReason).items()
                 if isinstance(v, int)}
        return f"{names.get(code, 'UNKNOWN')} ({code})"


def to_iterate(disc, z, w, lam, X=None):
    """The iterate (u1, u2, λ) of §2 in the layout of `disc` (a new PETSc Vec, or `X`) from
    the decoupled unknowns (PETSc Vecs or arrays of the owned entries):
    u1 = (z + μ2 w)/(μ1 + μ2), u2 = (z - μ1 w)/(μ1 + μ2)."""
    mu1, mu2 = disc.mu1, disc.mu2
    z, w, lam = (v.array_r if hasattr(v, "array_r") else np.asarray(v) for v in (z, w, lam))
    X = disc.vector3() if X is None else X
    X.setArray(np.concatenate([(z + mu2 * w) / (mu1 + mu2), (z - mu1 * w) / (mu1 + mu2), lam]))
    return X


class DecoupledSolver:
    """The decoupled problem of one discretisation (§10), set up for PETSc: `solve_z` and
    `solve_w` solve the two lines from given initial guesses (PETSc Vecs of the owned P1
    dofs, overwritten by the solutions).

    ksp, pc: the Krylov method and preconditioner of both the z solve and SNES's reduced
    systems ('hypre' means BoomerAMG). rtol: the z solve's KSP tolerance and SNES's.
    options: further PETSc options (without '-') for the SNES and its KSP, e.g.
    {"snes_stol": 0, "ksp_rtol": 1e-10}, on top of BoomerAMG's `AMG_OPTIONS` (the z solve takes
    those alone); they are set under a private prefix and removed."""

    _count = 0

    def __init__(self, disc, rtol=1e-8, ksp="cg", pc="hypre", options=None, max_it=None,
                 reference=None):
        from petsc4py import PETSc
        self.disc = disc
        # [largest initial residual norm so far]: the levels of one run share it (_converged)
        self.reference = [0.0] if reference is None else reference
        self.rtol, self.ksp_type, self.pc_type, self.max_it = rtol, ksp, pc, max_it
        self.options = dict(options or {})
        mu1, mu2 = disc.mu1, disc.mu2
        self.kappa = mu1 * mu2 / (mu1 + mu2)
        S = disc.S
        # owned boundary dofs, by local and by global index
        self.bl = disc.boundary_owned
        self.bg = disc.V.dofmap.index_map.local_to_global(self.bl).astype(PETSc.IntType)
        # right sides: F1 + F2 for z, b = (μ2 F1 - μ1 F2)/(μ1 + μ2) for w
        F1, F2 = disc.F1.array_r, disc.F2.array_r
        self.rhs_z = S.createVecLeft()
        self.rhs_z.setArray(F1 + F2)
        self.b = S.createVecLeft()
        self.b.setArray((mu2 * F1 - mu1 * F2) / (mu1 + mu2))
        self.D = disc.D.array_r.copy()
        self.interior = disc.interior
        self.scale = gap_scale(disc, self.kappa, self.b.array_r, self.D)
        self._A = None

    # ## z: the Poisson problem S z = F1 + F2, z = μ1 g on ∂Ω
    def solve_z(self, z):
        """CG + BoomerAMG on S with the boundary rows and columns eliminated
        (MatZeroRowsColumns moves the known boundary values to the right side)."""
        from petsc4py import PETSc
        disc = self.disc
        self._A = A = disc.S.copy()
        z.array[self.bl] = disc.mu1 * disc.g
        rhs = self.rhs_z.copy()
        A.zeroRowsColumns(self.bg, 1.0, z, rhs)
        from ..linalg.preconditioners import put_options, take_options
        ksp = PETSc.KSP().create(disc.comm)
        prefix, options = self._prefix(), self._amg()
        ksp.setOptionsPrefix(prefix)
        put_options(prefix, options)
        try:
            self._ksp(ksp).setFromOptions()
            ksp.setOperators(A)
            ksp.setTolerances(rtol=self.rtol)
            ksp.setInitialGuessNonzero(True)
            ksp.solve(rhs, z)
        finally:
            take_options(prefix, options)
        its, reason = ksp.getIterationNumber(), ksp.getConvergedReason()
        ksp.destroy()
        rhs.destroy()
        return its, reason

    # ## w: the complementarity problem Φ(w) = κ S w - b ⊥ w ≥ 0
    def solve_w(self, w, monitor=None):
        """SNES vinewtonrsls from w (whose boundary entries must be g); returns
        (SNES iterations, CG iterations, converged reason, λ as a PETSc Vec).
        monitor(its, w) sees every SNES iterate (its = 0: the initial guess)."""
        from petsc4py import PETSc
        disc, kappa, bl = self.disc, self.kappa, self.bl
        S = disc.S
        # the Jacobian κ S, boundary rows and columns κ × identity: reuse the z matrix
        J = self._A if self._A is not None else self._boundary_eliminated()
        self._A = None
        J.scale(kappa)

        # SNES works on w / s (module docstring, Units): data b / s, boundary values g / s
        scale = self.scale
        b, g = self.b.copy(), disc.g / scale
        b.scale(1.0 / scale)
        w.scale(1.0 / scale)

        def residual(snes, x, f):
            S.mult(x, f)                                   # f = κ S w - b
            f.scale(kappa)
            f.axpy(-1.0, b)
            with f as fa:
                fa[bl] = kappa * (x.array_r[bl] - g)       # boundary rows κ (w - g)

        snes = PETSc.SNES().create(disc.comm)
        prefix = self._prefix()
        snes.setOptionsPrefix(prefix)
        snes.setType("vinewtonrsls")
        f = S.createVecLeft()
        snes.setFunction(residual, f)
        snes.setJacobian(lambda snes, x, A, P: None, J, J)   # constant
        lower, upper = w.duplicate(), w.duplicate()
        lower.set(0.0)
        upper.set(PETSc.INFINITY)
        snes.setVariableBounds(lower, upper)
        snes.setTolerances(rtol=self.rtol, max_it=self.max_it)
        snes.setConvergenceTest(_converged, args=(self.reference, [0.0]))
        self._ksp(snes.getKSP())
        if monitor is not None:
            snes.setMonitor(lambda s, its, fnorm: monitor(its, _scaled(s.getSolution(), scale)))
        from ..linalg.preconditioners import put_options, take_options
        options = {**self._amg(), **self.options}            # the user's on top
        put_options(prefix, options)
        try:
            snes.setFromOptions()
            snes.solve(None, w)
        finally:
            take_options(prefix, options)
        its, lin = snes.getIterationNumber(), snes.getLinearSolveIterations()
        reason = snes.getConvergedReason()
        snes.setConvergenceTest("default")              # (drops the Python callable)
        residual(snes, w, f)
        w.scale(scale)
        f.scale(scale)
        lam = self.multiplier(w, f)
        for obj in (snes, f, lower, upper, J, b):
            obj.destroy()
        return its, lin, reason, lam

    def multiplier(self, w, f=None):
        """λ = Φ(w)/D on PETSc's active set (w_a ≤ 1e-8 s and Φ_a ≥ 0, interior), 0 elsewhere;
        f: Φ(w) if already computed."""
        disc = self.disc
        if f is None:
            f = disc.S.createVecLeft()
            disc.S.mult(w, f)
            f.scale(self.kappa)
            f.axpy(-1.0, self.b)
        phi, wa = f.array_r, w.array_r
        active = (wa <= PETSC_VI_ACTIVE_TOL * self.scale) & (phi >= 0.0) & self.interior
        lam = f.duplicate()
        lam.setArray(np.where(active, phi / self.D, 0.0))
        return lam

    def active(self, lam):
        """How many vertices carry λ > 0 (PETSc's active set less any with Φ_a = 0)."""
        from mpi4py import MPI
        n = int(np.count_nonzero(lam.array_r > 0.0))
        return self.disc.comm.allreduce(n, op=MPI.SUM)

    def _boundary_eliminated(self):
        A = self.disc.S.copy()
        A.zeroRowsColumns(self.bg, 1.0)
        return A

    @staticmethod
    def _prefix():
        """A PETSc options prefix of its own for each solver object."""
        prefix = f"membranes_peer{DecoupledSolver._count}_"
        DecoupledSolver._count += 1
        return prefix

    def _amg(self):
        """BoomerAMG's options where the PC is 'hypre' (ours' SWEEPS and `AMG_OPTIONS`), else
        none."""
        from ..linalg.preconditioners import SWEEPS
        return {**SWEEPS, **AMG_OPTIONS} if self.pc_type == "hypre" else {}

    def _ksp(self, ksp):
        ksp.setType(self.ksp_type)
        pc = ksp.getPC()
        pc.setType(self.pc_type)
        if self.pc_type == "hypre":
            pc.setHYPREType("boomeramg")
        return ksp


def gap_scale(disc, kappa, b, D):
    """s = max(g, (C_PF h_Ω)² max b_a⁺ / (κ D_a)) over the interior vertices: the size the
    data give the gap w (as `Discretisation.data_scales` for u1, u2, §11). Only b⁺ counts:
    w is at most the solution of κ S v = b⁺, v = g on ∂Ω (a supersolution), and where b < 0
    the contact pressure carries the load (μ1 ≪ μ2 makes b/κ large there). Collective."""
    from mpi4py import MPI
    inner = disc.interior
    m = disc.comm.allreduce(float((np.maximum(b[inner], 0.0) / D[inner]).max(initial=0.0)),
                            op=MPI.MAX)
    return max(disc.problem.g, disc.poincare ** 2 * m / kappa)


def _scaled(v, scale):
    """A copy of the PETSc Vec v times `scale`."""
    u = v.copy()
    u.scale(scale)
    return u


def _converged(snes, its, norms, reference, ttol):
    """PETSc's convergence test of VI solvers (SNESConvergedDefault_VI: NaN, atol, function
    count, rtol of the initial residual) plus its stol test where the residual is at most rtol
    times `reference[0]`, the largest initial residual of the run so far (module docstring);
    ttol[0]: rtol times this SNES's initial residual."""
    from petsc4py import PETSc
    R = PETSc.SNES.ConvergedReason
    xnorm, ynorm, fnorm = norms
    rtol, atol, stol, _ = snes.getTolerances()
    if its == 0:
        ttol[0] = rtol * fnorm
        reference[0] = max(reference[0], fnorm)
    if not np.isfinite(fnorm):
        return R.DIVERGED_FNORM_NAN
    if fnorm < atol:
        return R.CONVERGED_FNORM_ABS
    max_funcs = snes.getMaxFunctionEvaluations()
    if 0 <= max_funcs <= snes.getFunctionEvaluations():
        return R.DIVERGED_FUNCTION_COUNT
    if its and fnorm < ttol[0]:
        return R.CONVERGED_FNORM_RELATIVE
    if its and ynorm < stol * xnorm and fnorm <= rtol * reference[0]:
        return R.CONVERGED_SNORM_RELATIVE
    return R.CONVERGED_ITERATING


def _run(label, problems, progress, monitor, **settings):
    """Solve the decoupled problem on each of `problems` (a list of callables giving the
    level's Discretisation), each level from the prolongation of the last."""
    records, prev, reference = [], None, [0.0]
    for j, make in enumerate(problems):
        disc, setup = make()
        t0 = time.perf_counter()
        solver = DecoupledSolver(disc, reference=reference, **settings)
        z, w = disc.S.createVecRight(), disc.S.createVecRight()
        if prev is None:                                   # from zero (g on ∂Ω)
            z.set(0.0)
            w.set(0.0)
        else:                      # P1 prolongation (§10; made at its first use, timed)
            P, (zc, wc) = make.prolongation, prev
            P.mult(zc, z)
            P.mult(wc, w)
            zc.destroy()
            wc.destroy()
        w.array[solver.bl] = disc.g
        z_its, z_reason = solver.solve_z(z)
        clock = [t0, 0.0]                                  # start, wall paused

        def snes_monitor(its, wv, disc=disc, z=z, level=j, clock=clock, solver=solver):
            paused = time.perf_counter()
            monitor(level, its, paused - clock[0] - clock[1], disc,
                    to_iterate(disc, z, wv, solver.multiplier(wv)))
            clock[1] += time.perf_counter() - paused

        its, lin, reason, lam = solver.solve_w(w, snes_monitor if monitor else None)
        wall = time.perf_counter() - t0 - clock[1]
        rec = LevelRecord(j, disc.n_global, its, lin, z_its, reason, z_reason,
                          solver.active(lam), wall, setup)
        records.append(rec)
        if progress is not None:
            progress(f"peer ({label}) level {j}: {rec.vertices} vertices, "
                     f"{its} SNES steps ({lin} CG), z: {z_its} CG, active {rec.active}, "
                     f"reason {reason}, {wall:.3f} s (+ {setup:.3f} s discretisation)")
        if j + 1 < len(problems):
            prev = (z, w)
            lam.destroy()
    t0 = time.perf_counter()
    X = to_iterate(disc, z, w, lam)
    records[-1].wall_time_s += time.perf_counter() - t0
    return PeerResult(label, disc, X, z, w, lam, records)


class _Level:
    """Level j of `problem`: calling it gives (its Discretisation, the seconds spent making it:
    0 for one given); `prolongation` is P_j, from level j-1 into this one."""

    def __init__(self, problem, j, disc=None):
        self.problem, self.j, self.disc = problem, j, disc

    @property
    def prolongation(self):
        return self.problem.hierarchy.prolongation(self.j)

    def __call__(self):
        from ..fem.discretisation import discretise
        if self.disc is not None:
            return self.disc, 0.0
        t0 = time.perf_counter()
        disc = discretise(self.problem.on_level(self.j))
        return disc, time.perf_counter() - t0


def nested_peer(problem, rtol=1e-8, ksp="cg", pc="hypre", options=None, max_it=None,
                progress=None, monitor=None):
    """The competent peer of §10: SNES vinewtonrsls (`ksp` + `pc` inside, SNES rtol `rtol`)
    on the decoupled problem over the levels 0..J of `problem.hierarchy`, level 0 from zero,
    each next level from the P1 prolongation of the last level's z and w.

    max_it: SNES steps per level (None: PETSc's default, 50). progress(line): one line per
    level. monitor(level, its, seconds, disc, X): every SNES
    iterate (its = 0: the initial guess) as an iterate X of §2 on that level's `disc`, with
    the solver time of the level so far; building X and the monitor are not timed."""
    levels = [_Level(problem, j) for j in range(problem.hierarchy.levels + 1)]
    return _run("nested", levels, progress, monitor, rtol=rtol, ksp=ksp, pc=pc,
                options=options, max_it=max_it)


def plain_peer(problem, rtol=1e-8, ksp="cg", pc="hypre", options=None, max_it=PLAIN_MAX_IT,
               progress=None, monitor=None):
    """The plain peer: SNES vinewtonrsls on the finest mesh only, from w = 0 at the interior
    vertices (g on ∂Ω) and z = 0, to its own convergence (`max_it` SNES steps at most:
    PLAIN_MAX_IT). `problem` may be a Problem (its finest level is discretised) or a
    Discretisation (used as it is; no set-up time then). Other arguments as `nested_peer`."""
    from ..fem.discretisation import Discretisation
    if isinstance(problem, Discretisation):
        level = _Level(problem.problem, problem.problem.hierarchy.levels, problem)
    else:
        level = _Level(problem, problem.hierarchy.levels)
    return _run("plain", [level], progress, monitor, rtol=rtol, ksp=ksp, pc=pc,
                options=options, max_it=max_it)


def certify(result):
    """The certified peer's certificate (§10): our estimators set up on the peer's finest mesh
    and evaluated once at its final iterate X, with R the residual of X's linear rows
    (`final_residual`, §4): what a user who wants a guaranteed bound for the peer's answer
    runs after it. The data parts are made in the set-up (`eager_data`: the evaluation
    follows at once). Returns (estimates, set-up seconds, seconds in all)."""
    from ..estimation.equilibration import FluxEquilibration
    from ..estimation.estimators import Estimators
    from ..nonlinear.system import final_residual
    t = time.perf_counter()
    disc = result.disc
    est = Estimators(disc, FluxEquilibration(disc.V, disc.dx_data), eager_data=True)
    setup = time.perf_counter() - t
    out = est.evaluate(result.X, final_residual(disc, result.X, "min"))
    return out, setup, time.perf_counter() - t
