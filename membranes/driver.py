"""The API: `solve(problem, ...)` runs the discretisation and semismooth Newton on a problem.

    >>> from membranes import scenes, solve
    >>> sol = solve(scenes.disk(h=0.05), cfun="fb")          # exact Newton, GMRES + ILU(0)
    >>> sol.converged, sol.newton_iterations, sol.energy_error
    >>> sol.u1, sol.u2, sol.lam          # dolfinx P1 Functions on the computational mesh
    >>> sol.history                      # one dict per recorded iterate (X^0 included)

Only what the problem declares is computed: the energy error only where the scene knows the
exact solution; the estimators of DESIGN §7 unless `estimators=False`. The energy error never
counts in the wall times; the estimators count for the adaptive method, which uses them (set-up
and evaluations), and not for exact and inexact Newton, which do not (their costs are reported
apart in any case: `estimator_setup_s`, `estimator_time_s`). The wall time runs from the call of
`solve`: the Krylov solver's set-up counts (it checks the vertex_amg options on a 2 x 2
system: in a fresh process, the first compiled kernel's first call, membranes.compiled).
"""

import sys
import time
from dataclasses import dataclass, field

import numpy as np

from . import cfunctions, parallel
from .app import checks
from .discretisation import EnergyError, as_one_run, discretise, discretise_in_parts
from .estimators import ALG_ROUNDOFF, Estimators
from .estimators import COLUMNS as ESTIMATOR_COLUMNS
from .krylov import DEFAULT_MAX_LINEAR_ITS, DEFAULT_NU, Krylov
from .mean import LevelMean, MeanSolve, mean_bound, mean_of, theta
from .meshes import mesh_size
from .nested import level_problem, prolong, prolongation
from .newton import (DEFAULT_GAMMA, DEFAULT_TOL, check_choice, check_gamma, check_method,
                     linear_tolerance, semismooth_newton)
from .newton_system import initial_guess as paper_guess, initial_residual, linear_rows, split
from .preconditioner import DEFAULT_INNER, INNER_PREFIX

