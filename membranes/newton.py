"""Semismooth Newton for the discrete contact problem: exact, inexact and adaptive inexact
(DESIGN §3, §8).

    k = 0, X^0 = (g, 0, 0)
    repeat: linearise the C-function at X^{k-1}, solve A^{k-1} X^k = B^{k-1}
            (from X^{k,0} = X^{k-1} when the solver is iterative)
    until the variant's stopping test holds at X^k

The step is solved on the full 3N system or on the eliminated 2N system (newton_system), by
MUMPS (`krylov=None`) or by a Krylov solver (`krylov.Krylov`). Variants (DESIGN §8):

* exact: the linear residual ‖R_alg‖/‖B‖ ≤ EXACT_LINEAR_TOL = 2e-12 at every step (or tol/50
  when the Newton tolerance is tighter than 1e-10: the ratio of DESIGN §8, so that the linear
  solves stay below what Newton asks for), tested after every Krylov iteration; Newton stops
  at ‖R_lin(X^k)‖/‖(F, 0)‖ ≤ tol (1e-10 by default);
* inexact: ‖R_alg‖/‖B‖ ≤ ‖R_lin(X^{k-1})‖/‖(F, 0)‖, tested every ν Krylov iterations (the
  initial guess X^{k-1} meets it already: see `krylov`); Newton stops as for exact;
* adaptive (DESIGN §8, Algorithm 1; Krylov only, needs `estimate`): every ν Krylov steps
  (i = ν, 2ν, ...: the schedule, recorded in the history) the iterate X^{k,i} goes to the
  estimators; GMRES stops as soon as an iterate X^{k,i} of the step (i ≥ 1) has
  η_alg ≤ γ_alg max(η_disc, η_lin) (`linear_criterion`), and that iterate is X^k. An estimate
  may become available only later (the ν-extra-iterations flux of X^{k,i} needs X^{k,i+ν},
  DESIGN §6): then GMRES has run to i + ν, those iterations count, and X^k is still X^{k,i},
  the iterate the criterion was verified on (with a guaranteed bound of its own). GMRES also
  stops where the exact variant would (‖R_alg‖/‖B‖ ≤ 2e-12): nothing is left to gain, and the
  iterate needs no algebraic flux. Newton stops at the first X^k (k ≥ 1) with
  η_lin ≤ γ_lin η_disc (`newton_criterion`); `converged` means that this criterion was met.

**Robustness (DESIGN §11).** Residuals are measured in units of the data (newton_system:
rows of membrane α weighted by 1/μ_α, the C-function on (u1 - u2, κ λ)), and so are the
tolerances: ‖W R_lin‖/‖W F‖ ≤ tol, ‖W R_alg‖/‖W B‖ ≤ 2e-12 for exact solves.

* Fischer–Burmeister (exact and inexact variants) globalises Newton with a watchdog line
  search (Chamberlain–Powell) on the merit θ = ½‖W R_lin‖², continuously differentiable
  for FB, with ∇θ·d = -2θ along a Newton direction d. The iterate X_c where a run of full
  steps starts is the checkpoint; full steps are taken as long as, within WATCHDOG_STEPS =
  10 of them, one reaches θ ≤ (1 - 2σ) θ(X_c), σ = 1e-4 (the next checkpoint is then the
  new iterate). Otherwise the run goes back to X_c and takes the Armijo step there,
  X_c + t d_c with the first t = 1/2, 1/4, ... ≥ 2^-20 such that θ ≤ (1 - 2σ t) θ(X_c), and
  from then on every step is an Armijo step (t = 1, 1/2, ...) against the largest θ of the
  last LS_MEMORY = 5 Newton iterates (nonmonotone): full steps from the damped iterate
  would retrace the path that failed (seen on the 100:1 anisotropic mesh). With no such t
  the run stops (converged = false, the reason says so). Why a watchdog: FB Newton's merit rises on the way (disk, plain steps: 1 → 10 → 20 →
  6 → 1 → 0.08 → ... → 4e-11 in 12 steps, the same 11–12 steps at 411, 1.5k and 6k
  vertices, eliminated system with vertex_amg), and a nonmonotone line search at every
  step crept along with step lengths 2^-10 to 2^-3: 14 and 34 Newton steps at 411 and 6k
  vertices against the last 5 merits, 14, 18 and 32 at 411, 1.5k and 6k against the last
  10 (a monotone one took 16 steps instead of 11 on the radial scene). A damped iterate X_t = X_0 + t (X_1 - X_0) (X_0 the checkpoint or the current
  iterate, X_1 the full step from it with residual R_1) is recorded with its residual in
  the system of that step, B - A X_t = (1 - t) R_lin(X_0) + t R_1 (DESIGN §4), and its
  `step_length` t (1 for full steps); the iterates abandoned by a return stay in the
  history and count.
* **Active-set steps (Fischer–Burmeister, exact and inexact).** FB is positively homogeneous:
  its Newton row at a vertex, (cos φ - 1)(X1 - X2) + (sin φ - 1) κ X3 = 0 (B3 = 0, Euler),
  depends only on the angle φ of (a, b) = (u1 - u2, κ λ). Off the axes it is a mixed
  condition, gap and pressure of opposite signs; a vertex on the wrong side comes back to
  its axis only like φ → φ²/2 per step, and near the free boundary the tail is quadratic
  with the constant 1/(2 w*), w* the small gap of the solution there. Measured on the disk
  (h0 = 0.2, MUMPS, nested): from the prolonged guess the first step forces contact at the
  edge midpoints where w and λ are both positive (residual 4e-2 → 3 on T_3), the next steps
  bring such vertices back (angle -90°, -27°, -4°, ...), and the tail falls only ~30× per
  step (w* = 7e-6 against g = 0.05): 10, 7, 7, 7, 7 steps on T_0..T_4, min 4, 4, 4, 5, 4.
  Neither the element chosen at the kink (no iterate has a = b = 0 there), nor a local κ
  (D_a (1/S1_aa + 1/S2_aa), the gap a nodal pressure makes), nor a projection of the
  prolonged guess changed that much (measured: 10 on T_0, 6-8 on T_1..T_3).
  Hence, after a step that decreased the merit enough, θ(X^k) ≤ (1 - 2σ) θ(X^{k-1}), the
  next step first linearises FB at the projection P(X) of every pair (a, b) onto the
  complementarity set (cfunctions.project, `linear_step(at_projection=True)`), where FB
  vanishes and its Jacobian is (-1, 0) or (0, -1): the Newton system of min, the
  primal–dual active set step. It is kept if θ(X_P) ≤ (1 - 2σ) θ(X) (Armijo at t = 1;
  a kept step that also meets the checkpoint's test ends the watchdog's run); otherwise,
  or where its linear solve fails, the FB step at X is solved as well (both solves count in
  the step's linear iterations) and the watchdog above goes on. Once the active set is
  right the active-set step lands on the discrete solution: on the same disk 6, 3, 3, 4, 4
  steps. The C-function, the
  merit, the stopping test, the line search and the solution are FB's; the steps of a run
  up to its first sufficient decrease (at least one; also after Newton-min's guard switched
  to FB) are FB's own, and records say which linearisation each step used
  (`linearised_at`: 'iterate' or 'projection'). The adaptive variant takes no active-set
  steps (it takes GMRES iterates as they are: see below). Inexact steps with GMRES +
  ILU(0) are 10 GMRES iterations each on fine meshes, far from either Newton step, and
  there active-set steps do not pay (disk T_4: 123 Newton steps against 73; with
  vertex_amg on the eliminated system they do: 6, 3, 3, 4, 4 against 10, 7, 7, 7, 7).
* Newton-min has no merit function to descend (min is not differentiable), and with exact
  solves it is the primal–dual active set method, which can cycle (active sets that repeat;
  possible for P-matrices that are not M-matrices, e.g. obtuse meshes or a far-off start).
  The guard: before each step the active set {u1 - u2 ≤ κ λ} is compared with those of the
  earlier iterates; if it came back without the residual falling below 0.999 of its value
  at the earlier visit (a cycle), or, for the inexact variant, if the residual exceeds 1e6
  times the smallest so far (divergence: seen, up to 1e62, with 10 GMRES + ILU(0) steps per
  Newton step on a 100:1 anisotropic mesh; with exact solves the iterates are determined by
  the finitely many active sets and cannot diverge, while jumps of 1e3 are normal there, as
  on that mesh), the run continues with Fischer–Burmeister and its line search (same
  solution set: both C-functions vanish exactly at the solutions). The switch is named in `reason` and in each record's `cfun`.
* The adaptive variant takes the accepted Krylov iterate as it is (Algorithm 1): its
  estimates certify that iterate, and a damped one would need estimates of its own.

Non-convergence is reported, never hidden: the result carries `converged = False` and a
reason, when max_it Newton steps do not meet the stopping test or when a Krylov solve stops
(at max_linear_its) before its own test or criterion.

History: one record per Newton iterate (X^0 included, kind "initial"/"newton") and per ν-th
Krylov iterate inside a step (kind "krylov"), with `linear_it` the Krylov iterations done so
far in the step (the step's total for a Newton iterate, 1 for a direct solve per solve: 2
where an active-set step was rejected) and `linearised_at` the point where the step
linearised the C-function ('iterate', or 'projection' for an active-set step). An adaptive
step's Newton record repeats the accepted Krylov iterate (its X, residuals and estimates) with
the step's total. An adaptive run does not estimate X^0 (its record has no estimates):
Algorithm 1 tests the iterates of its steps only, and X^0's estimates would serve the record
alone (they took 10 % of the run at 9.3e5 vertices, with the ν flux they need). Callbacks, in
this order, for each recorded iterate X (3N) with the algebraic residual R = B - A X (3N;
R3 = 0 on the eliminated system) of the linear system that produced it (None for X^0):

* `estimate(record, X, R, same_as)` fills in the estimators (DESIGN §7) of this or of earlier
  iterates and returns those it completed now, as (record, X, R) triples; same_as is the
  accepted Krylov record when `record` is an adaptive step's Newton record (the same iterate);
* `monitor(record, X, R)` sees the record (diagnostics: energy error, progress).

**Estimates computed elsewhere.** An `estimate` may evaluate on other processes
(membranes.pipeline) and then has two more methods: `awaiting(record)` (its estimates are
still to come) and `resolve(record)` (wait for them). Where the adaptive stopping test at
X^{k-1} is awaiting its estimates, step k is computed meanwhile (the step depends on X^{k-1}
alone) and the test is taken when they come: GMRES asks after every iteration whether they
are in (`cancel` of Krylov.solve) and stops if the test is then met; at the latest the test is
taken once the step is solved. If it is met, the step is dropped and X^{k-1} ends the run as
it would have without the step. A Krylov iterate that step k hands out first waits for that
test (and ends the solve if it is met), so that no record of a dropped step is made: the
history, the iterates and the decisions are those of a run that evaluates every estimate at
once. Where the test at X^{k-1} is likely met (`likely_met`: the ratio η_lin/(γ_lin η_disc)
of X^{k-2}, contracted once more as from X^{k-3} to X^{k-2}, is at most LIKELY_MET), step k
is not computed ahead: the run waits for the estimates, and computes step k only if the test
is not met after all. A step ahead that is dropped slows the estimate it runs beside (the two
processes share two cores' memory bandwidth) and is noticed only at its next GMRES iteration
(its matrix and AMG set-up are not interrupted); on the finest level of the disk at 9.3e5
vertices the estimate of X³ then took 1.05 s and was seen 0.2-0.3 s later, against 1.05 s
seen at once when waited for. A wrong guess costs one estimate's time (process 0 idle). In
the disk runs of the benchmark (h0 = 0.2, J = 5 and h0 = 0.132, J = 6; Newton-min and FB,
vertex_amg) the rule waits at the last iterate of every level of three or more steps except
T_0 with Newton-min (ratios 3.8, 3.0, 0.32 and 5.6, 6.7, 0.95: it steps ahead there), and
never at an iterate whose test is not met (FB on T_0 at J = 6: 5.6, 3.7, 2.8, 2.0, 0.036,
predicted 2.4, 2.1, then 1.4: waits at the last only); levels of one or two steps have fewer
than two ratios. The decisions, and so the iterates, are the same either way.

**Two steps ahead.** Where no Krylov iterate has been handed out, step k's result X^k is
recorded (and sent for its estimates) even while the test at X^{k-1} is still awaited, and
step k+1 is computed next; the tests are taken in order as their estimates come (`pending`,
`first_met`), and before X^{k+1} is recorded the test at X^{k-1} is waited for. If the test
at X^{k-1} is met, X^k leaves the history again (`stop_at`; `estimate.forget`), and the run
ends at X^{k-1} with its iterate, counts and history, as without steps ahead; the estimator
processes, which take the same test at every Newton iterate they estimate, skip the
iterates after one that meets it (membranes.pipeline). Where the estimator process is the
slower side (its set-up of the finest level takes longer than process 0's mean and first
step), process 0 no longer waits for X¹'s estimate before step 3: on the finest level of
the disk at 9.3e5 vertices (J = 6, 2 processes) that wait was 0.33-0.7 s.

Wall times count the method's own work: assembly, linear solves, and what the variant's tests
use: the nonlinear residual of the Newton iterates (exact, inexact), or the Krylov iterates
handed out and their estimates (adaptive; with each record's nonlinear residual, one sparse
product). Everything else — recording Krylov iterates for exact and inexact, their
estimates, the monitor — is excluded.
"""

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import cfunctions
from . import mean as mean_module
from . import newton_system as ns
from .linear_solve import LinearSolveError, scaled_rows, solve_direct

