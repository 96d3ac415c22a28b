"""Krylov solvers of the Newton systems through PETSc KSP: presets, options, stopping tests
(§3, §4, §8, §12).

**Presets** (`PRESETS`), each a Newton system and a set of PETSc options; the user's options
(a dict, names without '-') go on top, under a prefix of their own per solver
(``membranes_<k>_``), so that they reach this solver's KSP (and its inner PCs) only:

* ``paper``: GMRES (restart 30, PETSc's) on the full 3N system, preconditioned on the right
  by ILU(0), with the unpreconditioned norm (GMRES minimises ‖B - A X‖ itself), as in the
  paper (§8). In parallel PETSc's ILU is block Jacobi: ``pc_type bjacobi`` with one block per
  process and ILU(0) inside it, i.e. the paper's ILU(0) on each process's diagonal block of the
  matrix (its own u1, u2 and λ rows); on one process it *is* the paper's ILU(0). The iteration
  counts grow with P as the blocks decouple. ILU's zero-pivot threshold is 0 (only an exactly
  zero pivot is a breakdown; so for every ``ilu`` of the user's, unless the user
  sets ``pc_factor_zeropivot``): PETSc's default declares a pivot zero below the absolute
  100 ε ≈ 2.2e-14, but every entry of the λ column (D/μ_α, κ ∂C/∂b), and so every λ pivot
  (about κ h²), carries the unit 1/μ. Scaling μ1, μ2, f1, f2 by c scales that column by 1/c
  and leaves u unchanged (§11); ILU(0) and right-preconditioned GMRES are invariant under
  column scaling, so the whole run is, save for that test, which broke it at large moduli
  (BENCHMARKS.md, Robustness, "ILU's pivots").
* ``direct``: MUMPS, distributed LU of the full 3N system (``preonly``, ``lu``), analysed
  anew at every step, with ICNTL(14) = 100 (100 % more working memory than its analysis
  estimates): the zero λ-diagonal of a min contact vertex makes MUMPS delay pivots, which
  outgrew its default 20 % (INFOG(1) = -9). MUMPS's own scaling is off (ICNTL(8) = 0): its
  default, an iterative row and column equilibration, is not invariant under the 1/μ of the
  λ column, and at extreme moduli it left an algebraic error that dominated η (BENCHMARKS.md,
  Robustness, "MUMPS's scaling"). Unscaled, the run is that of μ = 1 scaled, on one process
  and on several (MUMPS's column scalings, 3 and 4, act as 0 on a distributed matrix); the
  price is a little more round-off in η_alg, still far below η. A direct solve is held to the
  same test as a Krylov one (exact: ‖R_alg‖ ≤ 2e-12 ‖B‖, §8): where the back-solve leaves more,
  iterative refinement with the same factors (`refine`) goes on while each step halves the
  residual. A solve that stops above the bound at the round-off of its factors is as exact as
  the arithmetic allows and is taken (on strongly graded meshes that floor lies above 2e-12,
  where an exact Krylov solve cannot stop); one whose refinement steps ran out has failed.
* ``amg`` (the default): FGMRES on the eliminated 2N system, preconditioned by the mean/gap
  split of §10 with one BoomerAMG V-cycle on the mean and one on the gap (`preconditioners.
  MeanGapPC`; for Newton-min and Fischer–Burmeister alike). Iterations per Newton step do not
  grow with the mesh. The split reads no entry of the eliminated matrix, which is then the
  operator W E (T Y) (`membranes.nonlinear.system`). The user's ``pc_type`` replaces the split
  by a PETSc PC on the eliminated matrix, then assembled (``ilu``, ``lu``; BoomerAMG on the
  whole eliminated matrix stagnated on the disk once contact vertices carried z = λ, see
  docs/cli.md: the reason for the split).

FGMRES keeps the preconditioned basis, so building an iterate costs no extra PC application;
for a fixed preconditioner it is right-preconditioned GMRES.

**Stopping tests** (`StoppingTest`, installed by `ksp.setConvergenceTest`). PETSc's own test
compares with rtol ‖b‖, but the eliminated system's right-hand side is not B, and the inexact
tolerance is met by the initial guess itself. Ours is ‖R_alg‖ ≤ tol ‖B‖ (both weighted, B the
right side of the 3N system, so that both systems are measured alike), tested after the
iterations that are multiples of `every`:

* exact (§8): tol = `EXACT_TOL` = 2e-12, every iteration (and the initial guess);
* inexact (§8): tol = ‖R_lin(X^{k-1})‖/‖(F, 0)‖ (or EXACT_TOL, if larger), every ν
  iterations from i = ν. On the full system the initial guess X^{k-1} meets it
  (B - A X^{k-1} = R_lin(X^{k-1}) and ‖B‖ ≥ ‖(F, 0)‖), so that it is not tested, and GMRES,
  whose residual never grows, meets it at i = ν (the paper's 10 per step). On the eliminated
  system the initial guess is X^{k-1} with its eliminated unknowns (λ_l or u2_l) replaced
  from the new linearisation: its residual is not R_lin(X^{k-1}) and need not meet the
  bound, so the test may pass only at a later multiple of ν;
* adaptive (§8): the exact floor, and every ν iterations the callback `on_iterate(i, y, r)`
  with the current iterate y (`ksp.buildSolution`) and its weighted residual r = b - A y; it
  returns True to stop (η_alg ≤ γ_alg max(η_disc, η_lin) is decided by the Newton loop, which
  holds the estimators).

GMRES's recursive residual estimate (the `rnorm` of the test, the unpreconditioned norm) only
gates the test: where it says converged, the iterate is built and b - A y computed, and the
solve goes on while the true residual is above the bound (it drifts from the estimate near
round-off). With a preconditioned norm (set through the options) the true residual is computed
at every test. Where the estimate is below the bound but the true residual has not halved in
`STAGNATION` iterations, the two have parted for good: the iterates' updates are below the
round-off of the true residual (the attainable accuracy of the Krylov recurrences), and no
further iteration reaches the bound. The solve then ends as failed ("stagnated at
round-off"), not after `max_it` iterations (on strongly graded meshes the exact bound 2e-12
lies below that floor: BENCHMARKS.md, Robustness). It is not taken as converged: unlike a
direct solve's floor (`refine`), this one is the method's, not the arithmetic's.
The tolerances, not PETSc's rtol, decide: ``ksp_rtol``, ``ksp_atol``,
``ksp_max_it`` are refused (the limit is `max_it`).
"""

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from ..model.checks import positive_integer
from ..model.petsc_options import option_value
from .preconditioners import (
    INNER_DEFAULTS,
    InnerPC,
    MeanGapPC,
    configure,
    gap_operator,
    inner_defaults,
    petsc_message,
    put_options,
    take_options,
)