LINEAR_SOLVERS = ("gmres", "direct")
ALG_FLUXES = ("nu", "multilevel")
RECORD_KEYS = ESTIMATOR_COLUMNS + ("bound",)   # what the estimators add to a history record


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
    per_level: list = field(default_factory=list)   # one dict per level solved (_LevelRun)
    comm: object = None   # the processes that shared the patches (membranes.parallel), or None

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
        to the data scale (DESIGN §11): w against max(u_data, |u|∞), λ against
        max(λ_data, |λ|∞) (Discretisation.data_scales: the displacement the loads make on
        their own, the size against which newton_system measures residuals)."""
        d = self.disc
        u1, u2, lam = split(self.X, d.n)
        inner = d.interior
        w, lam = (u1 - u2)[inner], lam[inner]
        u_data, lam_data = d.data_scales()
        u_scale = max(u_data, np.abs(u1).max(), np.abs(u2).max())
        lam_scale = max(lam_data, np.abs(lam).max(initial=0.0), np.finfo(float).tiny)
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
            "gamma_lin": self.options["gamma_lin"],
            "gamma_alg": self.options["gamma_alg"],
            "alg_flux": self.options["alg_flux"],
            "initial_guess": self.options.get("initial_guess", "paper"),
            "nested": self.options.get("nested", False),
            "processes": 1 if self.comm is None else self.comm.size,
            "per_level": self.per_level,
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


def _reject(applies_to, **options):
    """ValueError naming the first of `options` that was given (not None): it applies to
    `applies_to` only."""
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise ValueError(f"{given[0]} applies to {applies_to} only")


def _krylov(linear_solver, petsc_options, nu, max_linear_its):
    """The Krylov solver of the run, None for MUMPS (exact Newton only)."""
    if linear_solver == "gmres":
        return Krylov(petsc_options, DEFAULT_NU if nu is None else nu,
                      DEFAULT_MAX_LINEAR_ITS if max_linear_its is None else max_linear_its)
    _reject("linear_solver 'gmres'", petsc_options=petsc_options, nu=nu,
            max_linear_its=max_linear_its)
    return None


def check_linear_solver(linear_solver="gmres", petsc_options=None, nu=None,
                        max_linear_its=None):
    """The Krylov solver of a run (None for MUMPS) once its options are checked, before any
    mesh is needed: `petsc_options` (a dict, or a string as on the command line) parsed
    (membranes.app.checks.parse_petsc_options), and refused if PETSc would not use one of them
    (a misspelt name, an option of another KSP or PC; `checks.check_petsc_options_used` on the
    options the solves apply). ValueError otherwise."""
    check_choice("linear solver", linear_solver, LINEAR_SOLVERS)
    if petsc_options is not None:
        petsc_options = checks.parse_petsc_options(petsc_options)
    krylov = _krylov(linear_solver, petsc_options, nu, max_linear_its)
    if krylov is not None and petsc_options:
        inner = krylov.vertex_amg
        inner_options = None if inner is None else \
            {**(DEFAULT_INNER if "pc_type" not in inner else {}), **inner}
        # krylov._petsc: the options each solve gives its KSP (vertex_amg: pc_type none)
        checks.check_petsc_options_used(petsc_options, krylov._petsc, inner_options,
                                        INNER_PREFIX, shown=krylov.options)
    return krylov


def _check_memory(problem, krylov, linear_solver, estimators, alg_flux, max_vertices, comm):
    """Refuse a computational mesh whose run needs more memory than each process has, or more
    vertices than `max_vertices`, before anything is assembled (membranes.app.checks)."""
    vertices = problem.mesh.topology.index_map(0).size_global
    max_vertices = checks.check_max_vertices(max_vertices)
    available = None if max_vertices is not None else checks.available_memory(comm)
    pc_type = None if krylov is None else krylov.options.get("pc_type")
    checks.check_size(vertices, available, max_vertices,
                      what=f"the computational mesh of {problem.name!r}",
                      linear_solver=linear_solver, pc_type=pc_type, estimators=estimators,
                      alg_flux=alg_flux)


def _stopping(newton, tol, gamma_lin, gamma_alg):
    """(tol, γ_lin, γ_alg) of the variant: tol for exact and inexact, the γ's for adaptive
    (DESIGN §8); the others are None and must not be given."""
    if newton != "adaptive":
        _reject("newton 'adaptive'", gamma_lin=gamma_lin, gamma_alg=gamma_alg)
        tol = DEFAULT_TOL if tol is None else tol
        if not (np.isfinite(tol) and tol > 0):
            raise ValueError(f"tol must be a positive finite number, got {tol}")
        return tol, None, None
    _reject("newton 'exact' and 'inexact' (adaptive stops by gamma_lin)", tol=tol)
    gammas = [DEFAULT_GAMMA if g is None else g for g in (gamma_lin, gamma_alg)]
    for name, g in zip(("gamma_lin", "gamma_alg"), gammas):
        check_gamma(name, g)
    return (None, *gammas)


INITIAL_GUESSES = ("paper", "zero")


def _nested(problem, nested):
    """Nested iteration or not: the default (None) where the problem has a hierarchy."""
    if nested is None:
        return problem.levels >= 1
    if not isinstance(nested, (bool, np.bool_)):
        raise ValueError(f"nested must be True, False or None, got {nested!r}")
    if nested and problem.levels < 1:
        raise ValueError("nested iteration needs a mesh hierarchy: levels >= 1 (--levels J)")
    return bool(nested)


def _initial_guess(initial_guess, disc):
    """X^0 of `solve` (nodal u1, u2, λ), or None for the paper's (g, 0, 0)."""
    if initial_guess is None or (isinstance(initial_guess, str) and initial_guess == "paper"):
        return None
    if isinstance(initial_guess, str):
        check_choice("initial guess", initial_guess, INITIAL_GUESSES)
        return np.zeros(3 * disc.n)
    # checked by semismooth_newton: 3N finite values
    return initial_guess(disc) if callable(initial_guess) else initial_guess


def _algebraic_flux(problem, alg_flux, estimators, newton):
    """The run's algebraic flux (DESIGN §6): the one asked for, else 'multilevel' where the
    problem has a hierarchy (levels ≥ 1), else 'nu'; None without estimators."""
    if not estimators:
        if newton == "adaptive":
            raise ValueError("the adaptive Newton variant needs the estimators")
        _reject("runs with estimators", alg_flux=alg_flux)
        return None
    if alg_flux is None:
        alg_flux = "multilevel" if problem.levels >= 1 else "nu"
    check_choice("algebraic flux", alg_flux, ALG_FLUXES)
    if alg_flux == "multilevel":
        if problem.levels < 1:
            raise ValueError("multilevel algebraic flux needs a mesh hierarchy: levels >= 1 "
                             "(--levels J)")
    return alg_flux