SYSTEMS = ("full", "eliminated")
VARIANTS = ("exact", "inexact", "adaptive")
DEFAULT_TOL = 1e-10            # DESIGN §8: Newton stops at ‖R_lin‖/‖(F, 0)‖ ≤ 1e-10 ...
EXACT_LINEAR_TOL = 2e-12       # ... and exact solves reach ‖R_alg‖/‖B‖ ≤ 2e-12
DEFAULT_GAMMA = 0.3            # γ_lin = γ_alg = 0.3 in the seed (DESIGN §8)
LS_SIGMA = 1e-4                # Armijo constant of the Fischer–Burmeister line search
LS_MIN_STEP = 2.0 ** -20       # smallest step length tried
WATCHDOG_STEPS = 10            # full FB steps allowed without sufficient decrease
LS_MEMORY = 5                  # after a return: nonmonotone reference over 5 Newton iterates
CYCLE_PROGRESS = 0.999         # a repeated active set counts as a cycle unless the residual
                               # fell below this fraction of its value at the earlier visit
LIKELY_MET = 2.0               # adaptive, estimates elsewhere: the predicted η_lin/(γ η_disc)
                               # up to which the test counts as likely met (`likely_met`)
DIVERGENCE = 1e6               # ... and (inexact) a residual this many times its smallest
                               # value so far as divergence