EXACT_TOL = 2e-12          # exact Newton: ‖R_alg‖/‖B‖ ≤ 2e-12 at every step (§8)
REFINEMENTS = 10           # iterative refinement steps of a direct solve, at most (`refine`)
STAGNATION = 100           # iterations of a converged estimate without the true residual
#                            halving, after which a Krylov solve has stagnated (module notes)
DEFAULT_NU = 10            # the paper's ν: estimators / inexact tests every 10 Krylov steps

PRESETS = {
    "paper": {"system": "full",
              "options": {"ksp_type": "gmres", "ksp_pc_side": "right",
                          "ksp_norm_type": "unpreconditioned", "pc_type": "bjacobi",
                          "sub_ksp_type": "preonly", "sub_pc_type": "ilu",
                          "sub_pc_factor_levels": 0}},
    "direct": {"system": "full",
               "options": {"ksp_type": "preonly", "pc_type": "lu",
                           "pc_factor_mat_solver_type": "mumps",
                           "mat_mumps_icntl_14": 100, "mat_mumps_icntl_8": 0}},
    "amg": {"system": "eliminated",
            "options": {"ksp_type": "fgmres", "ksp_norm_type": "unpreconditioned"}},
}
# incomplete factorisations: their zero-pivot threshold is set to 0 (module notes)
INCOMPLETE = ("ilu",)           # (ICC is refused: SYMMETRIC_ONLY)
# a KSP of type preonly applies its PC once: the linear solve is exact only by a factorisation
FACTORISATIONS = ("lu",)
# factorisations of a symmetric matrix's upper triangle: none of the matrices solved here is
# symmetric (the Newton systems; S_D and the gap's operator of the mean/gap split keep their
# boundary columns beside the identity rows of the boundary vertices)
SYMMETRIC_ONLY = {"cholesky": "lu", "icc": "ilu"}
RESERVED = {"ksp_rtol": "the Newton variant sets the linear tolerance",
            "ksp_atol": "the Newton variant sets the linear tolerance",
            "ksp_max_it": "use --max-linear-its (max_linear_its in the API)",
            "ksp_divtol": "the method's tests decide when a Krylov solve stops",
            "ksp_initial_guess_nonzero": "every Krylov solve starts from its Newton step's "
                                         "guess (theory §8)",
            "ksp_knoll": "every Krylov solve starts from its Newton step's guess (theory §8)",
            "ksp_guess_type": "every Krylov solve starts from its Newton step's guess "
                              "(theory §8)",
            "ksp_converged_maxits": "the method's tests decide when a Krylov solve stops",
            "ksp_converged_use_initial_residual_norm": "the method's tests decide when a "
                                                       "Krylov solve stops",
            "ksp_converged_use_min_initial_residual_norm": "the method's tests decide when a "
                                                           "Krylov solve stops",
            "ksp_reuse_preconditioner": "each Newton step's matrix is new, and so is its "
                                        "preconditioner"}

