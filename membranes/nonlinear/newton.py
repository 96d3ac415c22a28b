"""Semismooth Newton for the discrete contact problem: exact, inexact and adaptive inexact
(§3, §8).

    k = 0, X⁰ = (g, 0, 0)
    repeat                                       (Newton)
        k += 1; linearise C at X^{k-1}: A^{k-1}, B^{k-1}; X^{k,0} = X^{k-1}
        repeat one more Krylov step i            (linear solver)
        until the variant's linear test holds at X^{k,i}
    until the variant's Newton test holds at X^k

The step is solved on the full 3N system or on the eliminated 2N one
(`membranes.nonlinear.system`) by a `membranes.linalg.krylov` preset ('amg', 'paper',
'direct'). Variants (§8), with residuals weighted as in system's module notes (§11):

* exact: ‖R_alg‖/‖B‖ ≤ 2e-12 at every step; Newton stops at ‖R_lin‖/‖(F, 0)‖ ≤ tol;
* inexact: the Krylov solve stops at ‖R_alg‖/‖B‖ ≤ ‖R_lin(X^{k-1})‖/‖(F, 0)‖ (tested every ν
  iterations: see krylov), Newton stops as for exact; with `forcing` η instead at
  ‖R_alg‖ ≤ max(η ‖R_alg(X^{k,0})‖, 2e-12 ‖B‖), tested at every iteration (the nested run's
  coarse levels, membranes.app.driver); η is divided by 10 (`FORCING_SHRINK`) after every
  forced step whose ‖R_lin‖/‖(F, 0)‖ is no smaller than its predecessor's: with one or two
  GMRES + ILU(0) iterations per step, Newton-min drifted away on stiff cases (BENCHMARKS.md,
  robustness: "coarse levels' inexact Newton"), while deeper solves converge;
* adaptive (Algorithm 1): every ν Krylov steps the iterate X^{k,i} and its residual R^{k,i}
  go to the estimators (`estimate(X, R, 'krylov')`), and the solve stops at the first with
  η_alg ≤ γ_alg max(η_disc, η_lin) (or at the exact floor 2e-12); that iterate is X^k, whose
  estimates are then known. Newton stops at the first X^k, k ≥ 1, with η_lin ≤ γ_lin η_disc.
  X⁰ is not estimated (Algorithm 1 makes at least one step). With `forcing` η, a step that
  the estimates expect not to be the last (the first step, or the last answer to kind
  'newton' carries `more_steps` = True) stops its solve instead at ‖R_alg‖ ≤ η ‖R_alg(X^{k,0})‖
  (or at the exact floor, if that is larger), tested at every iteration, and hands its
  iterate over with kind 'forced' (η is not shrunk here: on T_J the forced steps are the
  first ones, whose residual may rise while the contact set settles). An answer None says
  its Newton test may hold: the solve then goes on to the exact floor from there (the two
  solves share the step's Krylov limit), and the iterate is estimated as 'newton'.
  Otherwise the answer is the iterate's estimates, and if they are full and Newton's test
  holds, the iterate stops Newton only if the linear criterion holds on them too
  (docs/choices.md).

**Estimates that need a later iterate.** The ν algebraic flux of X^{k,i} is built from
X^{k,i+ν} (§6): an `estimate` may answer the call for X^{k,i+ν} with the estimates of the
iterate it was handed before in the same step (X^{k,i}, or X^{k,0} = X^{k-1} at i = ν), marked
by the key `of_previous` = True. If the linear criterion holds on them and i ≥ 1, X^{k,i} is
accepted: the solve ran ν more iterations (they count) and X^k is the iterate the criterion
was verified on, with its own guaranteed bound (X^{k,0} is no candidate: accepting X^{k-1}
would repeat step k unchanged). Each Newton step first calls the callback with kind 'step'
(X^{k,0} and its residual in the step's system; no estimate wanted). X^{k,0} is the iterate
of the solver's initial guess: X^{k-1} itself on the full system; on the eliminated one,
X^{k-1} with its eliminated λ (or u2) taken from the new linearisation, the iterate whose
residual the solver starts from (the ν flux needs an iterate and its own residual). An
answer to kind 'newton' marked `partial` holds η_lin only (the estimates showed that the
Newton test fails without the flux equilibration, see membranes.app.schedule.LevelEstimates):
Newton goes on.

`estimate(X, R, kind)` is any callable returning a dict with at least eta_disc, eta_lin,
eta_alg (e.g. `membranes.estimation.estimators.Estimators.evaluate`, wrapped): X, R are PETSc
Vecs in the iterate layout, R = B - A X unweighted (§4; None for X⁰), kind 'initial',
'step' (its answer is not used), 'krylov', 'forced' (None allowed), 'newton' or 'stalled' (a
Newton iterate whose step made no Krylov iteration: full estimates wanted). The exact and
inexact variants estimate X⁰ and every Newton iterate when given one, for the record. The
Vecs are the loop's own: a callback that keeps one copies it.

No line search: a Newton step is the plain semismooth step of §3 (for Newton-min with exact
solves, the primal–dual active set method); the only safeguards are the inexact variant's
shrinking forcing term above and the divergence stop below. A step whose Krylov solve
makes no iteration (its initial guess X^{k,0} meets the bound, which is never below the exact
floor; X^{k,0} is X^{k-1}, on the eliminated system with its eliminated unknowns made
consistent) leaves the iterate where it was, and the next step would repeat it: if the
Newton test fails there, the run stops, not converged, and says so. The adaptive variant
asks for such an iterate's estimates with kind 'stalled' (in full, whatever a gate would
guess: its test decides whether the run stops). A run whose iterates run away stops too, not
converged, at the first Newton iterate whose ‖R_lin‖/‖(F, 0)‖ exceeds `DIVERGENCE` (1e8)
times the larger of X⁰'s and 1, the zero iterate's (SNES's divergence tolerance, with room
for converging runs that rise while the contact set settles: docs/choices.md, "When Newton
has diverged"). A Krylov solve that fails (PETSc error, iteration limit, breakdown) ends the
run with converged = False and says why; nothing is hidden.
"""