@dataclass
class NewtonResult:
    X: np.ndarray
    converged: bool
    reason: str
    newton_iterations: int
    linear_iterations: int
    history: list = field(default_factory=list)


class Stopwatch:
    """Wall clock that can be paused (for diagnostics the method itself does not need)."""

    def __init__(self):
        self.elapsed, self._start = 0.0, time.perf_counter()

    def pause(self):
        if self._start is not None:
            self.elapsed += time.perf_counter() - self._start
            self._start = None
        return self.elapsed

    def resume(self):
        self._start = time.perf_counter()


@dataclass
class LinearStep:
    """One Newton system as a linear solver sees it: A y = b in its own unknowns y, the initial
    guess, ‖B‖ of the 3N system, and the maps of y and of b - A y to the 3N X and R."""
    A: object
    b: np.ndarray
    guess: np.ndarray
    norm_B: float
    expand: Callable
    pad: Callable
    z_is_u2: np.ndarray = None    # eliminated system: where the second unknown z is u2 (not λ)
    min_step: bool = False        # eliminated system of a min step (the mean/gap structure)

    def contact(self):
        """Where a min step on the eliminated system eliminated u2 (its contact vertices, for
        vertex_amg's mean/gap split: preconditioner.mean_gap_split), else None."""
        return ~self.z_is_u2 if self.min_step else None