_prefixes = itertools.count()
REASONS = {v: k for k, v in vars(PETSc.KSP.ConvergedReason).items() if k.isupper()}


def linear_tolerance(variant, residual):
    """The tolerance of ‖R_alg‖/‖B‖ for a Newton step; `residual` = ‖R_lin(X^{k-1})‖/‖(F, 0)‖
    (§8). The adaptive variant's floor is the exact tolerance (its criterion stops first); the
    inexact one's never falls below it either (a Newton `tol` below round-off would otherwise
    ask the Krylov solver for what it cannot reach)."""
    return max(residual, EXACT_TOL) if variant == "inexact" else EXACT_TOL


@dataclass
class Krylov:
    """A preset (`PRESETS`) with the user's PETSc options on top, ν and the iteration limit of
    one solve. ValueError on an unknown preset or a refused option."""
    preset: str = "amg"
    options: dict = None
    nu: int = DEFAULT_NU
    max_it: int = 10000
    merged: dict = field(init=False)

    def __post_init__(self):
        if not isinstance(self.preset, str) or self.preset not in PRESETS:
            raise ValueError(f"unknown Krylov preset {self.preset!r} (choose from: "
                             f"{', '.join(PRESETS)})")
        for name in ("nu", "max_it"):
            setattr(self, name, positive_integer(name, getattr(self, name)))
        user = {}
        for name, value in (self.options or {}).items():
            name = str(name).lstrip("-").lower()      # PETSc's option names ignore case
            if name in RESERVED:
                raise ValueError(f"PETSc option -{name} is not accepted: {RESERVED[name]}")
            user[name] = option_value(name, value)
        self.merged = dict(PRESETS[self.preset]["options"])
        self.merged.update(user)
        for name, value in list(self.merged.items()):
            # an incomplete factorisation (the paper's ILU(0), or the user's on either
            # system) declares only an exact zero pivot a breakdown (module notes)
            if name.endswith("pc_type") and str(value).lower() in INCOMPLETE:
                self.merged.setdefault(name[:-len("type")] + "factor_zeropivot", 0.0)
        for name, value in self.merged.items():
            # PCMG on more than one level needs interpolations nobody supplies here: PETSc
            # crashes in its set-up (a segmentation fault, not an error)
            if name.endswith("pc_type") and str(value).lower() == "mg":
                raise ValueError(f"PETSc option -{name} mg needs interpolation operators, "
                                 "which membranes does not supply: use gamg or hypre")
            # Cholesky and ICC read the upper triangle only: on a nonsymmetric matrix they
            # factorise another matrix (Newton then fails, or a direct solve is wrong)
            if name.endswith("pc_type") and str(value).lower() in SYMMETRIC_ONLY:
                value = str(value).lower()
                raise ValueError(f"PETSc option -{name} {value} factorises a symmetric "
                                 f"matrix, and the matrices solved here are not symmetric: "
                                 f"use {SYMMETRIC_ONLY[value]}")
        # PETSc 3.18's Chebyshev, run under the method's test until its iterates overflow
        # (its spectrum estimate does not fit the nonsymmetric Newton matrices: the paper
        # preset with -pc_type jacobi on the disk), ends with DIVERGED_NANORINF and a KSP
        # whose reset or destruction crashes (a segmentation fault, not an error)
        if str(self.merged.get("ksp_type")).lower() == "chebyshev":
            raise ValueError("PETSc option -ksp_type chebyshev crashes PETSc when it "
                             "diverges, as it does on the nonsymmetric Newton systems: use a "
                             "Krylov method such as gmres, fgmres or bcgs")
        if not self.iterative and (self.mean_gap or
                                   self.merged.get("pc_type") not in FACTORISATIONS):
            pc = "the mean/gap split" if self.mean_gap else \
                f"-pc_type {self.merged.get('pc_type')}"
            whose = "the direct preset's" if self.preset == "direct" else "PETSc option"
            raise ValueError(f"{whose} -ksp_type preonly applies the preconditioner once, "
                             f"which solves the Newton system only as a factorisation "
                             f"(-pc_type {' or '.join(FACTORISATIONS)}), not {pc}")

    @property
    def description(self):
        """The preset's name, and how the user's options made it direct, for messages."""
        if self.preset == "direct" or self.iterative:
            return repr(self.preset)
        return f"{self.preset!r} with -ksp_type preonly"

    @property
    def system(self):
        """The preset's Newton system ('full' or 'eliminated')."""
        return PRESETS[self.preset]["system"]

    @property
    def iterative(self):
        return self.merged.get("ksp_type") != "preonly"

    @property
    def mean_gap(self):
        """Whether the mean/gap PC is used (the amg preset, no pc_type of the user's)."""
        return self.preset == "amg" and "pc_type" not in self.merged

    def inner(self):
        """The complete options of the mean/gap split's inner PCs by their prefix ('mean_',
        'gap_': `inner_defaults` below the user's), or {} without the split: what
        `check_petsc_options_used` checks the user's prefixed options against."""
        if not self.mean_gap:
            return {}
        return {name + "_": {k[len(name) + 1:]: v
                             for k, v in inner_defaults(self.merged, name).items()}
                for name in ("mean", "gap")}