import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from mpi4py import MPI

from ..linalg.krylov import EXACT_TOL, LinearSolver, as_krylov, linear_tolerance
from ..model.checks import positive_integer
from . import cfunctions
from .system import NewtonSystem, initial_guess

VARIANTS = ("exact", "inexact", "adaptive")
FORCING_SHRINK = 0.1    # the forcing term's factor after a forced step that did not help
# Newton stops as diverged at an iterate whose ‖R_lin‖/‖(F, 0)‖ exceeds DIVERGENCE times the
# larger of X⁰'s and 1, the zero iterate's (module notes)
DIVERGENCE = 1e8
SYSTEMS = ("full", "eliminated")


@dataclass
class NewtonResult:
    X: object                    # PETSc Vec, the final iterate (iterate layout)
    history: list                # one dict per recorded iterate
    newton_steps: int
    krylov_steps: int            # Krylov iterations over all steps (1 per direct solve)
    reason: str
    converged: bool
    times: dict = field(default_factory=dict)   # wall seconds: 'assembly', 'solve', 'estimate'
    stalled: bool = False        # stopped where a step repeats the iterate (module notes)
    # (a Newton record holds its step's 'times' too: 'assembly' = linearisation and matrices,
    # 'solve' = the linear solve with its preconditioner set-up, estimates excluded)


def _positive(name, value):
    try:
        ok = np.isfinite(value) and value > 0 and not isinstance(value, bool)
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def _check(cfun, variant, system, solver_spec, estimate, gamma_lin, gamma_alg, tol, max_newton):
    cfunctions.get(cfun)
    if variant not in VARIANTS:
        raise ValueError(f"unknown Newton variant {variant!r} (choose from: "
                         f"{', '.join(VARIANTS)})")
    if system not in SYSTEMS:
        raise ValueError(f"unknown Newton system {system!r} (choose from: {', '.join(SYSTEMS)})")
    if variant != "exact" and not solver_spec.iterative:
        raise ValueError(f"the {variant} Newton variant needs an iterative Krylov preset "
                         f"('amg' or 'paper'), not {solver_spec.description}")
    if solver_spec.mean_gap and system != "eliminated":
        raise ValueError("the amg preset's mean/gap preconditioner works on the eliminated "
                         "system (system='eliminated')")
    if variant == "adaptive" and estimate is None:
        raise ValueError("the adaptive Newton variant needs the estimators (estimate=...)")
    for name, value in (("gamma_lin", gamma_lin), ("gamma_alg", gamma_alg), ("tol", tol)):
        _positive(name, value)
    positive_integer("max_newton", max_newton)


def linear_criterion(est, gamma_alg):
    """η_alg ≤ γ_alg max(η_disc, η_lin) (§8)."""
    return est["eta_alg"] <= gamma_alg * max(est["eta_disc"], est["eta_lin"])