def linear_step(rows, cfun, system, X, at_projection=False):
    """The Newton system at X (DESIGN §3), full or eliminated, with the membrane rows weighted
    by W (newton_system: units); the guess is X itself, or for the eliminated system the
    unknowns of X it keeps (u2 or λ at each vertex) and u1, moved where u2 is eliminated so
    that the guess keeps X's mean (`mean_keeping_shift`). `pad` maps the solver's residual
    back to the unweighted 3N R of DESIGN §4, which the estimators read. at_projection:
    Fischer–Burmeister linearised at the projection of X (the active-set step of the module
    notes)."""
    alpha, beta, B3 = ns.complementarity_rows(rows, cfun, X, at_projection)
    norm_B = float(np.linalg.norm(np.concatenate([rows.weights * rows.F, B3])))
    if system == "full":
        A, B = ns.full_system(rows, alpha, beta, B3)
        w = np.concatenate([rows.weights, np.ones(rows.n)])
        return LinearStep(scaled_rows(A, w), w * B, X, norm_B, lambda y: y, rows.unweighted)
    A, b, elim = ns.eliminated_system(rows, alpha, beta, B3, weighted=True)
    u1, u2, lam = ns.split(X, rows.n)
    guess = np.concatenate([u1, np.where(elim.eliminate_lambda, u2, lam)])
    guess[:rows.n] += mean_keeping_shift(rows, elim, u2, guess)
    return LinearStep(A, b, guess, norm_B, elim.expand,
                      lambda r: rows.unweighted(np.concatenate([r, np.zeros(rows.n)])),
                      elim.eliminate_lambda, cfun == "min")


def mean_keeping_shift(rows, elim, u2, guess):
    """The change of u1 at the vertices where the eliminated system drops u2 (N values, 0
    elsewhere) that makes the guess keep X's mean m = (μ1 u1 + μ2 u2)/(μ1 + μ2), which the
    complementarity rows do not enter (the mean/gap split of membranes.preconditioner).

    DESIGN §8 starts GMRES from X^{k-1}. The eliminated system cannot hold it where u2 is
    eliminated: u2 is then fixed by u1 and λ (u2 = u1 for min contact), and X^{k-1}'s u2 - u1
    there (a vertex that comes into contact) is lost. Keeping u1 would move the mean by θ times
    that jump, θ = μ2/(μ1 + μ2), and the step's solve would have to undo it. With u1 moved by
    θ (u2 - u2(guess)) the implied u2 moves by (1 - θ) times it in the other direction and m
    stays X^{k-1}'s, which the solve before left at its tolerance: the mean part of the
    residual is then settled from the second step of a level on (`MeanGapAMG.settle_mean`)
    instead of the third, and the solves need fewer iterations (disk, h0 = 0.2, J = 5: 113
    GMRES iterations instead of 121, the same Newton steps). θ comes from the row weights
    (W = 1/μ_α on interior rows: θ = w1/(w1 + w2)); λ and the kept unknowns are X's."""
    n = rows.n
    w1, w2 = rows.weights[:n], rows.weights[n:]
    implied = elim.expand(guess)[n:2 * n]
    return np.where(elim.eliminate_lambda, 0.0, w1 / (w1 + w2) * (u2 - implied))