def as_krylov(krylov):
    """A `Krylov` from a preset name, a dict of its fields, or a `Krylov`."""
    if isinstance(krylov, Krylov):
        return krylov
    if isinstance(krylov, str):
        return Krylov(krylov)
    if isinstance(krylov, dict):
        return Krylov(**krylov)
    raise ValueError(f"krylov must be a preset name ({', '.join(PRESETS)}), a dict or a "
                     f"Krylov, got {krylov!r}")


class StoppingTest:
    """The KSP convergence test of the module notes: ‖b - A y‖ ≤ bound after iterations
    i ≡ 0 mod `every` (the initial guess too where `guess`, by default where every = 1), and
    every ν iterations the callback `on_iterate(i, y, r)` (y the current iterate,
    r = b - A y; True stops). A solve whose recursive estimate met the bound while the true
    residual has not halved in `STAGNATION` iterations has stagnated at round-off (module
    notes): it ends as DIVERGED_BREAKDOWN with `stagnated` set."""

    def __init__(self, A, b, bound, every=1, nu=DEFAULT_NU, on_iterate=None, guess=None):
        self.A, self.b, self.bound = A, b, bound
        self.every, self.nu, self.on_iterate = every, nu, on_iterate
        self.guess = every == 1 if guess is None else guess
        self.y, self.r = A.createVecRight(), b.duplicate()
        self.last, self.stopped, self.true_norm = -1, False, None
        self.decided = False        # whether this test ended the solve at the iterate y
        self.stagnated = False      # whether it ended the solve at the round-off (class notes)
        self.best, self.since = math.inf, 0   # the least true residual since it last halved

    def _build(self, ksp):
        ksp.buildSolution(self.y)
        self.A.mult(self.y, self.r)
        self.r.aypx(-1.0, self.b)
        self.true_norm = self.r.norm()
        return self.true_norm

    def __call__(self, ksp, its, rnorm):
        if its <= self.last:        # the same iterate again after a GMRES restart
            return PETSc.KSP.ConvergedReason.ITERATING
        self.last = its
        norm_type = ksp.getNormType()
        gate = norm_type != PETSc.KSP.NormType.UNPRECONDITIONED or rnorm <= self.bound
        # rnorm 0: a solved system, tested at once; but without a norm (-ksp_norm_type none)
        # PETSc passes 0 at every iteration, and the schedule (every, guess) holds
        solved = rnorm == 0 and norm_type != PETSc.KSP.NormType.NONE
        if (its % self.every == 0 and (its > 0 or self.guess) or solved) and gate:
            if self._build(ksp) <= self.bound:
                self.decided = True
                return PETSc.KSP.ConvergedReason.CONVERGED_ATOL
            if not math.isfinite(self.true_norm):
                return PETSc.KSP.ConvergedReason.DIVERGED_NANORINF
            if rnorm <= self.bound:           # the estimate says converged, the residual not
                if self.true_norm <= 0.5 * self.best:
                    self.best, self.since = self.true_norm, its
                elif its - self.since >= STAGNATION:
                    self.stagnated = True
                    return PETSc.KSP.ConvergedReason.DIVERGED_BREAKDOWN
        if self.on_iterate is not None and its > 0 and its % self.nu == 0:
            # a non-finite iterate (a method whose recurrence broke down unnoticed, such as
            # TFQMR with the right preconditioning of the amg preset) ends the solve: it is
            # no iterate for the estimators (its flux fails its check, §5)
            if not math.isfinite(self._build(ksp)):
                return PETSc.KSP.ConvergedReason.DIVERGED_NANORINF
            if self.on_iterate(its, self.y, self.r):
                self.stopped = self.decided = True
                return PETSc.KSP.ConvergedReason.CONVERGED_ITS
        return PETSc.KSP.ConvergedReason.ITERATING

    def destroy(self):
        self.y.destroy()
        self.r.destroy()


