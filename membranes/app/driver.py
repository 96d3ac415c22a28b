"""The API: `solve(problem, ...)` runs semismooth Newton on a problem and certifies the answer
(§3, §7, §8).

    >>> from membranes import scenes, solve
    >>> sol = solve(scenes.disk(h=0.2, levels=3))           # adaptive, amg preset, nested
    >>> sol.converged, sol.newton_iterations, sol.estimates["eta"], sol.energy_error
    >>> sol.u1, sol.u2, sol.lam          # dolfinx P1 Functions on the computational mesh

Everything runs on the problem's communicator: the same call under `mpirun -n P` distributes
the mesh, the assembly, the solves and the estimators, and every process returns the same
figures (and its own part of the iterate).

**What is computed** (lean runs): the estimators of §7 where the method needs them (the
adaptive variant, at the iterates its stopping tests read: on T_J, and on the coarse levels
of a nested run only with coarse='estimated', see `_coarse_levels`) and
at the final iterate (the certificate), unless `estimators=False`; the energy error only where
the scene knows its exact solution, at the final iterate, or at every recorded iterate with
`errors="iterates"` (for error-against-time curves; then outside the clock).

**Wall time** runs from the call of `solve` to the certified answer: meshes are the
problem's (built before the call), discretisation, Newton, Krylov and every estimate the run
makes are in it; energy errors are not (diagnostics). Every history record carries the clock
at the moment it was made (`wall_time_s`: after its estimate where the method estimates it;
the final iterate's after its certificate), so that error and η can be drawn against time.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Callable, Literal, Mapping, Optional, Union

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from ..fem.discretisation import Discretisation, discretise
from ..fem.meshes import LARGEST_COORDINATE
from ..linalg.krylov import Krylov
from ..model import checks
from ..model.petsc_options import check_petsc_options_used, parse_petsc_options
from ..model.problem import Problem, real_number
from ..model.progress import reporter
from ..nonlinear import cfunctions
from ..nonlinear.newton import VARIANTS
from ..nonlinear.newton import newton as run_newton
from ..nonlinear.system import final_residual
from ..nonlinear.system import initial_guess as newton_guess
from .garbage import release_garbage
from .logs import quiet_jit_logging
from .schedule import DEFAULT_GAMMA, GATE, LevelEstimates
from .setups import Setups
from .solution import ESTIMATOR_COLUMNS, Solution, record_of_X

DEFAULT_TOL = 1e-10
ALG_FLUXES = ("nu", "multilevel")
INITIAL_GUESSES = ("paper", "zero")
ERRORS = ("final", "iterates", "none")
COARSE = ("residual", "estimated")
DEFAULT_COARSE_TOL = 1e-6
# coarse='residual': a Krylov solve stops at ‖R_alg‖ ≤ COARSE_FORCING ‖R_alg(X^{k,0})‖
COARSE_FORCING = 0.1
# adaptive with the amg preset: a Newton step expected not to be the last stops its Krylov
# solve at ‖R_alg‖ ≤ ADAPTIVE_FORCING ‖R_alg(X^{k,0})‖ (`LevelEstimates._more_steps`; the
# paper preset keeps Algorithm 1 as the paper ran it); None: Algorithm 1's test everywhere
ADAPTIVE_FORCING = 0.01


def _choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r} (choose from: {', '.join(choices)})")
    return value


def _reject(applies_to, **options):
    """ValueError naming the first of `options` that was given (not None)."""
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise ValueError(f"{given[0]} applies to {applies_to} only")


def _gamma(name, value):
    value = DEFAULT_GAMMA if value is None else real_number(name, value)
    if not (np.isfinite(value) and 0.0 < value < 1.0):
        raise ValueError(f"{name} must lie in (0, 1), got {value}")
    return value


def _default_variant(newton, estimators, krylov):
    """The Newton variant of a run that names none (§8): the adaptive Algorithm 1, unless it
    cannot run: without the estimators (its stopping tests read them) or with a direct
    solver (no Krylov iterations to stop); exact Newton then. A variant asked for is kept,
    and refused later if it cannot run."""
    if newton is not None:
        return newton
    return "adaptive" if estimators and krylov.iterative else "exact"


def _stopping(newton, tol, gamma_lin, gamma_alg):
    """(tol, γ_lin, γ_alg) of the variant (§8); the ones it does not use must not be given."""
    if newton != "adaptive":
        _reject("newton 'adaptive'", gamma_lin=gamma_lin, gamma_alg=gamma_alg)
        tol = DEFAULT_TOL if tol is None else real_number("tol", tol)
        # (tol >= 1 is met by any start: a run of no step, called converged)
        if not (np.isfinite(tol) and 0.0 < tol < 1.0):
            raise ValueError(f"tol must lie in (0, 1), got {tol}")
        return tol, None, None
    _reject("newton 'exact' and 'inexact' (adaptive stops by gamma_lin)", tol=tol)
    return DEFAULT_TOL, _gamma("gamma_lin", gamma_lin), _gamma("gamma_alg", gamma_alg)


def _nested(levels, nested):
    if nested is None:
        return levels >= 1
    if not isinstance(nested, (bool, np.bool_)):
        raise ValueError(f"nested must be True, False or None, got {nested!r}")
    if nested and levels < 1:
        raise ValueError("nested iteration needs a mesh hierarchy: levels >= 1 (--levels J)")
    return bool(nested)


# the method keys of checks.estimate_memory for each solver preset
MEMORY_METHOD = {"direct": {"linear_solver": "direct"},
                 "paper": {"linear_solver": "gmres", "pc_type": None},
                 "amg": {"linear_solver": "gmres", "pc_type": "vertex_amg"}}


def _check_memory(problem, solver, estimators, max_vertices, alg_flux=None):
    """Refuse a computational mesh whose run needs more memory than the processes have, or
    more vertices than `max_vertices`, before anything is assembled (model.checks)."""
    comm = problem.mesh.comm
    max_vertices = checks.check_max_vertices(max_vertices)
    available = None if max_vertices is not None else checks.room_for_run(comm)
    checks.check_size(problem.mesh.topology.index_map(0).size_global, available, max_vertices,
                      what=f"the computational mesh of {problem.name!r}",
                      estimators=estimators, processes=comm.size, replicated=False,
                      alg_flux=alg_flux, **MEMORY_METHOD.get(solver, {}))


def _algebraic_flux(levels, alg_flux, estimators, newton):
    """The algebraic flux of §6 for iterates whose residual is not at round-off: the one
    asked for, else 'nu'; None without estimators."""
    if not estimators:
        if newton == "adaptive":
            raise ValueError("the adaptive Newton variant needs the estimators")
        _reject("runs with estimators", alg_flux=alg_flux)
        return None
    alg_flux = "nu" if alg_flux is None else _choice("algebraic flux", alg_flux, ALG_FLUXES)
    if alg_flux == "multilevel" and levels < 1:
        raise ValueError("the multilevel algebraic flux needs a mesh hierarchy: levels >= 1 "
                         "(--levels J)")
    return alg_flux


class _Recorder:
    """Newton's `estimate` callback, wrapped: it is called at every iterate Newton records
    (all but the adaptive variant's X⁰), so each record gets the run's clock when it is made
    (after its estimate, if the method estimates it) and, with errors='iterates', its energy
    error, computed off the clock. `estimate` None: the method does not estimate (returns
    None, so Newton records no estimates). An estimate marked `of_previous` (the ν flux, §6)
    is that of the iterate handed over before (X^{k,0} announced as 'step', or the last
    Krylov iterate), and so is the error of its record."""

    def __init__(self, estimate, error, clock):
        self.estimate, self.error, self.clock = estimate, error, clock
        self.stamps = []                         # (seconds on the clock, energy error)
        self.previous = None                     # the error of the iterate handed over last

    def __call__(self, X, R, kind):
        out = self.estimate(X, R, kind) if self.estimate is not None else None
        if kind == "forced" and out is None:   # not a record: Newton finishes the solve
            return out
        t = self.clock.now()
        err = self.clock.off(self.error, X) if self.error is not None else None
        earlier, self.previous = self.previous, err
        if kind == "step":                     # not a record: X^{k,0} announced
            return out
        self.stamps.append((t, earlier if out is not None and out.get("of_previous") else err))
        return out


class _Clock:
    """Seconds since `solve` was called, less the diagnostics run off the clock (`off`)."""

    def __init__(self, started):
        self.started, self.paused = started, 0.0

    def now(self):
        return time.perf_counter() - self.started - self.paused

    def off(self, f, *args):
        t = time.perf_counter()
        try:
            return f(*args)
        finally:
            self.paused += time.perf_counter() - t


def _initial_guess(initial_guess, disc):
    """X^0 (None: the paper's (g, 0, 0), §3)."""
    if initial_guess is None or (isinstance(initial_guess, str) and initial_guess == "paper"):
        return None
    if isinstance(initial_guess, str):
        _choice("initial guess", initial_guess, INITIAL_GUESSES)
        return disc.vector3()
    X = initial_guess
    if _guess_function(initial_guess):
        # the user's function may fail on some processes only (a file one cannot read): every
        # process learns of it, or the others wait in the next collective for ever
        failed = None
        try:
            X = initial_guess(disc)
        except BaseException as e:      # noqa: BLE001  (re-raised below, on every process)
            failed = e
        who = disc.comm.allgather(None if failed is None else
                                  f"{type(failed).__name__}: {failed}")
        if failed is not None:
            raise failed
        first = next((k for k, w in enumerate(who) if w is not None), None)
        if first is not None:
            raise RuntimeError(f"the initial guess function failed on process {first}: "
                               f"{who[first]}")
    # collective: a Vec whose layout is wrong on some processes only must be refused by all
    if not disc.comm.allreduce(hasattr(X, "getLocalSize") and X.getLocalSize() == 3 * disc.n,
                               op=MPI.LAND):
        raise ValueError("an initial guess must be a PETSc Vec in the iterate layout "
                         "(Discretisation.vector3) or a function of the discretisation "
                         "returning one")
    if not disc.comm.allreduce(bool(np.all(np.isfinite(X.array_r))), op=MPI.LAND):
        raise ValueError("the initial guess has non-finite values")
    # as a mesh's coordinates (`meshes.LARGEST_COORDINATE`): beyond it the residual's and the
    # estimators' squares overflow, and a nested run's coarse level went on from an infinite
    # residual to a refusal that blamed the data
    size = disc.comm.allreduce(float(np.abs(X.array_r).max(initial=0.0)), op=MPI.MAX)
    if size > LARGEST_COORDINATE:
        raise ValueError(f"the initial guess has values up to {size:.3g}, beyond "
                         f"{LARGEST_COORDINATE:.0e}, whose squares overflow double precision: "
                         f"rescale it")
    return X


def _guess_function(initial_guess):
    """Whether `initial_guess` is a function of the discretisation: callable, but not a UFL
    object (a dolfinx Function is callable as x ↦ its value; called with the discretisation it
    logged UFL warnings for ever). It is refused as no Vec instead."""
    import ufl
    return callable(initial_guess) and not isinstance(initial_guess, ufl.core.expr.Expr)


def prolong(P, disc, X_coarse, n_coarse):
    """The nested iteration's initial guess on the next level: u1, u2 and λ each prolonged
    by the P1 prolongation P (§8 nested iteration, §9; it keeps u1 = g, u2 = λ = 0 on ∂Ω)."""
    X = disc.vector3()
    xc, xf = P.createVecRight(), P.createVecLeft()
    a = X_coarse.array_r
    for k in range(3):
        xc.array[:] = a[k * n_coarse:(k + 1) * n_coarse]
        P.mult(xc, xf)
        X.array[k * disc.n:(k + 1) * disc.n] = xf.array_r
    xc.destroy()
    xf.destroy()
    return X


def check_method(levels, newton=None, cfun="min", solver="amg", system=None,
                 petsc_options=None, nu=None, max_linear_its=None, tol=None, max_newton=100,
                 estimators=True, alg_flux=None, gamma_lin=None, gamma_alg=None, nested=None,
                 coarse="residual", coarse_tol=None, comm=None):
    """`solve`'s method options (its keywords of the same names) checked against each other
    and against the number of refinements `levels`, with no mesh: what `solve` refuses of
    them, the command line refuses before it builds a mesh (docs/cli.md). ValueError as
    `solve`; returns (krylov, newton, max_newton, petsc_options, tol, gamma_lin, gamma_alg,
    alg_flux, nested, coarse, coarse_tol), completed with their defaults. `comm`: the run's
    communicator, where PETSc options are tried (collective on it; default one process)."""
    if newton is not None:
        _choice("Newton variant", newton, VARIANTS)
    cfunctions.get(cfun)
    if not isinstance(estimators, (bool, np.bool_)):     # ('no' would have meant yes)
        raise ValueError(f"estimators must be True or False, got {estimators!r}")
    max_newton = checks.positive_integer("max_newton", max_newton)
    petsc_options = parse_petsc_options(petsc_options)
    if max_linear_its is not None:
        max_linear_its = checks.positive_integer("max_linear_its", max_linear_its)
        if max_linear_its > np.iinfo(PETSc.IntType).max:     # (KSP's max_it is a PetscInt)
            raise ValueError(f"max_linear_its must be at most {np.iinfo(PETSc.IntType).max} "
                             f"(PETSc's largest integer), got {max_linear_its}")
    krylov = Krylov(solver, petsc_options, **({} if nu is None else {"nu": nu}),
                    **({} if max_linear_its is None else {"max_it": max_linear_its}))
    if not krylov.iterative:      # (one factorisation per step: no Krylov iterate to count)
        _reject("iterative Krylov solvers (a direct solve has no Krylov iterations)", nu=nu,
                max_linear_its=max_linear_its)
    if petsc_options:       # refused here if PETSc would not read one of them
        check_petsc_options_used(petsc_options, krylov.merged, krylov.inner(), comm)
    if system is not None:
        _choice("system", system, ("full", "eliminated"))
    if krylov.mean_gap and (system or krylov.system) != "eliminated":
        raise ValueError("the amg preset's mean/gap preconditioner works on the eliminated "
                         "system (system='eliminated')")
    newton = _default_variant(newton, estimators, krylov)
    if newton == "adaptive" and not krylov.iterative:
        raise ValueError(f"the adaptive variant stops a Krylov solver: choose solver 'amg' "
                         f"or 'paper', not {krylov.description}")
    if newton == "inexact" and not krylov.iterative:
        raise ValueError(f"the inexact Newton variant needs an iterative Krylov preset "
                         f"('amg' or 'paper'), not {krylov.description}")
    tol, gamma_lin, gamma_alg = _stopping(newton, tol, gamma_lin, gamma_alg)
    alg_flux = _algebraic_flux(levels, alg_flux, estimators, newton)
    nested = _nested(levels, nested)
    coarse, coarse_tol = _coarse_levels(coarse, coarse_tol, newton, nested)
    return (krylov, newton, max_newton, petsc_options, tol, gamma_lin, gamma_alg, alg_flux,
            nested, coarse, coarse_tol)


def _energy_error(disc):
    """The energy error against the problem's exact solution on disc's mesh (§9; imported
    here: only a scene with an exact solution measures it)."""
    from ..estimation.energy_error import EnergyError
    return EnergyError(disc)


def solve(problem: Problem,
          newton: Optional[Literal["adaptive", "exact", "inexact"]] = None,
          cfun: Literal["min", "fb"] = "min",
          solver: Literal["amg", "paper", "direct"] = "amg",
          system: Optional[Literal["full", "eliminated"]] = None,
          petsc_options: Union[None, str, Mapping[str, Any]] = None,
          nu: Optional[int] = None,
          max_linear_its: Optional[int] = None,
          tol: Optional[float] = None,
          max_newton: int = 100,
          estimators: bool = True,
          alg_flux: Optional[Literal["nu", "multilevel"]] = None,
          gamma_lin: Optional[float] = None,
          gamma_alg: Optional[float] = None,
          initial_guess: Union[None, Literal["paper", "zero"], PETSc.Vec,
                               Callable[[Discretisation], PETSc.Vec]] = None,
          nested: Optional[bool] = None,
          errors: Literal["final", "iterates", "none"] = "final",
          progress: Union[bool, Callable[[str], Any]] = False,
          max_vertices: Optional[int] = None,
          coarse: Literal["residual", "estimated"] = "residual",
          coarse_tol: Optional[float] = None,
          setups: Optional[Setups] = None) -> Solution:
    """Solve the discrete contact problem of `problem` by semismooth Newton and certify it.

    newton: 'exact' (linear residual ≤ 2e-12), 'inexact' (≤ the previous nonlinear residual)
    or 'adaptive' (Algorithm 1 of §8: Krylov stops at η_alg ≤ γ_alg max(η_disc, η_lin),
    Newton at η_lin ≤ γ_lin η_disc, γ = `gamma_lin`, `gamma_alg`, 0.3 by default; with the
    amg preset a step not expected to be the last stops Krylov at ADAPTIVE_FORCING, see
    membranes.app.schedule); default (None): 'adaptive', or 'exact' where adaptive cannot
    run — without the estimators it stops by, or with the direct solver, which has no Krylov
    iterations to stop (`_default_variant`);
    cfun: 'min' or 'fb'; solver: a Krylov preset of membranes.linalg.krylov, 'amg' (the
    eliminated system, FGMRES with the mean/gap BoomerAMG preconditioner), 'paper' (the full
    system, GMRES + ILU(0), block Jacobi across processes) or 'direct' (MUMPS); system:
    'full' or 'eliminated' instead of the preset's; petsc_options: PETSc options on top of the
    preset (a dict, or a string "-name value ..."); nu: estimate (adaptive) and record every
    ν Krylov steps (10); max_linear_its: Krylov iterations allowed per Newton step (10000);
    tol: exact and inexact stop at ‖R_lin‖/‖(F, 0)‖ ≤ tol (1e-10, in (0, 1)); max_newton:
    Newton steps allowed on each level (100; beyond them the run ends not converged);
    estimators: certify the final iterate (and let adaptive use them); alg_flux: 'nu' or
    'multilevel' (§6); initial_guess: None or 'paper' (the default, (g, 0, 0)), 'zero', or a
    PETSc Vec in the iterate layout (or a function of the discretisation returning one,
    called on every process: where it raises on some, those raise their exception and the
    others a RuntimeError naming it) on the first mesh solved, whose boundary vertices take
    the Dirichlet values (u1 = g, u2 = λ = 0);
    nested: solve T_0, …, T_J in turn, each from the prolonged solution of the last
    (default where the problem has levels ≥ 1); errors: the energy error at the 'final'
    iterate (default), at all recorded 'iterates', or 'none'; progress: True for one stderr
    line per Newton step and two around each estimator set-up (rank 0), or a callable taking
    the line (called on rank 0; an exception it raises stops the run on every process,
    `model.progress.reporter`); max_vertices: refuse a computational mesh of more vertices
    (default: refuse one whose run needs more memory than the processes have, model.checks);
    coarse: how the adaptive variant of a nested run leaves the coarse levels T_0 … T_{J-1}
    (`_coarse_levels`): 'residual' (default: inexact Newton to ‖R_lin‖/‖(F, 0)‖ ≤
    coarse_tol, 1e-6, no estimators) or 'estimated' (Algorithm 1 with the estimators on
    every level); setups: a `membranes.Setups` that keeps the flux
    equilibration of each mesh for the next solves on it (a parameter study on one
    hierarchy: the patch systems of §5 depend on the mesh only; membranes.app.setups; one
    solve at a time: another started with it before this one ends is refused).
    """
    if not isinstance(problem, Problem):
        raise ValueError(f"problem must be a membranes.Problem (from membranes.scenes), got "
                         f"{type(problem).__name__}")
    release_garbage(problem, collect=False)   # what earlier solves left (outside the clock)
    started = time.perf_counter()
    quiet_jit_logging()       # the forms' JIT builds are not the user's business
    _choice("errors", errors, ERRORS)
    if setups is not None and not isinstance(setups, Setups):
        raise ValueError(f"setups must be a membranes.Setups, got {type(setups).__name__}")
    (krylov, newton, max_newton, petsc_options, tol, gamma_lin, gamma_alg, alg_flux, nested,
     coarse, coarse_tol) = check_method(
        problem.levels, newton=newton, cfun=cfun, solver=solver, system=system,
        petsc_options=petsc_options, nu=nu, max_linear_its=max_linear_its, tol=tol,
        max_newton=max_newton, estimators=estimators, alg_flux=alg_flux, gamma_lin=gamma_lin,
        gamma_alg=gamma_alg, nested=nested, coarse=coarse, coarse_tol=coarse_tol,
        comm=problem.mesh.comm)
    _check_memory(problem, solver, estimators, max_vertices, alg_flux)
    if nested and initial_guess is not None and not isinstance(initial_guess, str) and \
            not _guess_function(initial_guess):
        raise ValueError("with nested iteration the initial guess is that of the coarse mesh "
                         "T_0: give 'paper', 'zero' or a function of the discretisation, or "
                         "nested=False")
    with (setups.in_use() if setups is not None else contextlib.nullcontext()):
        comm = problem.mesh.comm
        say = reporter(progress, comm)
        options = {"newton": newton, "cfun": cfun, "solver": solver,
                   "system": system or krylov.system, "petsc_options": dict(petsc_options or {}),
                   "nu": krylov.nu if krylov.iterative else None,
                   "max_linear_its": krylov.max_it if krylov.iterative else None,
                   "gamma_lin": gamma_lin, "gamma_alg": gamma_alg,
                   "alg_flux": alg_flux, "nested": nested,
                   "tol": None if newton == "adaptive" else tol,        # (adaptive: unused)
                   "coarse": coarse, "coarse_tol": coarse_tol,
                   "initial_guess": initial_guess if isinstance(initial_guess, str) or
                   initial_guess is None else "given"}

        J = problem.levels
        levels = list(range(J + 1)) if nested else [J]
        history, per_level = [], []
        its_offset, newton_total = 0, 0
        est_setup, est_time = 0.0, 0.0
        X, disc, estimate, prev = None, None, None, None
        clock = _Clock(started)                    # energy errors run off the clock
        for j in levels:
            t_level = clock.now()
            pj = problem.on_level(j)
            disc = discretise(pj)
            X0 = _initial_guess(initial_guess, disc) if prev is None else \
                prolong(problem.hierarchy.prolongation(j), disc, prev[0], prev[1])
            last = j == J
            # the adaptive variant's coarse levels without estimators (`_coarse_levels`)
            variant, level_tol, forcing = newton, tol, None
            if newton == "adaptive" and krylov.preset == "amg":
                forcing = ADAPTIVE_FORCING
            if not last and coarse == "residual":
                variant, level_tol, forcing = "inexact", coarse_tol, COARSE_FORCING
            estimate = None
            tag = f"level {j}: " if nested else ""
            if alg_flux is not None and prev is None:
                checks.check_force_scale(disc)     # (the certificate's refusal, before any solve)
            if alg_flux is not None and (variant == "adaptive" or last):
                # the set-up is a long silent phase on a fine mesh (the patch systems of §5)
                if say:
                    say(f"{tag}setting up the estimators on {disc.n_global:,} vertices")
                hits = setups.hits if setups is not None else 0
                estimate = LevelEstimates(disc, alg_flux if last else "nu",
                                          problem.hierarchy.up_to(j),
                                          gamma_alg or DEFAULT_GAMMA, gamma_lin or DEFAULT_GAMMA,
                                          gate=GATE, setups=setups)
                est_setup += estimate.setup_time
                if say:
                    kept = setups is not None and setups.hits > hits
                    say(f"{tag}estimators set up in {estimate.setup_time:.2f} s" +
                        (" (flux equilibration kept from an earlier solve)" if kept else ""))
            error = clock.off(_energy_error, disc) if problem.exact is not None and \
                errors != "none" and (last or errors == "iterates") else None
            recorder = _Recorder(estimate if variant == "adaptive" else None,
                                 error if errors == "iterates" else None, clock)
            t_start = clock.now()
            result = run_newton(disc, X0, cfun=cfun, variant=variant, system=system,
                                krylov=krylov, estimate=recorder,
                                gamma_lin=gamma_lin or DEFAULT_GAMMA,
                                gamma_alg=gamma_alg or DEFAULT_GAMMA, tol=level_tol,
                                max_newton=max_newton, forcing=forcing,
                                progress=(lambda line, tag=tag: say(tag + line)) if say else None)
            # the records Newton made through the recorder (all but the adaptive X⁰), in order
            stamped = result.history[1:] if variant == "adaptive" else result.history
            if len(stamped) != len(recorder.stamps):
                raise RuntimeError("Newton's records and its estimate calls do not match")
            for rec, (t, err) in zip(stamped, recorder.stamps):
                rec["wall_time_s"], rec["energy_error"] = t, err
            if variant == "adaptive":
                result.history[0]["wall_time_s"] = t_start
                result.history[0]["energy_error"] = None if error is None or \
                    errors != "iterates" else clock.off(error, newton_guess(disc, X0))
            final = record_of_X(result.history)
            if estimate is not None and (variant != "adaptive" or
                                         not (final.get("estimates") or {}).get("bound")):
                # exact, inexact: the certificate; adaptive: an X that Newton left before a full
                # estimate of it (X⁰ or a gated iterate, at the Newton limit or a failed solve)
                final["estimates"] = estimate(result.X, final_residual(disc, result.X, cfun))
                if final is result.history[-1]:   # (else the records' clock would go back)
                    final["wall_time_s"] = clock.now()        # the certificate is part of X^k
            stops = last or not (result.converged or result.stalled)   # (the `break` below)
            if errors == "final" and stops and problem.exact is not None:
                if error is None:        # a coarse level the run ends on: its X is the answer
                    error = clock.off(_energy_error, disc)
                final["energy_error"] = clock.off(error, result.X)
            level_time = clock.now() - t_level
            for rec in result.history:
                rec["level"] = j
                rec["cumulative_linear_its"] = rec.pop("krylov_total") + its_offset
                rec["newton_it"], rec["linear_it"] = rec.pop("k"), rec.pop("i")
                est = rec.pop("estimates", None) or {}
                rec.update({k: est.get(k) for k in ESTIMATOR_COLUMNS})
                rec["bound"] = est.get("bound")
                if est.get("eta_K") is not None:
                    rec["_eta_K"] = est["eta_K"]
                rec.setdefault("energy_error", None)
            history.extend(result.history)
            newton_total += result.newton_steps
            its_offset += result.krylov_steps
            if estimate is not None:
                est_time += estimate.time
            per_level.append({"level": j, "n_vertices": int(disc.n_global),
                              "converged": result.converged, "reason": result.reason,
                              "newton_iterations": result.newton_steps,
                              "linear_iterations": result.krylov_steps,
                              "wall_time_s": level_time, "final_residual": final["residual"],
                              "energy_error": final["energy_error"], "eta": final.get("eta"),
                              "times": result.times})
            if stops and not last:
                break               # (a coarse level that stalled holds its discrete solution to
            prev = (result.X, disc.n)   # the floor: the best start for the next one)
            if not last:
                disc.destroy()             # its PETSc objects (Solution keeps only T_J's)
        X = result.X
        wall = clock.now()
        final = record_of_X(history)
        eta_K = final.pop("_eta_K", None)
        for rec in history:
            rec.pop("_eta_K", None)
        estimates = {k: final.get(k) for k in ESTIMATOR_COLUMNS} if final.get("eta") is not None \
            else None
        if estimates is not None:
            estimates["bound"] = final.get("bound")
        sol = Solution(problem if disc.mesh is problem.mesh else pj, disc, X, result.converged,
                       result.reason, newton_total, its_offset, wall, history, options,
                       energy_error=final.get("energy_error"),
                       energy_error_kind=_error_kind(problem) if final.get("energy_error")
                       is not None else None,
                       functions=disc.functions(X), eta_K=eta_K, estimates=estimates,
                       estimator_times=(est_setup, est_time) if alg_flux is not None
                       else (None, None), per_level=per_level)
        del estimate, result, recorder, error
        release_garbage(problem)            # this solve's, outside its clock
        return sol


def _coarse_levels(coarse, coarse_tol, newton, nested):
    """How the coarse levels of an adaptive nested run stop (§8, nested iteration).

    Only the answer on T_J is certified; a coarse level only hands its iterate, prolonged, to
    the next. 'estimated' runs Algorithm 1 there too, which sets the estimators up on every
    mesh (the flux equilibration's patch systems, §5) for a stopping test whose only use is
    the move up. 'residual' (default) moves up on a cheaper signal: inexact Newton (§8) down
    to ‖R_lin‖/‖(F, 0)‖ ≤ coarse_tol, with no estimator, each Krylov solve stopped at
    COARSE_FORCING (0.1) times its initial residual, a constant forcing term (Eisenstat &
    Walker): the paper's inexact test is met by a step's initial guess, so that tested every ν
    iterations it solves each step ν iterations deep, far below what the next step keeps.
    Either way T_J runs Algorithm 1 from the prolonged iterate and its answer carries the
    guaranteed bound of §7: the bound holds for any iterate, so how the start was obtained
    does not matter to it. Other variants and single-level runs have no coarse levels to
    leave this way: they refuse 'estimated' and coarse_tol, and take the default
    'residual' as None."""
    _choice("coarse", coarse, COARSE)
    if newton != "adaptive" or not nested:
        _reject("the adaptive variant with nested iteration", coarse_tol=coarse_tol,
                coarse=None if coarse == "residual" else coarse)   # (the default passes)
        return None, None
    if coarse == "estimated":
        _reject("coarse 'residual'", coarse_tol=coarse_tol)
        return coarse, None
    coarse_tol = DEFAULT_COARSE_TOL if coarse_tol is None else \
        real_number("coarse_tol", coarse_tol)
    if not (np.isfinite(coarse_tol) and 0.0 < coarse_tol < 1.0):
        raise ValueError(f"coarse_tol must lie in (0, 1), got {coarse_tol}")
    return coarse, coarse_tol


def _error_kind(problem):
    """What `energy_error` measures (docs/outputs.md): the error against the scene's exact
    solution, restricted to the computational polygon."""
    if problem.hierarchy.projection is not None:
        return ("exact solution of the curved domain on the polygon of T_J (boundary "
                "vertices on the curve)")
    return "exact solution"