def linear_tolerance(variant, tol, residual):
    """‖R_alg‖/‖B‖ at which the step's solve stops; `residual` = ‖R_lin(X^{k-1})‖/‖(F, 0)‖.
    For adaptive this is the floor of the module notes (its criterion usually stops first)."""
    if variant == "inexact":
        return residual
    if variant == "adaptive":
        return EXACT_LINEAR_TOL
    return EXACT_LINEAR_TOL * min(1.0, tol / DEFAULT_TOL)


def linear_criterion(record, gamma_alg):
    """η_alg ≤ γ_alg max(η_disc, η_lin) at a recorded iterate (DESIGN §8)."""
    return record["eta_alg"] <= gamma_alg * max(record["eta_disc"], record["eta_lin"])


def newton_criterion(record, gamma_lin):
    """η_lin ≤ γ_lin η_disc at a recorded iterate (DESIGN §8)."""
    return record["eta_lin"] <= gamma_lin * record["eta_disc"]


def solve_step(step, krylov, tol, test_every, on_iterate, cancel=None, mean=None):
    """X^k, its residual R (3N) and the linear iterations of one step (`cancel`: see
    Krylov.solve). `mean` (membranes.mean.LevelMean; eliminated system, Krylov solver): the
    step is solved for the gap and λ (the mean part of its initial residual taken out of the
    right side, to GAP_SHARE of the tolerance: M's own residual takes the rest) and X^k gets
    the mean M; R is b - A y of that y, in the step's own system."""
    if krylov is None:
        y, its = solve_direct(step.A, step.b)
        r = step.b - step.A @ y
    elif mean is None or step.z_is_u2 is None:
        y, r, its = krylov.solve(step.A, step.b, step.guess, tol, step.norm_B, test_every,
                                 on_iterate, cancel, contact=step.contact())
    else:
        def meaned(y):
            y = mean_module.with_mean(y, mean.M, mean.theta, step.expand, step.z_is_u2)
            return y, step.b - step.A @ y

        def on_meaned_iterate(its, current):
            return on_iterate(its, lambda: meaned(current()[0]))
        b = mean_module.without_mean_residual(step.A, step.b, step.guess, mean.theta)
        y, _, its = krylov.solve(step.A, b, step.guess, mean_module.GAP_SHARE * tol,
                                 step.norm_B, test_every,
                                 None if on_iterate is None else on_meaned_iterate, cancel,
                                 mean.theta, contact=step.contact())
        y, r = meaned(y)
    return step.expand(y), step.pad(r), its


def check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r} (choose from: {', '.join(choices)})")


def check_method(system, variant, krylov):
    """ValueError unless the system and variant exist and the variant can use the solver."""
    check_choice("Newton system", system, SYSTEMS)
    check_choice("Newton variant", variant, VARIANTS)
    if variant != "exact" and krylov is None:
        raise ValueError(f"the {variant} Newton variant needs linear_solver 'gmres' (a direct "
                         "solve is exact)")


def check_gamma(name, value):
    """γ_lin, γ_alg: positive finite numbers (DESIGN §8)."""
    try:
        ok = np.isfinite(value) and value > 0 and not isinstance(value, bool)
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def active_set(rows, X):
    """Newton-min's active set at X: the interior vertices whose row is e1 - e2 (contact
    predicted), as a hashable signature."""
    u1, u2, lam = ns.split(X, rows.n)
    take_a = (u1 - u2) <= rows.kappa * lam
    take_a[rows.boundary] = False
    return np.packbits(take_a).tobytes()