def refine(pc, A, b, y, r, bound, norm, steps=REFINEMENTS):
    """Iterative refinement of a direct solve (Wilkinson's): y += P⁻¹ r, r = b - A y with the
    factors P of A that `pc` holds, while ‖r‖ > `bound` and each step at least halves ‖r‖, at
    most `steps` times. A step that does not halve ‖r‖ is undone: the solve has reached the
    round-off of its factors. `r` holds b - A y of `y` (norm `norm`) on entry, and of the
    returned iterate on exit. Returns (steps kept, ‖r‖, settled): settled where ‖r‖ ≤ bound
    or at round-off, not where the steps ran out or ‖r‖ is not finite. Collective."""
    d = y.duplicate()
    try:
        for done in range(steps):
            if norm <= bound:
                return done, norm, True
            pc.apply(r, d)
            y.axpy(1.0, d)
            A.mult(y, r)
            r.aypx(-1.0, b)
            new = r.norm()
            if not new <= 0.5 * norm:       # (also for NaN)
                y.axpy(-1.0, d)
                A.mult(y, r)
                r.aypx(-1.0, b)
                norm = r.norm()
                return done, norm, math.isfinite(norm)
            norm = new
        return steps, norm, norm <= bound
    finally:
        d.destroy()


def _mumps_info(pc):
    """MUMPS's INFOG(1), INFOG(2) of a failed factorisation, as text ('' if not MUMPS)."""
    try:
        F = pc.getFactorMatrix()
        return f" (MUMPS INFOG(1) = {F.getMumpsInfog(1)}, INFOG(2) = {F.getMumpsInfog(2)})"
    except PETSc.Error:
        return ""