class IterateEstimates:
    """The estimators (DESIGN §7) at the recorded iterates of a run, with its algebraic flux
    σ_alg (DESIGN §6): the `estimate` callback of semismooth Newton (membranes.newton).

    Every recorded iterate is some X^{k,i}, the i-th Krylov iterate of the linear solve of
    Newton step k, whose initial guess X^{k,0} is the Newton iterate X^{k-1} (X^0 included).

    * 'multilevel': σ_alg = MultilevelFlux.sigma(R), ∇·σ_alg = r_h exactly, no remainder:
      every iterate is estimated when it is recorded.
    * 'nu': an iterate whose algebraic residual is at round-off needs no flux (Estimators:
      σ_alg = 0 and the Poincaré remainder) and is estimated when recorded. Any other X^{k,i}
      waits for the next iterate of the same solve, X^{k,i+ν} (or the solve's last iterate,
      fewer steps on), then gets σ_alg = σ_disc(X^{k,i+ν}) - σ_disc(X^{k,i}) and its remainder
      (Estimators.nu_flux). A Newton iterate X^{k-1} = X^{k,0} is thus paired with the first
      iterate of step k. Two kinds of iterates are followed by none: the last one of a run
      (`finish` estimates it without flux: η is missing unless its residual is at round-off),
      and in adaptive runs X^{k,i+ν} once X^{k,i} is accepted (not estimated at all: the
      method does not use it).

    An adaptive step's Newton record is the accepted Krylov iterate again (`same_as`): it
    takes that record's values. Records get the COLUMNS of the estimators and `bound`
    (RECORD_KEYS), None where not estimated.

    Built and called only inside `solve`, whose BLAS runs on one thread
    (`discretisation.as_one_run`), as the small dense blocks of the patch problems want
    (`parallel.one_blas_thread`).
    """

    def __init__(self, disc, rows, alg_flux, comm=None):
        t = time.perf_counter()
        self.rows = rows
        # with several processes each sets up its own vertices' patches (parallel)
        self.sum_parts = None if comm is None else parallel.Summation(comm)
        self.est = Estimators(disc, owned=parallel.owned_vertices(disc.n, comm),
                              sum_parts=self.sum_parts)
        if alg_flux == "multilevel":
            from .algebraic_flux import MultilevelFlux   # only a run that uses it pays
            hierarchy = disc.problem.hierarchy
            owned = None if comm is None else \
                [parallel.owned_vertices(m.topology.index_map(0).size_local, comm)
                 for m in hierarchy.meshes[:-1]]
            self.multilevel = MultilevelFlux(disc, hierarchy, owned=owned)
        else:
            self.multilevel = None
        self.setup_time = time.perf_counter() - t
        self.time = 0.0
        self.pending = None        # ('nu') (record, X, R) waiting for its later iterate
        self.latest_eta_K = None   # η_K of the iterate estimated last
        self.eta_K = None          # η_K of the Newton iterate (or X^0) estimated last

    def __call__(self, rec, X, R, same_as=None):
        t = time.perf_counter()
        if same_as is not None:
            # the accepted iterate is the one estimated last (its estimate met the criterion);
            # the later iterate of its solve (pending, 'nu') will have no successor
            rec.update({k: same_as[k] for k in RECORD_KEYS})
            if self.pending is not None:
                self.pending[0].update(dict.fromkeys(RECORD_KEYS))
            self.eta_K, self.pending, ready = self.latest_eta_K, None, []
        else:
            if R is None:   # X^0 comes from no linear solve: its linear rows are out of balance
                R = initial_residual(self.rows, X)
            ready = [] if self.pending is None else [self._estimate(*self.pending, (X, R))]
            self.pending = None
            if self.multilevel is not None or self._alg(rec, R) <= ALG_ROUNDOFF:
                ready.append(self._estimate(rec, X, R))
            else:
                self.pending = (rec, X, R)
        self.time += time.perf_counter() - t
        return ready

    def finish(self):
        """Estimate the iterate still waiting for a later one: none will come."""
        t = time.perf_counter()
        if self.pending is not None:
            self._estimate(*self.pending)
            self.pending = None
        self.time += time.perf_counter() - t

    def _alg(self, rec, R):
        """‖W R‖/‖W B‖ (‖W R‖/‖W F‖ for X^0; W: newton_system's row weights)."""
        alg = rec["alg_residual"]
        if alg is None:
            return float(np.linalg.norm(self.rows.weighted(R))) / self.rows.norm_F
        return alg

    def _estimate(self, rec, X, R, later=None):
        """Fill in rec's estimates at X; `later` = (X', R') the next iterate for 'nu'."""
        alg = self._alg(rec, R)
        if self.multilevel is not None:
            sigma_alg = self.multilevel.sigma(R)
            if self.sum_parts is not None:   # this process's patches: add the others'
                sigma_alg = self.sum_parts(sigma_alg)
            values = self.est.evaluate(X, R, alg, sigma_alg=sigma_alg)
        elif later is not None:
            sigma_alg, eta_rem = self.est.nu_flux(X, R, *later)
            values = self.est.evaluate(X, R, alg, sigma_alg=sigma_alg, eta_rem=eta_rem)
        else:
            values = self.est.evaluate(X, R, alg)
        rec.update({k: values[k] for k in RECORD_KEYS})
        self.latest_eta_K = values["eta_K"]
        if rec["kind"] != "krylov":
            self.eta_K = values["eta_K"]
        return rec, X, R


