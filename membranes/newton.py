"""Semismooth Newton for the discrete contact problem (DESIGN §3, §8).

    k = 0, X^0 = (g, 0, 0)
    repeat: linearise the C-function at X^{k-1}, solve A^{k-1} X^k = B^{k-1}
    until ‖R_lin(X^k)‖ / ‖(F, 0)‖ ≤ tol  (1e-10 by default, DESIGN §8)

The step is solved either on the full 3N system or on the eliminated 2N system
(newton_system). Non-convergence is reported, never hidden: the result carries
`converged = False` and a reason. A `monitor(record, X)` callback sees every iterate
(X^0 included); the time it takes is excluded from the recorded wall time.
"""

import time
from dataclasses import dataclass, field

import numpy as np

from . import newton_system as ns
from .linear_solve import LinearSolveError, solve_direct

SYSTEMS = ("full", "eliminated")


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
        self.elapsed += time.perf_counter() - self._start
        return self.elapsed

    def resume(self):
        self._start = time.perf_counter()


def newton_step(rows, cfun, system, X):
    """One exact semismooth Newton step from X: returns X^{new} and the linear iterations."""
    alpha, beta, B3 = ns.complementarity_rows(rows, cfun, X)
    if system == "full":
        A, B = ns.full_system(rows, alpha, beta, B3)
        Xn, its = solve_direct(A, B)
    else:
        A, B, elim = ns.eliminated_system(rows, alpha, beta, B3)
        Y, its = solve_direct(A, B)
        Xn = elim.expand(Y)
    return Xn, its


def semismooth_newton(rows, g, cfun="min", system="full", tol=1e-10, max_it=100, X0=None,
                      monitor=None):
    """Exact semismooth Newton (direct linear solves) from X0 (default (g, 0, 0))."""
    if system not in SYSTEMS:
        raise ValueError(f"unknown Newton system {system!r} (choose from: {', '.join(SYSTEMS)})")
    clock = Stopwatch()
    X = ns.initial_guess(rows, g) if X0 is None else np.array(X0, dtype=float)
    scale = rows.norm_F
    history, cumulative = [], 0

    def record(k, its, X):
        residual = float(np.linalg.norm(ns.nonlinear_residual(rows, cfun, X))) / scale
        rec = {"newton_it": k, "linear_it": its, "cumulative_linear_its": cumulative,
               "wall_time_s": clock.pause(), "residual": residual}
        if monitor is not None:
            monitor(rec, X)
        history.append(rec)
        clock.resume()
        return residual

    residual = record(0, 0, X)
    for k in range(1, max_it + 1):
        if residual <= tol:
            break
        try:
            X_new, its = newton_step(rows, cfun, system, X)
        except LinearSolveError as e:
            return NewtonResult(X, False, f"linear solver failed at Newton step {k}: {e}",
                                k - 1, cumulative, history)
        if not np.all(np.isfinite(X_new)):
            return NewtonResult(X, False, f"non-finite iterate at Newton step {k}",
                                k - 1, cumulative, history)
        X = X_new
        cumulative += its
        residual = record(k, its, X)
    k = history[-1]["newton_it"]
    if residual <= tol:
        return NewtonResult(X, True, f"relative residual {residual:.2e} <= {tol:.0e}",
                            k, cumulative, history)
    return NewtonResult(X, False, f"no convergence in {max_it} Newton steps "
                        f"(relative residual {residual:.2e} > {tol:.0e})", k, cumulative, history)