def line_search(rows, cfun, X, X_full, residual, reference, t=1.0):
    """Armijo backtracking on the merit θ = ½‖Φ‖², Φ = W R_lin (newton_system), along
    d = X_full - X: the first of t, t/2, t/4, ... ≥ LS_MIN_STEP with
    θ(X + t d) ≤ θ_ref - 2 LS_SIGMA t θ(X) (∇θ·d = -2θ along a Newton direction; θ is C¹
    for Fischer–Burmeister), θ_ref = ½ reference². `residual`, `reference`: relative
    residuals ‖Φ‖/‖W F‖. Returns (X + t d, t), or (None, None) where no t qualifies."""
    d = X_full - X
    while t >= LS_MIN_STEP:
        trial = X + t * d
        r = rows.relative_residual(cfun, trial)
        if r * r <= reference * reference - 2.0 * LS_SIGMA * t * residual * residual:
            return trial, t
        t *= 0.5
    return None, None


def semismooth_newton(rows, g, cfun="min", system="full", variant="exact", krylov=None,
                      tol=DEFAULT_TOL, max_it=100, X0=None, monitor=None, estimate=None,
                      gamma_lin=DEFAULT_GAMMA, gamma_alg=DEFAULT_GAMMA, mean=None):
    """Semismooth Newton from X0 (default (g, 0, 0)); krylov=None: MUMPS (exact only).
    tol: the Newton tolerance of exact and inexact; gamma_lin, gamma_alg: the adaptive
    criteria's; `estimate` and `monitor`: see the module notes (adaptive needs `estimate`);
    `mean`: the mesh's exact mean (membranes.mean.LevelMean), which the steps then take
    (`solve_step`)."""
    check_method(system, variant, krylov)
    cfunctions.get(cfun)
    adaptive = variant == "adaptive"
    if adaptive:
        if estimate is None:
            raise ValueError("the adaptive Newton variant needs the estimators")
        check_gamma("gamma_lin", gamma_lin)
        check_gamma("gamma_alg", gamma_alg)
    clock = Stopwatch()
    X = ns.initial_guess(rows, g) if X0 is None else np.array(X0, dtype=float)
    if X.shape != (3 * rows.n,) or not np.all(np.isfinite(X)):
        raise ValueError(f"the initial guess must be {3 * rows.n} finite values (u1, u2, lam at "
                         f"the {rows.n} vertices), got shape {X.shape}"
                         + ("" if X.shape != (3 * rows.n,) else " with non-finite values"))
    history = []
    recorded_at = [0.0]     # the clock when the last record was made
    # the C-function in use (the guard may switch it), where the step linearised it, and
    # whether the last step decreased the merit enough (FB: the next step tries active-set)
    state = {"cfun": cfun, "note": "", "at": "iterate", "decreased": False}

    def record(kind, k, its, cumulative, X, R, norm_B, same_as=None, step_length=None,
               residual=None):
        """Record X (`residual`: its relative residual if known); returns its record and the
        iterates whose estimates are complete now."""
        rec = {"newton_it": k, "linear_it": its, "cumulative_linear_its": cumulative,
               "residual": rows.relative_residual(state["cfun"], X) if residual is None
               else residual,
               "alg_residual": None if R is None
               else float(np.linalg.norm(rows.weighted(R))) / norm_B,
               "kind": kind, "cfun": state["cfun"], "step_length": step_length,
               "linearised_at": None if kind == "initial" else state["at"]}
        if not adaptive:
            clock.pause()
        # Algorithm 1 evaluates the estimators after Krylov steps only (DESIGN §8): the
        # adaptive variant never tests X^0 (it makes at least one step), so X^0 is not
        # estimated there; the other variants estimate it for the record
        skip = estimate is None or (adaptive and kind == "initial")
        ready = [] if skip else estimate(rec, X, R, same_as)
        rec["wall_time_s"] = recorded_at[0] = clock.pause()
        if monitor is not None:
            monitor(rec, X, R)
        history.append(rec)
        clock.resume()
        return rec, ready

    def hand_out(k, step, done, accepted, before=0, unsettled=False):
        """The Krylov callback of step k (`done`: the linear iterations of the steps before,
        `before`: those of this step's rejected active-set solve): record X^{k,i}; for
        adaptive, keep in `accepted` the first iterate of this step that meets the linear
        criterion, and stop GMRES then. `unsettled`: step k is computed before the stopping
        tests of `pending` records (module notes): the first handed-out iterate waits for
        those tests, and stops GMRES if one is met (the step is then dropped)."""
        def on_iterate(its, current):
            if unsettled and first_met(wait=True) is not None:
                return True
            if not adaptive:
                clock.pause()
            y, r = current()
            _, ready = record("krylov", k, before + its, done + before + its, step.expand(y),
                              step.pad(r), step.norm_B)
            if adaptive:
                accepted.extend(it for it in ready if it[0]["kind"] == "krylov"
                                and it[0]["newton_it"] == k
                                and linear_criterion(it[0], gamma_alg))
            return bool(accepted)
        return on_iterate

    def deferred(rec):
        """Whether rec's estimates are still being computed elsewhere (module notes)."""
        return hasattr(estimate, "awaiting") and estimate.awaiting(rec)

    def stopping(rec):
        """The variant's Newton stopping test at rec: (met, description)."""
        if adaptive:
            if rec["kind"] == "initial":      # Algorithm 1 makes at least one step
                return False, "no Newton step made"
            if deferred(rec):
                estimate.resolve(rec)
            met = newton_criterion(rec, gamma_lin)
            return met, (f"adaptive criterion eta_lin {rec['eta_lin']:.2e} "
                         f"{'<=' if met else '>'} gamma_lin eta_disc = "
                         f"{gamma_lin * rec['eta_disc']:.2e} (relative residual "
                         f"{rec['residual']:.2e})")
        met = rec["residual"] <= tol
        return met, f"relative residual {rec['residual']:.2e} {'<=' if met else '>'} {tol:.0e}"

    def likely_met(rec):
        """Whether the adaptive test at rec, whose estimates are still to come, will likely be
        met (module notes): the ratio ρ = η_lin/(γ_lin η_disc) of the two Newton iterates
        before, contracting once more as it did between them (superlinear convergence
        contracts it faster), is at most LIKELY_MET. False before two ratios are known."""
        ratios = [r["eta_lin"] / (gamma_lin * r["eta_disc"]) for r in history
                  if r["kind"] == "newton" and r is not rec and r.get("eta_lin") is not None
                  and r["eta_disc"] > 0]
        if len(ratios) < 2:
            return False
        return ratios[-1] * min(ratios[-1] / ratios[-2], 1.0) <= LIKELY_MET

    pending = []      # adaptive: records whose stopping test is still to be taken, in order
    kept = {}         # id(record) -> (X, linear iterations, clock) when it was recorded

    def first_met(wait, leave=0):
        """Take the stopping tests of the `pending` records in order, as far as their
        estimates are in (with `wait`: all but the last `leave`, waiting for them): the first
        record whose test is met (it stays first in `pending`), else None; a record whose
        test is not met leaves (and its iterate with it)."""
        while len(pending) > leave:
            if not wait and deferred(pending[0]):
                return None
            if stopping(pending[0])[0]:
                return pending[0]
            del kept[id(pending.pop(0))]
        return None

    def stop_at(met):
        """The run ends at `met`, a pending record whose test is met: the records after it
        (computed ahead: module notes) leave the history, the estimator forgets them; `met`
        is complete only now, and its wall time says so. Returns (X, linear iterations) at
        `met`."""
        at = next(i for i, r in enumerate(history) if r is met)
        for r in history[at + 1:]:
            if hasattr(estimate, "forget"):
                estimate.forget(r)
        del history[at + 1:]
        X_met, done_met, clock_met = kept[id(met)]
        met["wall_time_s"] += clock.pause() - clock_met
        clock.resume()
        return X_met, done_met

    def result(converged, reason, k, done):
        return NewtonResult(X, converged, reason + state["note"], k, done, history)

    seen = {}         # Newton-min's active sets: signature -> (step, residual at that step)
    watch = None      # FB watchdog: (step, X, residual, full step, its R) at the checkpoint
    damped = False    # FB: True once the watchdog returned to a checkpoint
    rec, done = record("initial", 0, 0, 0, X, None, None)[0], 0
    met = None
    for k in range(1, max_it + 1):
        step = None     # the system before goes first: its buffers make the next one's
        # adaptive, with the estimates of X^{k-1} on their way from other processes: compute
        # step k meanwhile, and take the stopping test at X^{k-1} once they are in; but where
        # the test will likely be met, wait for them instead (module notes)
        if adaptive:
            pending.append(rec)
            kept[id(rec)] = (X, done, recorded_at[0])
            met = first_met(wait=False)
            if met is None and pending and likely_met(pending[-1]):
                met = first_met(wait=True)
            if met is not None:
                break
        elif stopping(rec)[0]:
            break
        unsettled = bool(pending)
        if state["cfun"] == "min" and not adaptive:
            signature = active_set(rows, X)
            earlier = seen.get(signature)
            best = min(r for _, r in seen.values()) if seen else rec["residual"]
            why = None
            if earlier is not None and rec["residual"] >= CYCLE_PROGRESS * earlier[1]:
                why = (f"cycled (the active set of step {earlier[0]} came back at step {k - 1} "
                       f"without progress)")
            elif variant == "inexact" and rec["residual"] > DIVERGENCE * best:
                why = (f"diverged (residual {rec['residual']:.1e} at step {k - 1}, "
                       f"{DIVERGENCE:.0e} times its smallest value {best:.1e})")
            if why is not None:
                state["cfun"] = "fb"
                state["note"] = (f"; Newton-min {why}, continued from step {k} with "
                                 f"Fischer-Burmeister and its line search")
                rec["residual"] = rows.relative_residual("fb", X)
                state["decreased"] = False
            else:
                seen[signature] = (k - 1, rec["residual"])
        lin_tol = linear_tolerance(variant, tol, rec["residual"])
        test_every = 1 if variant != "inexact" else krylov.nu
        fb_steps = state["cfun"] == "fb" and not adaptive
        before, r_new, t, same_as, accepted = 0, None, None, None, []
        if fb_steps and state["decreased"]:
            # the active-set step of the module notes, kept if it decreases the merit (a
            # solve that fails is rejected as well: the FB step may still be solved)
            state["at"] = "projection"
            step = linear_step(rows, "fb", system, X, at_projection=True)
            try:
                X_new, R, its = solve_step(step, krylov, lin_tol, test_every,
                                           hand_out(k, step, done, accepted), mean=mean)
                r_new = rows.relative_residual("fb", X_new) \
                    if np.all(np.isfinite(X_new)) else np.inf
            except LinearSolveError as e:
                its, r_new = e.its, np.inf
            if r_new * r_new <= (1.0 - 2.0 * LS_SIGMA) * rec["residual"] ** 2:
                t = 1.0
                if watch is not None and r_new * r_new <= \
                        (1.0 - 2.0 * LS_SIGMA) * watch[2] * watch[2]:
                    watch = None
            else:
                before, r_new = its, None
        try:
            if t is None:
                state["at"] = "iterate"
                step = linear_step(rows, state["cfun"], system, X)
                X_new, R, its = solve_step(step, krylov, lin_tol, test_every,
                                           hand_out(k, step, done, accepted, before, unsettled),
                                           None if not unsettled else
                                           lambda: first_met(wait=False) is not None, mean)
        except LinearSolveError as e:
            met = first_met(wait=True)
            if met is not None:
                break
            unmet = " before the adaptive criterion was met" if adaptive else ""
            return result(False, f"linear solver failed at Newton step {k}{unmet}: {e}",
                          k - 1, done + before + e.its)
        # the tests still to be taken before X^k is recorded: none, or with estimates
        # elsewhere and no Krylov iterate handed out, X^{k-1}'s (two steps ahead: module notes)
        ahead = 1 if hasattr(estimate, "awaiting") and \
            not any(r["kind"] == "krylov" for r in history) else 0
        met = first_met(wait=False)
        if met is None:
            met = first_met(wait=True, leave=ahead)
        if met is not None:
            break
        its += before
        done += its
        if accepted:
            same_as, X_new, R = accepted[0]
        if not np.all(np.isfinite(X_new)):
            return result(False, f"non-finite iterate at Newton step {k}", k - 1, done)
        if fb_steps and t is None:
            # the watchdog line search of the module notes
            t, X_t, X_from, R_from = 1.0, None, X, R
            if damped:          # after a return: a nonmonotone Armijo step at every step
                merits = [r["residual"] for r in history if r["kind"] != "krylov"][-LS_MEMORY:]
                X_t, t = line_search(rows, "fb", X, X_new, rec["residual"], max(merits))
            else:
                if watch is None:
                    watch = (k, X, rec["residual"], X_new, R)
                k_c, X_c, r_c, X_full_c, R_c = watch
                r_new = rows.relative_residual("fb", X_new)
                if r_new * r_new <= (1.0 - 2.0 * LS_SIGMA) * r_c * r_c:
                    watch = None
                elif k - k_c + 1 >= WATCHDOG_STEPS:   # back to the checkpoint, Armijo there
                    X_from, R_from = X_c, R_c
                    X_t, t = line_search(rows, "fb", X_c, X_full_c, r_c, r_c, 0.5)
                    watch, damped, r_new = None, True, None
            if t is None:
                return result(False, f"line search failed at Newton step {k}: no step length "
                              f">= {LS_MIN_STEP:.0e} decreases the merit enough", k - 1, done)
            if t < 1.0:
                # B - A X_t = (1 - t)(B - A X_from) + t R_from in the system that gave the
                # direction, where B - A X_from = R_lin(X_from)
                R = (1.0 - t) * ns.nonlinear_residual(rows, "fb", X_from) + t * R_from
                X_new = X_t
        previous, X = rec["residual"], X_new
        rec = record("newton", k, its, done, X, R, step.norm_B, same_as, t, r_new)[0]
        state["decreased"] = rec["residual"] ** 2 <= (1.0 - 2.0 * LS_SIGMA) * previous ** 2
    if met is None:
        met = first_met(wait=True)
    if met is not None:
        X, done = stop_at(met)
        rec = met
    met, description = stopping(rec)
    k = rec["newton_it"]
    if met:
        return result(True, description, k, done)
    return result(False, f"no convergence in {max_it} Newton steps ({description})", k, done)