@as_one_run
def solve(problem, newton="exact", cfun="min", system="full", linear_solver="gmres",
          petsc_options=None, nu=None, max_linear_its=None, tol=None, max_newton=100,
          estimators=True, progress=False, gamma_lin=None, gamma_alg=None, alg_flux=None,
          initial_guess=None, nested=None, comm=None, max_vertices=None):
    """Solve the discrete contact problem of `problem` by semismooth Newton (DESIGN §3, §8).

    newton: 'exact' (linear residual ≤ 2e-12), 'inexact' (≤ the previous nonlinear residual)
    or 'adaptive' (Algorithm 1 of DESIGN §8: GMRES stops at η_alg ≤ γ_alg max(η_disc, η_lin),
    Newton at η_lin ≤ γ_lin η_disc; γ = `gamma_lin`, `gamma_alg`, 0.3 by default; estimators
    evaluated every ν Krylov steps; see membranes.newton for the accepted iterate);
    cfun: 'min' or 'fb'; system: 'full' (3N) or 'eliminated' (2N);
    linear_solver: 'gmres' (PETSc KSP, GMRES + ILU(0) unless `petsc_options`, a dict such as
    {"pc_type": "jacobi"}, say otherwise; every ν = `nu` (10) Krylov steps the iterate is
    recorded; at most `max_linear_its` (10000) iterations per step) or 'direct' (MUMPS, exact
    only); tol: exact and inexact stop at ‖R_lin‖/‖(F, 0)‖ ≤ tol (1e-10); estimators: evaluate
    the a posteriori estimators of DESIGN §7 at every recorded iterate (history columns eta,
    eta_disc, …; set up once per mesh; adaptive needs them); alg_flux: the algebraic flux of
    DESIGN §6 for iterates whose residual is not at round-off, 'multilevel' (default where the
    problem has levels ≥ 1) or 'nu' (ν extra iterations, default otherwise; see
    IterateEstimates); progress: True for one stderr line per Newton step, or a callable
    taking the line; initial_guess: X^0, 'paper' (default: (g, 0, 0), DESIGN §3), 'zero', or
    the nodal values (u1, u2, λ) as one array of 3N values or a function of the
    discretisation returning it (nested runs: X^0 on T_0, so not an array);
    nested: nested iteration on the hierarchy (membranes.nested, `_solve_nested`): solve on
    T_0, prolong the solution to T_1 as its initial guess, ..., up to T_J, every level with
    the variant's stopping test; default True where the problem has levels ≥ 1. Iteration
    counts and the wall time are those of all levels (per level: `Solution.per_level`); the
    iterate, estimates and energy error those of T_J;
    comm: an MPI communicator of P ≥ 2 processes (membranes.pipeline: each process builds the
    same problem on MPI.COMM_SELF; Newton and GMRES run on process 0, the estimators on the
    others, which share the patch problems when P ≥ 3; progress lines come from process 0;
    every process returns the same Solution, whose discretisation on the estimator processes
    has no stiffness matrices, S1 = S2 = None); None: one process;
    max_vertices: refuse a computational mesh of more vertices (default: refuse one whose run
    needs more memory than each process has, membranes.app.checks, issue 29).
    """
    started = time.perf_counter()       # the wall time of the run starts here (module notes)
    parallel.check_replicated(problem.mesh, comm)
    comm = comm if comm is not None and comm.size > 1 else None
    cfunctions.get(cfun)
    check_choice("linear solver", linear_solver, LINEAR_SOLVERS)
    if int(max_newton) < 1:
        raise ValueError(f"max_newton must be at least 1, got {max_newton}")
    krylov = check_linear_solver(linear_solver, petsc_options, nu, max_linear_its)
    check_method(system, newton, krylov)
    if krylov is not None and krylov.options.get("pc_type") == "vertex_amg" and \
            system != "eliminated":
        raise ValueError("pc_type vertex_amg preconditions the eliminated system only "
                         "(system='eliminated', --system eliminated)")
    tol, gamma_lin, gamma_alg = _stopping(newton, tol, gamma_lin, gamma_alg)
    alg_flux = _algebraic_flux(problem, alg_flux, estimators, newton)
    if isinstance(initial_guess, str):
        check_choice("initial guess", initial_guess, INITIAL_GUESSES)
    nested = _nested(problem, nested)
    _check_memory(problem, krylov, linear_solver, estimators, alg_flux, max_vertices, comm)
    guess_name = initial_guess if isinstance(initial_guess, str) else \
        "paper" if initial_guess is None else "given"
    say = progress if callable(progress) else \
        (lambda line: print(line, file=sys.stderr, flush=True)) if progress else None
    if comm is not None and comm.rank > 0:
        say = None

    options = {"newton": newton, "cfun": cfun, "system": system,
               "linear_solver": linear_solver,
               "petsc_options": {} if krylov is None else krylov.options,
               "nu": None if krylov is None else krylov.nu,
               "gamma_lin": gamma_lin, "gamma_alg": gamma_alg, "alg_flux": alg_flux,
               "initial_guess": guess_name, "nested": nested}
    if nested and not (initial_guess is None or isinstance(initial_guess, str) or
                       callable(initial_guess)):
        raise ValueError("with nested iteration the initial guess is that of the coarse "
                         "mesh T_0: give 'paper', 'zero' or a function of the "
                         "discretisation, or nested=False for nodal values on the "
                         "computational mesh")
    link = None
    if comm is not None:        # Newton on process 0, the estimators on the others
        from . import pipeline
        est_comm, link, lent = pipeline.roles(comm)
        if est_comm is not None:
            return _on_estimator_process(problem, comm, est_comm, lent)
    method = _Method(newton, cfun, system, krylov, tol, int(max_newton), gamma_lin,
                     gamma_alg, say, link)
    try:
        if not nested:
            runs = [_solve_on(problem, method, alg_flux, initial_guess, level=problem.levels,
                              started=started)]
        else:
            runs = _solve_nested(problem, method, alg_flux, estimators, initial_guess, started)
        sol = _solution(problem, runs, options)
    except Exception as e:
        if link is not None:
            link.close()
            comm.bcast(("error", type(e).__name__, str(e)), root=0)
        raise
    if link is not None:
        link.close()
        comm.bcast({k: getattr(sol, k) for k in _SHARED}, root=0)
        sol.comm = comm
    return sol