def newton_criterion(est, gamma_lin):
    """η_lin ≤ γ_lin η_disc (§8)."""
    return est["eta_lin"] <= gamma_lin * est["eta_disc"]


def newton(disc, X0=None, cfun="min", variant="exact", system=None, krylov="amg",
           estimate=None, gamma_lin=0.3, gamma_alg=0.3, tol=1e-10, max_newton=100,
           progress=None, forcing=None):
    """Semismooth Newton on `disc` (a membranes.fem.discretisation.Discretisation) from X0 (a
    PETSc Vec in the iterate layout, not changed; its boundary vertices take the Dirichlet
    values of §2, `system.initial_guess`; default (g, 0, 0)).

    cfun 'min' | 'fb'; variant 'exact' | 'inexact' | 'adaptive'; system 'full' | 'eliminated'
    (default: the preset's); krylov: a preset name ('amg', 'paper', 'direct'), a dict of
    `membranes.linalg.krylov.Krylov` fields (preset, options, nu, max_it) or a Krylov;
    estimate: see the module notes; progress: True (print on rank 0) or a callable taking one
    line per Newton step (called on every process, with the same lines: the caller chooses
    which process writes them, `membranes.model.progress.reporter`); forcing (inexact: every
    step; adaptive: the steps not expected to be the last): the Krylov solve of a step stops
    instead at ‖R_alg‖ ≤ forcing ‖R_alg(X^{k,0})‖, tested at every iteration (the module
    notes). Returns a `NewtonResult`."""
    spec = as_krylov(krylov)
    system = spec.system if system is None else system
    _check(cfun, variant, system, spec, estimate, gamma_lin, gamma_alg, tol, max_newton)
    if forcing is not None:
        if variant == "exact":
            raise ValueError("forcing applies to the inexact and adaptive variants only")
        _positive("forcing", forcing)
        if forcing >= 1.0:
            raise ValueError(f"forcing must lie in (0, 1), got {forcing!r}")
    comm = disc.comm
    say = None
    if callable(progress):
        say = progress
    elif progress and comm.rank == 0:
        say = partial(print, flush=True)
    adaptive = variant == "adaptive"
    times = {"assembly": 0.0, "solve": 0.0, "estimate": 0.0}

    if X0 is not None and X0.getLocalSize() != 3 * disc.n:
        raise ValueError(f"X0 must have the iterate layout (local size {3 * disc.n}), got "
                         f"{X0.getLocalSize()}")
    t0 = time.perf_counter()
    ns = NewtonSystem(disc)
    solver = LinearSolver(spec, comm)
    split = (ns.S_D, ns.D * (1.0 / ns.mu[0] + 1.0 / ns.mu[1]), ns.theta)
    times["assembly"] += time.perf_counter() - t0

    X = initial_guess(disc, X0)     # X0 with the Dirichlet values of §2
    R = disc.vector3()              # the residual handed to the estimators
    X_try = disc.vector3()          # Krylov iterates, built for the callback
    history = []

    def estimated(Xv, Rv, kind):
        t = time.perf_counter()
        est = estimate(Xv, Rv, kind)
        times["estimate"] += time.perf_counter() - t
        return est

    def record(kind, k, i, total, Xv, alg, est=None):
        rec = {"kind": kind, "k": k, "i": i, "krylov_total": total,
               "residual": ns.relative_residual(Xv, cfun), "alg_residual": alg}
        if est is not None:
            rec["estimates"] = est
        history.append(rec)
        return rec

    est0 = estimated(X, None, "initial") if estimate is not None and not adaptive else None
    last = record("initial", 0, 0, 0, X, None, est0)
    divergent = DIVERGENCE * max(last["residual"], 1.0)
    total, k, reason, converged = 0, 0, None, False
    forced = False          # whether the last step's solve stopped at the forcing term

    def more_steps(rec):
        """Adaptive: whether the step after `rec` is expected not to be the last (the first
        step, or the estimates at `rec` say so: key `more_steps`)."""
        return rec["kind"] == "initial" or bool(rec["estimates"].get("more_steps"))

    def met(rec, forced):
        """The variant's Newton stopping test at `rec`: (met, description). An adaptive
        iterate whose solve was `forced` (stopped by the forcing term) must also meet the
        linear criterion, which its solve did not test."""
        if adaptive:
            if rec["kind"] == "initial":
                return False, ""
            e = rec["estimates"]
            if e.get("partial"):        # η_lin only: the test fails (module notes)
                return False, f"eta_lin {e['eta_lin']:.3e} (eta_disc not evaluated)"
            ok = newton_criterion(e, gamma_lin)
            description = (f"eta_lin {e['eta_lin']:.3e} {'<=' if ok else '>'} gamma_lin "
                           f"eta_disc = {gamma_lin * e['eta_disc']:.3e}")
            if ok and forced and not linear_criterion(e, gamma_alg):
                return False, description + (f", but eta_alg {e['eta_alg']:.3e} > gamma_alg "
                                             f"max(eta_disc, eta_lin) after a forced solve")
            return ok, description
        ok = rec["residual"] <= tol
        return ok, f"relative residual {rec['residual']:.3e} {'<=' if ok else '>'} {tol:.3g}"

    stalled = False         # whether the last step's Krylov solve made no iteration
    forcing_now = forcing   # the forcing term, shrunk where a forced step did not help
    try:
        while True:
            ok, description = met(last, forced)
            if ok:
                reason, converged = f"converged: {description}", True
                break
            if stalled:
                # X^{k-1} solved step k's system to the floor: X^k is X^{k-1}, and every
                # further step would repeat it (module notes)
                reason = (f"Newton stalled at step {k}: its Krylov solve made no iteration "
                          f"(the iterate solves the step's system to the floor), so further "
                          f"steps repeat it ({description})")
                break
            if last["residual"] > divergent:
                reason = (f"diverged at Newton step {k}: relative residual "
                          f"{last['residual']:.3e} > {DIVERGENCE:.0e} max(that of X^0, 1) "
                          f"= {divergent:.3e}")
                break
            if k >= max_newton:
                reason = f"no convergence in {max_newton} Newton steps ({description})"
                break
            k += 1
            t = time.perf_counter()
            lin = ns.linearise(X, cfun)
            # the mean/gap PC reads no entry of the eliminated matrix: an operator suffices
            step = ns.step(lin, system, assembled=not spec.mean_gap)
            y = step.guess(X)
            t_assembly = time.perf_counter() - t
            times["assembly"] += t_assembly
            lin_tol = linear_tolerance(variant, last["residual"])
            accepted = []

            earlier = []        # the iterate handed to the estimators last: (X, R, alg, i)
            if adaptive:        # X^{k,0} and its residual in this step's system
                # (X^{k,0} is the iterate of the solver's initial guess: X^{k-1} on the full
                # system; on the eliminated one its eliminated λ or u2 follows this step's
                # linearisation, and R0 is the residual of that iterate, not of X^{k-1}: the
                # ν flux of §6 needs the pair of one iterate)
                R0 = R.copy()
                norm0 = step.residual(y, R0)
                X0k = step.expand(y, X_try).copy()
                estimate(X0k, R0, "step")
                earlier.append((X0k, R0, norm0 / lin.norm_B, 0))

            def on_iterate(i, yi, ri, k=k, step=step, accepted=accepted, earlier=earlier):
                """Adaptive: estimate X^{k,i} (or the iterate before it, `of_previous`);
                stop the solve where the linear criterion holds (§8)."""
                step.expand(yi, X_try)
                norm = step.residual(yi, R, rw=ri)
                e = estimated(X_try, R, "krylov")
                if e.get("of_previous"):
                    Xp, Rp, alg_p, i_p = earlier[-1]
                    rec = record("krylov", k, i_p, total + i, Xp, alg_p, e)
                    # X^{k,0} = X^{k-1} is no candidate: Algorithm 1 takes i ≥ 1 (accepting
                    # it would repeat step k unchanged)
                    ok = i_p >= 1 and linear_criterion(e, gamma_alg)
                    if ok:
                        accepted.append((rec, Xp.copy(), Rp.copy()))
                else:
                    rec = record("krylov", k, i, total + i, X_try, norm / lin.norm_B, e)
                    ok = linear_criterion(e, gamma_alg)
                    if ok:
                        accepted.append((rec, None, None))
                if earlier:
                    earlier[-1][0].destroy()
                    earlier[-1][1].destroy()
                    earlier.clear()
                earlier.append((X_try.copy(), R.copy(), norm / lin.norm_B, i))
                return ok

            t = time.perf_counter()
            t_est = times["estimate"]
            bound, every = lin_tol * lin.norm_B, spec.nu if variant == "inexact" else 1
            forced = forcing is not None and (not adaptive or more_steps(last))
            if forced:                      # relative to X^{k,0}'s residual (R: scratch here)
                # never below the exact floor: a solve that reaches it is exact (an X^{k,0}
                # already at round-off, e.g. an exact prolongation, would never stop)
                bound = max(forcing_now * (norm0 if adaptive else step.residual(y, R)),
                            EXACT_TOL * lin.norm_B)
                every = 1
            split_ = split if step.system == "eliminated" else None
            # inexact: X^{k,0} = X^{k-1} meets its test ‖R_alg‖ ≤ ‖R_lin(X^{k-1})‖ at once (an
            # equality where B = (F, 0)): tested at i ≥ ν only, also where ν = 1
            rw = step.b.duplicate()         # b - A y at the end of the solve
            its, name, solved, norm = solver.solve(
                step, y, bound, every, on_iterate if adaptive else None, split_,
                guess=False if variant == "inexact" and not forced else None, residual=rw)
            if its == 0:        # X^{k,0} met the bound, so the floor: nothing was cut short
                forced = False
            answer = None               # the estimates of a forced adaptive step's iterate
            if forced and adaptive and solved and not accepted:
                step.expand(y, X_try)
                step.residual(y, R, rw=rw)
                answer = estimated(X_try, R, "forced")
                if answer is None:      # its Newton test may hold: finish the solve
                    forced = False
                    bound = lin_tol * lin.norm_B
                    # the step's Krylov limit (max_it) covers both solves
                    left = spec.max_it - its
                    if left > 0:
                        more, name, solved, norm = solver.solve(step, y, bound, 1, None,
                                                                split_, max_it=left,
                                                                residual=rw)
                        its += more
                    else:
                        name, solved = "DIVERGED_MAX_IT", norm <= bound
            t_solve = time.perf_counter() - t - (times["estimate"] - t_est)
            times["solve"] += t_solve
            total += its
            if not solved:
                reason = (f"Krylov solver failed at Newton step {k}: {name} after {its} "
                          f"iterations, ||R_alg||/||B|| = {norm / lin.norm_B:.2e} "
                          f"(asked {bound / lin.norm_B:.1e})")
                step.destroy()
                y.destroy()
                rw.destroy()
                break
            stalled = its == 0
            if answer is None:          # else X_try and R are those of y already
                step.expand(y, X_try)
                step.residual(y, R, rw=rw)
            if accepted and accepted[0][1] is not None:     # an earlier iterate accepted
                accepted[0][1].copy(X_try)
                accepted[0][2].copy(R)
                accepted[0][1].destroy()
                accepted[0][2].destroy()
            for Xe, Re, *_ in earlier:
                Xe.destroy()
                Re.destroy()
            step.destroy()
            y.destroy()
            rw.destroy()
            if not comm.allreduce(bool(np.all(np.isfinite(X_try.array_r))), op=MPI.LAND):
                reason = f"non-finite iterate at Newton step {k}"
                break
            X_try.copy(X)
            before = last["residual"]
            if accepted:
                last = accepted[0][0]
                last["kind"], last["krylov_total"] = "newton", total
            else:
                e = answer
                # an adaptive step that made no Krylov iteration repeats X^{k-1}: its test
                # is estimated in full (kind 'stalled'), not left to the gate's guess
                kind = "stalled" if adaptive and stalled else "newton"
                if e is None and estimate is not None:
                    if adaptive:        # a full estimate may follow: not under its peak
                        ns.release()
                        solver.release()
                    e = estimated(X, R, kind)
                last = record("newton", k, its, total, X, norm / lin.norm_B, e)
            last["times"] = {"assembly": t_assembly, "solve": t_solve}
            if forced and not adaptive and last["residual"] >= before:
                # the inexact step did not reduce the nonlinear residual: solve the next
                # steps deeper (module notes)
                forcing_now *= FORCING_SHRINK
            if say is not None:
                line = (f"Newton {k:3d}: residual {last['residual']:.3e}, {its} Krylov "
                        f"iterations ({total} in all), ||R_alg||/||B|| "
                        f"{last['alg_residual']:.1e}")
                e = last.get("estimates")
                if e is not None and e.get("partial"):
                    line += f", eta_lin {e['eta_lin']:.3e} (eta_disc not evaluated)"
                elif e is not None:
                    line += (f", eta_disc {e['eta_disc']:.3e}, eta_lin {e['eta_lin']:.3e}, "
                             f"eta_alg {e['eta_alg']:.3e}")
                say(line)
    finally:
        solver.destroy()
        ns.destroy()
        R.destroy()
        X_try.destroy()
    return NewtonResult(X, history, k, total, reason, converged, times, stalled)


__all__ = ["newton", "NewtonResult", "VARIANTS", "SYSTEMS", "EXACT_TOL",
           "linear_criterion", "newton_criterion"]
