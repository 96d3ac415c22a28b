"""The API: `solve(problem, ...)` runs the discretisation and semismooth Newton on a problem.

    >>> from membranes import scenes, solve
    >>> sol = solve(scenes.disk(h=0.05), cfun="fb")          # exact Newton, GMRES + ILU(0)
    >>> sol.converged, sol.newton_iterations, sol.energy_error
    >>> sol.u1, sol.u2, sol.lam          # dolfinx P1 Functions on the computational mesh
    >>> sol.history                      # one dict per recorded iterate (X^0 included)

Only what the problem declares is computed: the energy error only where the scene knows the
exact solution; the estimators of DESIGN §7 unless `estimators=False`. Neither is counted in
the wall times (the exact and inexact methods do not use them; their costs are reported apart:
`estimator_setup_s`, `estimator_time_s`).
"""

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from . import cfunctions
from .discretisation import EnergyError, discretise
from .estimators import COLUMNS as ESTIMATOR_COLUMNS
from .estimators import Estimators
from .krylov import DEFAULT_MAX_LINEAR_ITS, DEFAULT_NU, Krylov
from .meshes import mesh_size
from .newton import DEFAULT_TOL, check_choice, check_method, semismooth_newton
from .newton_system import linear_rows, split

LINEAR_SOLVERS = ("gmres", "direct")


@dataclass
class Solution:
    problem: object
    disc: object
    X: np.ndarray
    converged: bool
    reason: str
    newton_iterations: int
    linear_iterations: int
    wall_time_s: float
    history: list
    options: dict
    energy_error: float = None
    functions: list = field(default_factory=list)
    eta_K: np.ndarray = None          # local distribution η_K at X (DESIGN §7), if estimated
    estimator_times: tuple = (None, None)   # (set-up, all evaluations) in seconds

    @property
    def u1(self):
        return self.functions[0]

    @property
    def u2(self):
        return self.functions[1]

    @property
    def lam(self):
        return self.functions[2]

    @property
    def final_record(self):
        """The history record of X, the last Newton iterate (Krylov iterates may follow it
        when a linear solve failed)."""
        return next(rec for rec in reversed(self.history) if rec["kind"] != "krylov")

    def complementarity_violation(self):
        """Largest violation of w = u1 - u2 ≥ 0, λ ≥ 0, λ w = 0 at interior vertices, relative
        to the data scale (u: max(g, |u|∞); λ: max(|λ|∞, max_a |F_α,a| / D_a))."""
        d = self.disc
        u1, u2, lam = split(self.X, d.n)
        inner = d.interior
        w, lam = (u1 - u2)[inner], lam[inner]
        u_scale = max(d.problem.g, np.abs(u1).max(), np.abs(u2).max())
        load = np.maximum(np.abs(d.F1), np.abs(d.F2))[inner] / d.D[inner]
        lam_scale = max(np.abs(lam).max(initial=0.0), load.max(initial=0.0),
                        np.finfo(float).tiny)
        return float(max(np.max(-w, initial=0.0) / u_scale,
                         np.max(-lam, initial=0.0) / lam_scale,
                         np.max(np.abs(w * lam), initial=0.0) / (u_scale * lam_scale)))

    def summary(self):
        """The documented keys of summary.json (README)."""
        p = self.problem
        mesh = p.mesh
        return {
            "scene": p.name,
            "description": p.description,
            "n_vertices": int(mesh.topology.index_map(0).size_global),
            "n_cells": int(mesh.topology.index_map(2).size_global),
            "h": mesh_size(mesh),
            "h_coarse": mesh_size(p.hierarchy.meshes[0]),
            "levels": p.levels,
            "mu1": p.mu1, "mu2": p.mu2, "g": p.g,
            "newton": self.options["newton"],
            "cfun": self.options["cfun"],
            "system": self.options["system"],
            "linear_solver": self.options["linear_solver"],
            "petsc_options": self.options["petsc_options"],
            "nu": self.options["nu"],
            "converged": self.converged,
            "reason": self.reason,
            "newton_iterations": self.newton_iterations,
            "linear_iterations": self.linear_iterations,
            "wall_time_s": self.wall_time_s,
            "final_residual": self.final_record["residual"],
            "complementarity_violation": self.complementarity_violation(),
            "energy_error": self.energy_error,
            **self._estimator_summary(),
        }

    def _estimator_summary(self):
        last = self.final_record
        out = {k: last.get(k) for k in ESTIMATOR_COLUMNS}
        out["bound_guaranteed"] = last.get("bound")
        eta, err = out["eta"], self.energy_error
        out["effectivity"] = eta / err if eta is not None and err else None
        out["estimator_setup_s"], out["estimator_time_s"] = self.estimator_times
        return out