_SHARED = ("X", "converged", "reason", "newton_iterations", "linear_iterations",
           "wall_time_s", "history", "options", "energy_error", "eta_K", "estimator_times",
           "per_level")


def _on_estimator_process(problem, comm, est_comm, lent):
    """An estimator process's part of a run on several processes (membranes.pipeline): serve
    the estimates, then return the Solution that process 0 made."""
    from .pipeline import serve
    level, disc = serve(problem, comm, est_comm, lent)
    est_comm.Free()
    shared = comm.bcast(None, root=0)
    if isinstance(shared, tuple):           # process 0 failed: so does this one
        raise (ValueError if shared[1] == "ValueError" else RuntimeError)(shared[2])
    if level != problem.levels:
        disc = discretise(problem)
    sol = Solution(problem, disc, functions=disc.functions(shared["X"]), **shared)
    sol.comm = comm
    return sol


@dataclass
class _Method:
    """The Newton method of a run, as `solve` checked it (one level solves with it)."""
    newton: str
    cfun: str
    system: str
    krylov: object
    tol: float
    max_newton: int
    gamma_lin: float
    gamma_alg: float
    say: object
    link: object = None      # process 0's link to the estimator processes (pipeline), or None

    @property
    def mean_options(self):
        """vertex_amg's inner options where the steps take the mesh's exact mean
        (membranes.mean: Krylov with vertex_amg on the eliminated system), else None."""
        if self.system != "eliminated" or self.krylov is None:
            return None
        return self.krylov.vertex_amg


@dataclass
class _EstimatorTimes:
    """What a released level keeps of its IterateEstimates."""
    setup_time: float
    time: float


@dataclass
class _LevelRun:
    """One semismooth Newton solve on one mesh (a level of a nested run, or the whole run)."""
    level: int
    disc: object
    result: object
    est: object
    wall_time_s: float      # this level's own: set-up, prolongation (nested) and Newton (on
    # several processes, the parts made ahead count in the level whose waits they fill)
    _record: dict = None    # the figures, once `release` dropped what they come from

    def release(self):
        """Drop the level's discretisation and estimators (a nested run, once the next level
        has its initial guess), keeping its figures, iterate and history."""
        if self._record is None:
            self._record = self.record()
        if self.est is not None:
            self.est = _EstimatorTimes(self.est.setup_time, self.est.time)
        self.disc = None

    def record(self):
        """The level's figures (Solution.per_level)."""
        if self._record is not None:
            return self._record
        r, last = self.result, next(rec for rec in reversed(self.result.history)
                                    if rec["kind"] != "krylov")
        return {"level": self.level, "n_vertices": int(self.disc.n),
                "converged": r.converged, "reason": r.reason,
                "newton_iterations": r.newton_iterations,
                "linear_iterations": r.linear_iterations,
                "wall_time_s": self.wall_time_s, "final_residual": last["residual"],
                "energy_error": last.get("energy_error"), "eta": last.get("eta"),
                "alg_flux": None if self.est is None else
                ("multilevel" if self.est.multilevel is not None else "nu")}