class LinearSolver:
    """One KSP for a Newton run: configured once from the Krylov spec (under its own prefix),
    handed each step's matrix; for the mean/gap split it keeps the mean's AMG (S_D does not
    change on a mesh) and the gap's of the last step, made anew where G or p change."""

    def __init__(self, krylov, comm):
        self.krylov = as_krylov(krylov)
        self.comm = comm
        self.prefix = f"membranes_{next(_prefixes)}_"
        options = dict(self.krylov.merged)
        for prefix, pc in self.krylov.inner().items():      # the mean/gap split's inner PCs
            options.update({prefix + name: value for name, value in pc.items()})
        self.options = options
        put_options(self.prefix, options)
        self.ksp = PETSc.KSP().create(comm)
        self.mean = None
        self._gap = None         # (G, p, K, its InnerPC) of the last eliminated solve
        self._context = None
        try:
            configure(self.ksp, self.prefix)
        except ValueError:
            self.destroy()
            raise

    def _shell(self, step, split):
        """Install the mean/gap PC of the eliminated `step` (`split` = (S_D, ab, theta))."""
        S_D, ab, theta = split
        if self.mean is None:
            self.mean = InnerPC(S_D, self.prefix + "mean_")
        context = MeanGapPC(S_D, ab, theta, step.lam_out, step.c, step.d, self.mean,
                            lambda G, p: self._gap_pc(S_D, G, p))
        pc = self.ksp.getPC()
        pc.setType(PETSc.PC.Type.PYTHON)
        pc.setPythonContext(context)
        self._context = context

    def _gap_pc(self, S_D, G, p):
        """The gap's InnerPC on (S_D + diag p)[G, G]: the last solve's where G and p are the
        same on every process (the same operator, so its AMG set-up is reused: the two
        solves of a forced Newton step, and Newton-min's steps once its contact set has
        settled, p = 0), else made anew. Kept until the next solve that needs another, or
        `release`."""
        kept = self._gap
        same = (kept is not None and np.array_equal(kept[0], G)
                and np.array_equal(kept[1], p))
        if kept is not None and self.comm.allreduce(same, op=MPI.LAND):
            return kept[3]
        self._drop_gap()
        K = gap_operator(S_D, G, p)
        self._gap = (G, p, K, InnerPC(K, self.prefix + "gap_"))
        return self._gap[3]

    def _drop_gap(self):
        if self._gap is not None:
            self._gap[3].destroy()
            self._gap[2].destroy()
            self._gap = None

    def solve(self, step, y, bound, every=1, on_iterate=None, split=None, guess=None,
              max_it=None, residual=None):
        """Solve step.A y = step.b from y (changed in place) until ‖b - A y‖ ≤ bound (tested
        after multiples of `every` iterations, and at y itself where `guess`: StoppingTest)
        or `on_iterate` stops it (see StoppingTest).
        `split`: (S_D, ab, θ) for the mean/gap PC of an eliminated step; `max_it`: the
        iterations this solve may make (default the Krylov spec's, a positive integer: a
        Newton step that solves twice shares its limit between them); `residual`: a Vec that
        receives b - A y at the end (not where PETSc raised: the solve then failed). A direct
        solve (``preonly``) counts one iteration and its refinement steps (`refine`), and has
        converged at ‖b - A y‖ ≤ bound or at the round-off of its factors. Returns
        (iterations, reason name, converged, ‖b - A y‖ at the end)."""
        ksp = self.ksp
        if not self.krylov.iterative:
            # a factorisation is analysed anew each step: MUMPS's pivot order of the step
            # before (λ-diagonal β ≠ 0 everywhere at X⁰) fails on the zero β of a min contact
            ksp.getPC().reset()
        ksp.setOperators(step.A)
        if self.krylov.mean_gap:
            if split is None or step.system != "eliminated":
                raise ValueError("the amg preset's mean/gap preconditioner needs the "
                                 "eliminated system")
            self._shell(step, split)
        iterative = self.krylov.iterative
        test = None
        try:
            if iterative:
                test = StoppingTest(step.A, step.b, bound, every, self.krylov.nu, on_iterate,
                                    guess)
                ksp.setConvergenceTest(test)
                ksp.setInitialGuessNonzero(True)
                ksp.setTolerances(max_it=self.krylov.max_it if max_it is None else max_it)
            try:
                ksp.solve(step.b, y)
            except PETSc.Error as e:
                return ksp.getIterationNumber(), f"PETSc error: {petsc_message(e)}", False, \
                    float("nan")
            its, reason = ksp.getIterationNumber(), ksp.getConvergedReason()
            refined, settled = 0, False
            if test is not None and test.decided:
                # the iterate the test judged (and the estimators saw) is the answer: some
                # KSPs end a step past the one they build (Chebyshev), or keep right-
                # preconditioned iterates apart from it (-ksp_type qmrcgs, fbcgs, symmlq);
                # its residual norm is the test's (b - A y of that iterate, just made)
                test.y.copy(y)
                norm = test.true_norm
                if residual is not None:
                    test.r.copy(residual)
            else:
                r = step.b.duplicate() if residual is None else residual
                step.A.mult(y, r)
                r.aypx(-1.0, step.b)
                norm = r.norm()
                if not iterative and reason > 0:
                    refined, norm, settled = refine(ksp.getPC(), step.A, step.b, y, r, bound,
                                                    norm)
                if residual is None:
                    r.destroy()
            name = REASONS.get(reason, str(reason))
            if test is not None and test.stagnated:
                name = (f"stagnated at round-off (its own residual estimate below the bound, "
                        f"the true residual not halved in {STAGNATION} iterations)")
            if not iterative and reason < 0:
                name += _mumps_info(ksp.getPC())
            if not iterative:
                if refined:
                    name += f" and {refined} refinement step{'s' * (refined > 1)}"
                if settled and norm > bound:
                    name += ", at the round-off of its factors"
                return max(its, 1) + refined, name, reason > 0 and settled, norm
            # the true residual decides: a solve cut off by max_it before its test was made
            # (every > max_it: inexact with --max-linear-its below ν) may have met the bound
            converged = (reason > 0 and test.stopped) or norm <= bound
            return its, name, converged, norm
        finally:
            if iterative:
                ksp.setConvergenceTest(None)
            if test is not None:
                test.destroy()
            if self._context is not None:
                ksp.getPC().setType(PETSc.PC.Type.NONE)
                self._context.destroy()
                self._context = None
            # the Krylov basis and the PC's data are the step's: freed now, so that they are
            # not alive under the estimates that follow the solve (the next step's matrix
            # needs a new set-up anyway; the mean's AMG, kept in `mean`, is not the KSP's)
            ksp.reset()

    def release(self):
        """Free the mean's and the kept gap's PCs (made again at the next eliminated
        solve)."""
        if self.mean is not None:
            self.mean.destroy()
            self.mean = None
        self._drop_gap()

    def destroy(self):
        """Free the KSP and the mean's and gap's PCs, and take the solver's options out of
        PETSc's database."""
        self.ksp.destroy()
        self.release()
        take_options(self.prefix, self.options)


__all__ = ["EXACT_TOL", "DEFAULT_NU", "PRESETS", "INNER_DEFAULTS", "Krylov", "as_krylov",
           "LinearSolver", "StoppingTest", "linear_tolerance"]