def _krylov(linear_solver, petsc_options, nu, max_linear_its):
    """The Krylov solver of the run, None for MUMPS (exact Newton only)."""
    if linear_solver == "gmres":
        return Krylov(petsc_options, DEFAULT_NU if nu is None else nu,
                      DEFAULT_MAX_LINEAR_ITS if max_linear_its is None else max_linear_its)
    given = [k for k, v in (("petsc_options", petsc_options), ("nu", nu),
                            ("max_linear_its", max_linear_its)) if v is not None]
    if given:
        raise ValueError(f"{given[0]} applies to linear_solver 'gmres' only")
    return None


def solve(problem, newton="exact", cfun="min", system="full", linear_solver="gmres",
          petsc_options=None, nu=None, max_linear_its=None, tol=DEFAULT_TOL, max_newton=100,
          estimators=True, progress=False):
    """Solve the discrete contact problem of `problem` by semismooth Newton (DESIGN §3, §8).

    newton: 'exact' (linear residual ≤ 2e-12) or 'inexact' (≤ the previous nonlinear residual,
    DESIGN §8); cfun: 'min' or 'fb'; system: 'full' (3N) or 'eliminated' (2N);
    linear_solver: 'gmres' (PETSc KSP, GMRES + ILU(0) unless `petsc_options`, a dict such as
    {"pc_type": "jacobi"}, say otherwise; every ν = `nu` (10) Krylov steps the iterate is
    recorded; at most `max_linear_its` (10000) iterations per step) or 'direct' (MUMPS, exact
    only); tol: stop at ‖R_lin‖/‖(F, 0)‖ ≤ tol; estimators: evaluate the a posteriori
    estimators of DESIGN §7 at every recorded iterate (history columns eta, eta_disc, …; set
    up once per mesh); progress: True for one stderr line per Newton step, or a callable taking
    the line.
    """
    cfunctions.get(cfun)
    check_choice("linear solver", linear_solver, LINEAR_SOLVERS)
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number, got {tol}")
    if int(max_newton) < 1:
        raise ValueError(f"max_newton must be at least 1, got {max_newton}")
    krylov = _krylov(linear_solver, petsc_options, nu, max_linear_its)
    check_method(system, newton, krylov)
    say = progress if callable(progress) else \
        (lambda line: print(line, file=sys.stderr, flush=True)) if progress else None

    t0 = time.perf_counter()
    disc = discretise(problem)
    rows = linear_rows(disc)
    setup_time = time.perf_counter() - t0
    error = EnergyError(disc) if problem.exact is not None else None
    t = time.perf_counter()
    est = Estimators(disc) if estimators else None
    est_times = [time.perf_counter() - t if estimators else None, 0.0 if estimators else None]
    local = {}

    def estimate(rec, X, R):
        t = time.perf_counter()
        alg = rec["alg_residual"]
        if R is None:   # X^0 comes from no linear solve: its linear rows are out of balance
            R = np.concatenate([rows.F - rows.E @ X, np.zeros(disc.n)])
            alg = float(np.linalg.norm(R)) / rows.norm_F
        values = est.evaluate(X, R, alg_residual=alg)
        rec.update({k: values[k] for k in ESTIMATOR_COLUMNS}, bound=values["bound"])
        if rec["kind"] != "krylov":
            local["eta_K"] = values["eta_K"]
        est_times[1] += time.perf_counter() - t

    def monitor(rec, X, R):
        rec["wall_time_s"] += setup_time
        rec["energy_error"] = error(X) if error is not None else None
        if est is not None:
            estimate(rec, X, R)
        if say is not None and rec["kind"] != "krylov":
            line = (f"newton {rec['newton_it']:3d}  residual {rec['residual']:.3e}  "
                    f"linear its {rec['linear_it']:5d}  total {rec['cumulative_linear_its']:6d}  "
                    f"time {rec['wall_time_s']:7.2f} s")
            if rec["energy_error"] is not None:
                line += f"  energy error {rec['energy_error']:.4e}"
            if rec.get("eta") is not None:
                line += f"  eta {rec['eta']:.4e}"
            say(line)

    result = semismooth_newton(rows, problem.g, cfun=cfun, system=system, variant=newton,
                               krylov=krylov, tol=tol, max_it=int(max_newton), monitor=monitor)
    sol = Solution(problem, disc, result.X, result.converged, result.reason,
                   result.newton_iterations, result.linear_iterations,
                   result.history[-1]["wall_time_s"], result.history,
                   {"newton": newton, "cfun": cfun, "system": system,
                    "linear_solver": linear_solver,
                    "petsc_options": {} if krylov is None else krylov.options,
                    "nu": None if krylov is None else krylov.nu},
                   functions=disc.functions(result.X), eta_K=local.get("eta_K"),
                   estimator_times=tuple(est_times))
    sol.energy_error = sol.final_record["energy_error"]
    return sol