@dataclass
class _Level:
    """What a level's Newton run needs that no iterate decides: the level's problem, its
    discretisation and linear rows; on T_j, j ≥ 1, of a nested run the prolongation P from
    T_{j-1}; where the steps take the exact mean (membranes.mean), M, and its MeanSolve
    while the next level may still build its multigrid on it."""
    problem: object
    disc: object
    rows: object
    P: object = None
    mean: object = None          # LevelMean, or None
    mean_solve: object = None


def _mean_bound(method, rows):
    """The bound M is solved to (membranes.mean.mean_bound) for the run's Newton steps."""
    return mean_bound(rows, linear_tolerance("adaptive" if method.tol is None else "exact",
                                             method.tol, None))


def _first_level(problem, method, initial_guess, keep_mean):
    """The _Level of a single-mesh run, or of T_0 of a nested one, with X^0 (None for the
    paper's) and the seconds X^0 took (`initial_guess` is the caller's: not the method's
    time). M is solved from the mean of X^0 where X^0 is 3N finite values (else Newton says
    what is wrong with it); its MeanSolve is kept with `keep_mean` (T_0 of a nested run: the
    finer levels' multigrid is built on it)."""
    disc = discretise(problem)
    made = _Level(problem, disc, linear_rows(disc))
    t = time.perf_counter()
    X0 = _initial_guess(initial_guess, disc)
    guess_time = time.perf_counter() - t
    if method.mean_options is not None:
        guess = paper_guess(made.rows, problem.g) if X0 is None else np.asarray(X0, float)
        if guess.shape == (3 * disc.n,) and np.all(np.isfinite(guess)):
            th = theta(problem)
            made.mean_solve = MeanSolve(disc, method.mean_options)
            made.mean = LevelMean(th, made.mean_solve.solve(mean_of(guess, disc.n, th),
                                                            _mean_bound(method, made.rows)))
            if not keep_mean:
                made.mean_solve.destroy()
                made.mean_solve = None
    return made, X0, guess_time


def _level_parts(problem, j, below, ship=None):
    """Level j ≥ 1 of a nested run (its _Level, without the mean) made after `below`, the
    _Level of T_{j-1}: a generator that yields between the parts (`_Ahead`): the problem on
    T_j, its discretisation (discretise_in_parts), linear rows and the prolongation P from
    T_{j-1}."""
    pj = level_problem(problem, j)
    disc = yield from discretise_in_parts(pj)
    if ship is not None:
        ship(j, disc)
    yield
    rows = linear_rows(disc)
    P = prolongation(below.disc.V, disc.V, problem.hierarchy.parent_cells[j - 1])
    return _Level(pj, disc, rows, P)


def _mean_multigrid(made, below, method):
    """Level j's MeanSolve: the multigrid on T_0 ⊂ … ⊂ T_j, built on the MeanSolve of `below`
    (the _Level of T_{j-1}, whose M is solved: it is done with then)."""
    made.mean_solve = MeanSolve(made.disc, method.mean_options, below.mean_solve, made.P)
    below.mean_solve = None


def _level_mean(made, below, method, last):
    """Where the steps take the exact mean: level j's M, by CG with its multigrid
    (`_mean_multigrid`, if not built yet) from P M_{j-1}. M_{j-1} is the mean of every
    Newton iterate of level j-1 from its first step on (membranes.mean), so P M_{j-1} is the
    mean of the prolonged solution. `last`: level j is T_J (its MeanSolve is freed)."""
    if below.mean is None:
        return
    if made.mean_solve is None:
        _mean_multigrid(made, below, method)
    M = made.mean_solve.solve(made.P @ below.mean.M, _mean_bound(method, made.rows))
    made.mean = LevelMean(below.mean.theta, M)
    if last:
        made.mean_solve.destroy()
        made.mean_solve = None


