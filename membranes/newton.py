"""Semismooth Newton for the discrete contact problem, exact and inexact (DESIGN §3, §8).

    k = 0, X^0 = (g, 0, 0)
    repeat: linearise the C-function at X^{k-1}, solve A^{k-1} X^k = B^{k-1}
            (from X^{k,0} = X^{k-1} when the solver is iterative)
    until ‖R_lin(X^k)‖ / ‖(F, 0)‖ ≤ tol  (1e-10 by default, DESIGN §8)

The step is solved on the full 3N system or on the eliminated 2N system (newton_system), by
MUMPS (`krylov=None`) or by a Krylov solver (`krylov.Krylov`). Variants (DESIGN §8):

* exact: the linear residual ‖R_alg‖/‖B‖ ≤ EXACT_LINEAR_TOL = 2e-12 at every step (or tol/50
  when the Newton tolerance is tighter than 1e-10: the ratio of DESIGN §8, so that the linear
  solves stay below what Newton asks for), tested after every Krylov iteration;
* inexact: ‖R_alg‖/‖B‖ ≤ ‖R_lin(X^{k-1})‖/‖(F, 0)‖, tested every ν Krylov iterations (the
  initial guess X^{k-1} meets it already: see `krylov`).

Non-convergence is reported, never hidden: the result carries `converged = False` and a
reason, e.g. when the Krylov solver stops before its tolerance.

History: one record per Newton iterate (X^0 included, kind "initial"/"newton") and per ν-th
Krylov iterate inside a step (kind "krylov"), with `linear_it` the Krylov iterations done so
far in the step (the step's total for a Newton iterate, 1 for a direct solve). A
`monitor(record, X, R)` callback sees each recorded iterate X (3N) with the algebraic residual
R = B - A X (3N; R3 = 0 on the eliminated system) of the linear system that produced it, None
for X^0. Wall times count the method's own work: assembly, linear solves, the nonlinear
residual of the Newton iterates (the stopping test). Recording a Krylov iterate (building it,
its residuals) and the monitor are excluded.
"""

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import newton_system as ns
from .linear_solve import LinearSolveError, solve_direct

SYSTEMS = ("full", "eliminated")
VARIANTS = ("exact", "inexact")
DEFAULT_TOL = 1e-10            # DESIGN §8: Newton stops at ‖R_lin‖/‖(F, 0)‖ ≤ 1e-10 ...
EXACT_LINEAR_TOL = 2e-12       # ... and exact solves reach ‖R_alg‖/‖B‖ ≤ 2e-12


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


def linear_step(rows, cfun, system, X):
    """The Newton system at X (DESIGN §3), full or eliminated; the guess is X itself, or for the
    eliminated system the unknowns of X it keeps (u1, and u2 or λ at each vertex)."""
    alpha, beta, B3 = ns.complementarity_rows(rows, cfun, X)
    norm_B = float(np.linalg.norm(np.concatenate([rows.F, B3])))
    if system == "full":
        A, B = ns.full_system(rows, alpha, beta, B3)
        return LinearStep(A, B, X, norm_B, lambda y: y, lambda r: r)
    A, b, elim = ns.eliminated_system(rows, alpha, beta, B3)
    u1, u2, lam = ns.split(X, rows.n)
    guess = np.concatenate([u1, np.where(elim.eliminate_lambda, u2, lam)])
    return LinearStep(A, b, guess, norm_B, elim.expand,
                      lambda r: np.concatenate([r, np.zeros(rows.n)]))


def linear_tolerance(variant, tol, residual):
    """‖R_alg‖/‖B‖ the step must reach; `residual` = ‖R_lin(X^{k-1})‖/‖(F, 0)‖."""
    if variant == "exact":
        return EXACT_LINEAR_TOL * min(1.0, tol / DEFAULT_TOL)
    return residual


def solve_step(step, krylov, tol, test_every, on_iterate):
    """X^k, its residual R (3N) and the linear iterations of one step."""
    if krylov is None:
        y, its = solve_direct(step.A, step.b)
        r = step.b - step.A @ y
    else:
        y, r, its = krylov.solve(step.A, step.b, step.guess, tol, step.norm_B, test_every,
                                 on_iterate)
    return step.expand(y), step.pad(r), its


def check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r} (choose from: {', '.join(choices)})")


def check_method(system, variant, krylov):
    """ValueError unless the system and variant exist and the variant can use the solver."""
    check_choice("Newton system", system, SYSTEMS)
    check_choice("Newton variant", variant, VARIANTS)
    if variant == "inexact" and krylov is None:
        raise ValueError("the inexact Newton variant needs linear_solver 'gmres' (a direct "
                         "solve is exact)")


def semismooth_newton(rows, g, cfun="min", system="full", variant="exact", krylov=None,
                      tol=DEFAULT_TOL, max_it=100, X0=None, monitor=None):
    """Semismooth Newton from X0 (default (g, 0, 0)); krylov=None: MUMPS (exact only)."""
    check_method(system, variant, krylov)
    clock = Stopwatch()
    X = ns.initial_guess(rows, g) if X0 is None else np.array(X0, dtype=float)
    scale = rows.norm_F
    history = []

    def record(kind, k, its, cumulative, X, R, norm_B):
        residual = float(np.linalg.norm(ns.nonlinear_residual(rows, cfun, X))) / scale
        rec = {"newton_it": k, "linear_it": its, "cumulative_linear_its": cumulative,
               "wall_time_s": clock.pause(), "residual": residual,
               "alg_residual": None if R is None else float(np.linalg.norm(R)) / norm_B,
               "kind": kind}
        if monitor is not None:
            monitor(rec, X, R)
        history.append(rec)
        clock.resume()
        return residual

    def krylov_recorder(k, step, done):
        def on_iterate(its, current):
            clock.pause()
            y, r = current()
            record("krylov", k, its, done + its, step.expand(y), step.pad(r), step.norm_B)
        return on_iterate

    residual, done = record("initial", 0, 0, 0, X, None, None), 0
    for k in range(1, max_it + 1):
        if residual <= tol:
            break
        step = linear_step(rows, cfun, system, X)
        try:
            X_new, R, its = solve_step(step, krylov, linear_tolerance(variant, tol, residual),
                                       1 if variant == "exact" else krylov.nu,
                                       krylov_recorder(k, step, done))
        except LinearSolveError as e:
            return NewtonResult(X, False, f"linear solver failed at Newton step {k}: {e}",
                                k - 1, done + e.its, history)
        done += its
        if not np.all(np.isfinite(X_new)):
            return NewtonResult(X, False, f"non-finite iterate at Newton step {k}",
                                k - 1, done, history)
        X = X_new
        residual = record("newton", k, its, done, X, R, step.norm_B)
    k = history[-1]["newton_it"]
    if residual <= tol:
        return NewtonResult(X, True, f"relative residual {residual:.2e} <= {tol:.0e}",
                            k, done, history)
    return NewtonResult(X, False, f"no convergence in {max_it} Newton steps "
                        f"(relative residual {residual:.2e} > {tol:.0e})", k, done, history)