class _Ahead:
    """Levels 1 … J of a nested run, each made (`_level_parts`) before its Newton run where
    there is time: `step()` makes one part of the first level not made yet, `level(j)` hands
    out level j, its parts not made yet made then, and `run` solves its mean. One process makes
    each level when its Newton run begins; process 0 of several makes the finer levels' parts
    also while it waits for estimates (membranes.pipeline, Link.meanwhile): their
    discretisation, rows and prolongation are then ready, in part or whole, when their turn
    comes, and so is the next level's mean multigrid (it needs the running level's M). The
    mean is solved when the level begins, from the mean of the level below (the estimator
    processes set up the level's estimators meanwhile, which takes longer). Nothing of it
    depends on when it is made: the iterates are the same either way."""

    def __init__(self, problem, method):
        self.problem, self.method = problem, method
        self.running = self.last = self.parts = None
        self.made = {}
        self.ship, self.shipped = None, ()    # Link.ship and the levels it is for

    def start(self, first):
        """Begin with T_0's _Level (level 0 running)."""
        self.running = self.last = first

    def step(self):
        """Make one part of the first level not made yet; once all are made, the multigrid
        of the next level's mean (the running level's M is solved: `_mean_multigrid`).
        False when there is nothing left to make."""
        if self.last is None:
            return False
        if _level_of(self.last) < self.problem.levels:
            if self.parts is None:
                j = _level_of(self.last) + 1
                self.parts = _level_parts(self.problem, j, self.last,
                                          self.ship if j in self.shipped else None)
            try:
                next(self.parts)
            except StopIteration as done:
                self.last, self.parts = done.value, None
                self.made[_level_of(self.last)] = self.last
            return True
        following = self.made.get(_level_of(self.running) + 1)
        if following is None or following.mean_solve is not None or \
                self.running.mean_solve is None:
            return False
        _mean_multigrid(following, self.running, self.method)
        return True

    def level(self, j):
        """Level j (≥ 1), the one after the one running, its parts made to the end."""
        if self.running is None or j != _level_of(self.running) + 1:
            raise ValueError(f"level {j} does not follow the one running")
        while j not in self.made:
            self.step()
        return self.made.pop(j)

    def run(self, made):
        """Level `made` (from `level`) runs now: its mean solved from the one that ran."""
        _level_mean(made, self.running, self.method,
                    _level_of(made) == self.problem.levels)
        self.running = made


def _level_of(made):
    """The level of a _Level."""
    return len(made.problem.hierarchy.meshes) - 1


def _solve_on(problem, method, alg_flux, initial_guess, level, offset=0.0, its_offset=0,
              tag="", started=None, ahead=None, then=None):
    """Semismooth Newton on problem.mesh (the finest mesh of its hierarchy). The records get
    `level`; their wall times and cumulative linear iterations start at `offset` and
    `its_offset` (the earlier levels of a nested run). `started`: the clock's start
    (perf_counter) where it is earlier than this call (`solve`'s). `ahead`: the _Ahead of a
    nested run: level 0 starts it; a level j ≥ 1 takes its _Level from it and its initial
    guess from `initial_guess`, a _Prolonged (the prolongation is the method's: its time
    counts, where the user's initial guess on a single mesh or T_0 does not). `then`: the
    level whose estimators come next (nested), which the estimator processes of a run on
    several processes discretise meanwhile where they wait (membranes.pipeline)."""
    t0 = time.perf_counter() if started is None else started
    remote = method.link is not None and alg_flux is not None
    if remote:      # first: the estimator processes set this level up meanwhile
        from .pipeline import RemoteEstimates
        est = RemoteEstimates(method.link, level, alg_flux, method.newton == "adaptive",
                              method.gamma_lin)
        if then is not None:
            method.link.post("ahead", then)
    if ahead is None or level == 0:
        made, X0, guess_time = _first_level(problem, method, initial_guess,
                                            keep_mean=ahead is not None)
        if ahead is not None:
            ahead.start(made)
            if method.link is not None:     # the finer levels made while process 0 waits
                method.link.meanwhile = ahead.step
    else:
        made = ahead.level(level)
        X0, guess_time = initial_guess(made), 0.0      # the level below released: first
        ahead.run(made)
        problem = made.problem
        if method.link is not None:     # the next level's mean multigrid too
            method.link.meanwhile = ahead.step
    disc, rows, mean = made.disc, made.rows, made.mean
    if remote:      # X^0's residual and the data oscillation come from here
        est.discretised(disc, rows)
    setup_time = time.perf_counter() - t0 - guess_time
    error = EnergyError(disc) if problem.exact is not None else None
    if not remote:
        est = IterateEstimates(disc, rows, alg_flux) if alg_flux is not None else None
    if method.newton == "adaptive":
        setup_time += est.setup_time          # the adaptive method uses the estimators
    say = method.say

    def monitor(rec, X, R):
        if est is not None:     # None where not estimated (yet: X^0 of an adaptive run never)
            for k in RECORD_KEYS:
                rec.setdefault(k, None)
        rec["wall_time_s"] += setup_time + offset
        rec["cumulative_linear_its"] += its_offset
        rec["level"] = level
        rec["energy_error"] = error(X) if error is not None else None
        if say is not None and rec["kind"] != "krylov":
            if remote:      # the line once the estimates are in
                est.when_complete(rec, progress_line)
            else:
                progress_line(rec)

    def progress_line(rec):
        line = (f"{tag}newton {rec['newton_it']:3d}  residual {rec['residual']:.3e}  "
                f"linear its {rec['linear_it']:5d}  total {rec['cumulative_linear_its']:6d}  "
                f"time {rec['wall_time_s']:7.2f} s")
        if rec["energy_error"] is not None:
            line += f"  energy error {rec['energy_error']:.4e}"
        if rec.get("eta") is not None:
            line += f"  eta {rec['eta']:.4e}"
        say(line)

    result = semismooth_newton(rows, problem.g, cfun=method.cfun, system=method.system,
                               variant=method.newton, krylov=method.krylov, tol=method.tol,
                               max_it=method.max_newton, X0=X0, monitor=monitor, estimate=est,
                               gamma_lin=method.gamma_lin, gamma_alg=method.gamma_alg,
                               mean=mean)
    if est is not None:
        est.finish()
    return _LevelRun(level, disc, result, est, result.history[-1]["wall_time_s"] - offset)


class _Prolonged:
    """The initial guess of level j ≥ 1 of a nested run, called with the level's _Level: the
    solution of level j-1 (`below`, a _LevelRun, released then) prolonged by its P."""

    def __init__(self, below):
        self.below = below

    def __call__(self, made):
        X0 = prolong(made.P, self.below.result.X)
        self.below.release()       # its discretisation and estimators are not needed again
        return X0


def _solve_nested(problem, method, alg_flux, estimators, initial_guess, started):
    """Nested iteration (membranes.nested): solve on T_0, ..., T_J in turn, each level from the
    prolonged solution of the one below (level 0 from `initial_guess`), each with the variant's
    own stopping test; the levels' set-up is made by an _Ahead. Estimators run on the levels
    below J only where the method uses them (adaptive); there they take the ν flux, and the
    multilevel flux (when asked for) is set up for T_J alone: its set-up on every level cost
    more than the ν flux's extra GMRES steps (disk h0 = 0.2, J = 5: 64 s against 51 s, the
    same Newton and GMRES counts and the same final iterate). Level 0's time runs from
    `started` (solve's clock). Returns the _LevelRuns."""
    runs, offset, its = [], 0.0, 0
    J = problem.levels
    fluxes = [None if j < J and method.newton != "adaptive" else
              "nu" if j < J and alg_flux == "multilevel" else alg_flux for j in range(J + 1)]
    served = [j for j in range(J + 1) if fluxes[j] is not None]  # levels with estimators
    ahead = _Ahead(problem, method)
    if method.link is not None:     # the estimator processes take D, F1, F2 from process 0
        ahead.ship, ahead.shipped = method.link.ship, set(served)
    if method.link is not None and served and served[0] > 0:
        method.link.post("ahead", served[0])
    try:
        for j in range(J + 1):
            then = next((i for i in served if i > j), None)
            if j == 0:
                run = _solve_on(level_problem(problem, 0), method, fluxes[0], initial_guess,
                                level=0, tag="level 0  ", started=started, ahead=ahead,
                                then=then)
            else:
                run = _solve_on(problem, method, fluxes[j], _Prolonged(runs[-1]), level=j,
                                offset=offset, its_offset=its, tag=f"level {j}  ",
                                ahead=ahead, then=then)
            runs.append(run)
            offset += run.wall_time_s
            its += run.result.linear_iterations
    finally:
        if method.link is not None:
            method.link.meanwhile = None
    return runs


def _solution(problem, runs, options):
    """The Solution of a run on the levels `runs` (one for a single-mesh run): the finest
    level's iterate, functions, estimates and energy error; iterations summed over the levels,
    the wall time of them all, the history of every level (records carry `level`)."""
    fine = runs[-1]
    result = fine.result
    reason = result.reason
    failed = [r.level for r in runs[:-1] if not r.result.converged]
    if failed:
        reason += "; not converged on level(s) " + ", ".join(map(str, failed)) + \
            " (per_level)"
    history = [rec for r in runs for rec in r.result.history]
    estimated = [r.est for r in runs if r.est is not None]
    sol = Solution(problem, fine.disc, result.X, result.converged, reason,
                   sum(r.result.newton_iterations for r in runs),
                   sum(r.result.linear_iterations for r in runs),
                   history[-1]["wall_time_s"], history, options,
                   functions=fine.disc.functions(result.X),
                   eta_K=None if fine.est is None else fine.est.eta_K,
                   estimator_times=(None, None) if not estimated else
                   (sum(e.setup_time for e in estimated), sum(e.time for e in estimated)),
                   per_level=[r.record() for r in runs])
    sol.energy_error = sol.final_record["energy_error"]
    return sol
