"""Semismooth Newton on the distributed core (§3, §8, §10, §12): the discrete solution, the
same from every solver, C-function and number of processes, and independent checks.

Tolerances. Exact Newton stops at ‖R_lin‖/‖(F, 0)‖ ≤ 1e-10 after linear solves to 2e-12 (§8);
at that point Newton-min has found its active set and the last step solved the linear system
of that set, so the linear rows hold to the linear solver's accuracy (MUMPS: ~1e-15, Krylov:
2e-12) and the complementarity rows to round-off. Two solvers' final iterates differ by at most
cond × 2e-12 (cond ≲ 1e3 here: h = 0.1): 1e-8 of the data scale (u_data, λ_data of
`Discretisation.data_scales`, u and λ compared separately) leaves a margin of ~10; the
measured differences are ~1e-11.
"""

import json
import os
from functools import lru_cache

import numpy as np
import pytest
import ufl
from mpi4py import MPI
from petsc4py import PETSc

from membranes.fem import discretisation as fem_discretisation
from membranes.fem.discretisation import discretise
from membranes.model import scenes
from membranes.nonlinear.newton import newton
from membranes.nonlinear.system import NewtonSystem
from tests.conftest import mpirun
from tests.core.mpi_newton import make_scene
from tests.core.mpi_newton import run as mpi_run

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SAME = 1e-8            # two solvers, C-functions or process counts (module notes)
ROUND_OFF = 1e-12      # complementarity and linear rows after exact Newton with MUMPS


@lru_cache(maxsize=None)
def disc_of(scene, h, levels=0):
    return discretise(scenes.make(scene, h=h, levels=levels))


@lru_cache(maxsize=None)
def solved(scene, h, preset="direct", cfun="min", variant="exact"):
    res = newton(disc_of(scene, h), cfun=cfun, variant=variant, krylov=preset)
    assert res.converged, res.reason
    return res


def parts(disc, X):
    return [np.array(a) for a in disc.split(X)]


def assert_same(disc, X, Y, tol=SAME):
    """u1, u2 within tol u_data and λ within tol λ_data, at every owned vertex."""
    u_data, lam_data = disc.data_scales()
    (a1, a2, al), (b1, b2, bl) = parts(disc, X), parts(disc, Y)
    assert np.abs(a1 - b1).max() <= tol * u_data
    assert np.abs(a2 - b2).max() <= tol * u_data
    assert np.abs(al - bl).max() <= tol * lam_data


# ## (a) the discrete solution by exact Newton with MUMPS

@pytest.mark.parametrize("scene", ["disk", "square"])
def test_direct_exact_newton_solves_the_discrete_problem(scene):
    disc = disc_of(scene, 0.1)
    res = solved(scene, 0.1)
    assert res.history[-1]["residual"] <= 1e-10
    u_data, lam_data = disc.data_scales()
    sys_ = NewtonSystem(disc)
    u1, u2, lam = parts(disc, res.X)
    inner = disc.interior
    w = u1 - u2
    # complementarity at round-off: w ≥ 0, λ ≥ 0, w λ = 0 (in units of the data)
    assert w.min() >= -ROUND_OFF * u_data
    assert lam.min() >= -ROUND_OFF * lam_data
    assert np.abs(np.minimum(w / u_data, lam / lam_data))[inner].max() <= ROUND_OFF
    assert (lam > 1e-6 * lam_data).sum() > 0 and (w > 1e-6 * u_data).sum() > 0   # both sides
    # the linear rows, E X = F with the Dirichlet rows, independently of the Newton system:
    # μ1 S u1 - D λ = F1, μ2 S u2 + D λ = F2 at interior vertices, u1 = g, u2 = 0 on ∂Ω
    S, D = disc.S, disc.D.array_r
    Su = [S.createVecLeft() for _ in range(2)]
    for out, u in zip(Su, (u1, u2)):
        v = S.createVecRight()
        v.array[:] = u
        S.mult(v, out)
    r1 = disc.mu1 * Su[0].array_r - D * lam - disc.F1.array_r[:disc.n]
    r2 = disc.mu2 * Su[1].array_r + D * lam - disc.F2.array_r[:disc.n]
    scale = max(np.abs(disc.F1.array_r).max(), np.abs(disc.F2.array_r).max())
    assert np.abs(r1[inner]).max() <= ROUND_OFF * scale
    assert np.abs(r2[inner]).max() <= ROUND_OFF * scale
    b = disc.boundary_owned
    assert np.abs(u1[b] - disc.g).max() <= ROUND_OFF * u_data
    assert np.abs(u2[b]).max() <= ROUND_OFF * u_data
    assert np.abs(lam[b]).max() <= ROUND_OFF * lam_data
    sys_.destroy()


@pytest.mark.parametrize("scene", ["disk", "square"])
@pytest.mark.parametrize("preset", ["paper", "amg"])
def test_krylov_presets_reach_the_same_solution(scene, preset):
    disc = disc_of(scene, 0.1)
    res = solved(scene, 0.1, preset)
    assert_same(disc, res.X, solved(scene, 0.1).X)


def test_a_user_pc_on_the_eliminated_system_reads_the_assembled_matrix():
    """The amg preset's mean/gap split works on the operator W E T; a PETSc PC of the user's
    reads the matrix's entries, so the eliminated matrix is then assembled: LU of it solves
    every Newton step in one FGMRES iteration, to the same solution."""
    from membranes.linalg.krylov import Krylov
    disc = disc_of("disk", 0.1)
    res = newton(disc, cfun="min", krylov=Krylov("amg", {"pc_type": "lu"}))
    assert res.converged, res.reason
    steps = [h for h in res.history if h.get("kind") == "newton"]
    assert steps and all(h["i"] == 1 for h in steps), steps
    assert_same(disc, res.X, solved("disk", 0.1).X)


# ## (c) min and Fischer–Burmeister

@pytest.mark.parametrize("preset", ["direct", "amg"])
def test_min_and_fischer_burmeister_reach_the_same_solution(preset):
    disc = disc_of("square", 0.1)
    fb = solved("square", 0.1, preset, "fb")
    assert fb.history[-1]["residual"] <= 1e-10
    assert_same(disc, fb.X, solved("square", 0.1).X)


# ## Stiff moduli (§11): the weights W and the scale κ keep every row in units of the data

@pytest.mark.parametrize("mu1", [1e6, 1e-6])
def test_extreme_moduli(mu1):
    disc = discretise(scenes.make("radial", h=0.1, mu1=mu1, mu2=1.0))
    u_data, lam_data = disc.data_scales()
    ref = newton(disc, krylov="direct")
    assert ref.converged, ref.reason
    for cfun in ("min", "fb"):
        res = newton(disc, krylov="amg", cfun=cfun)
        assert res.converged, res.reason
        u1, u2, lam = parts(disc, res.X)
        inner = disc.interior
        assert np.abs(np.minimum((u1 - u2) / u_data, lam / lam_data))[inner].max() <= 1e-12
        assert_same(disc, res.X, ref.X)


# ## (d) the decoupled check of §10

def _mumps_solve(A, b):
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    pc.setFactorSolverType("mumps")
    ksp.setOperators(A)
    x = A.createVecRight()
    ksp.solve(b, x)
    ksp.destroy()
    return x


def decoupled_defect(disc, X):
    """(‖S z - (F1 + F2)‖ interior / ‖F1 + F2‖, ‖z - z_ref‖/‖z_ref‖): z = μ1 u1 + μ2 u2 of
    X against S z = F1 + F2, z = μ1 g on ∂Ω (§10), z_ref by MUMPS on that system alone."""
    u1, u2, _ = parts(disc, X)
    z = disc.mu1 * u1 + disc.mu2 * u2
    S = disc.S
    zv, Sz = S.createVecRight(), S.createVecLeft()
    zv.array[:] = z
    S.mult(zv, Sz)
    F = disc.F1.array_r[:disc.n] + disc.F2.array_r[:disc.n]
    inner = disc.interior
    comm = disc.comm
    defect = np.sqrt(comm.allreduce(float(np.sum((Sz.array_r - F)[inner] ** 2)), op=MPI.SUM))
    scale = np.sqrt(comm.allreduce(float(np.sum(F[inner] ** 2)), op=MPI.SUM))
    A = S.copy()
    r0 = A.getOwnershipRange()[0]
    A.zeroRows(np.asarray(disc.boundary_owned + r0, dtype=PETSc.IntType), 1.0)
    b = A.createVecLeft()
    b.array[:] = np.where(inner, F, disc.mu1 * disc.g)
    z_ref = _mumps_solve(A, b).array_r
    return defect / scale, np.linalg.norm(z - z_ref) / np.linalg.norm(z_ref)


@pytest.mark.parametrize("preset", ["direct", "amg"])
def test_decoupled_sum_solves_its_poisson_problem(preset):
    # the square has μ1 = 1 ≠ μ2 = 2 and f1 + f2 ≠ 0: the check is not trivial there
    disc = disc_of("square", 0.1)
    defect, error = decoupled_defect(disc, solved("square", 0.1, preset).X)
    tol = 1e-13 if preset == "direct" else 1e-11      # MUMPS round-off | 2e-12 of Krylov
    assert defect <= tol
    assert error <= 1e3 * tol                        # cond(S) ≲ 1e3 at h = 0.1


# ## (e) the forms reach the solver

def test_a_changed_membrane_form_changes_the_solution(monkeypatch):
    original = fem_discretisation.membrane_bilinear

    def doubled(mu, u, v, dx=ufl.dx):
        return original(2.0 * mu, u, v, dx)

    base = disc_of("square", 0.1)
    X = solved("square", 0.1).X
    monkeypatch.setattr(fem_discretisation, "membrane_bilinear", doubled)
    disc = discretise(base.problem)
    res = newton(disc, krylov="direct")
    assert res.converged, res.reason
    u_data = base.data_scales()[0]
    a, b = parts(disc, res.X), parts(base, X)
    assert np.abs(a[0] - b[0]).max() > 1e-2 * u_data
    # ... and the solution is that of the doubled form: 2 S z = F1 + F2 with S unchanged
    defect_doubled = decoupled_defect(disc, res.X)[0]
    assert defect_doubled <= 1e-14                   # disc.S is the doubled form's matrix
    assert decoupled_defect(base, res.X)[0] > 1e-2   # base.S is not


# ## Variants: inexact and adaptive (§8)

def test_inexact_newton_takes_nu_krylov_steps_and_reaches_the_solution():
    res = newton(disc_of("disk", 0.1), variant="inexact", krylov="paper")
    assert res.converged, res.reason
    steps = [r["i"] for r in res.history if r["kind"] == "newton"]
    assert all(i % 10 == 0 for i in steps)
    assert_same(disc_of("disk", 0.1), res.X, solved("disk", 0.1).X)


def test_inexact_newton_with_a_forcing_term():
    """forcing η: each Krylov solve stops at ‖R_alg‖ ≤ η ‖R_alg(X^{k,0})‖, tested at every
    iteration. The same solution as exact Newton (to SAME), in fewer Krylov steps than the
    paper's test every ν = 10 (which solves each step 10 iterations deep)."""
    disc = disc_of("disk", 0.1)
    plain = newton(disc, variant="inexact", krylov="amg")
    forced = newton(disc, variant="inexact", krylov="amg", forcing=0.1)
    assert forced.converged, forced.reason
    assert_same(disc, forced.X, solved("disk", 0.1).X)
    assert forced.krylov_steps < plain.krylov_steps
    assert any(r["i"] % 10 for r in forced.history if r["kind"] == "newton")


def forcing_bounds(monkeypatch):
    """Every Krylov solve's (bound, ‖b - A y‖ at its start, ‖B‖) in a list, recorded by a
    LinearSolver that `newton` uses in place of its own."""
    from membranes.nonlinear import newton as newton_module
    seen = []

    class Recording(newton_module.LinearSolver):
        def solve(self, step, y, bound, *args, **kwargs):
            r = step.b.duplicate()
            step.A.mult(y, r)
            r.aypx(-1.0, step.b)
            seen.append((bound, r.norm(), step.norm_B))
            r.destroy()
            return super().solve(step, y, bound, *args, **kwargs)

    monkeypatch.setattr(newton_module, "LinearSolver", Recording)
    return seen


def test_the_forcing_term_shrinks_after_a_step_that_did_not_help(monkeypatch):
    """Inexact Newton with forcing η (the coarse levels' solver): step k's Krylov solve stops
    at η_k ‖R_alg(X^{k,0})‖ with η_1 = η and η_{k+1} = η_k / 10 after a step whose
    ‖R_lin‖ / ‖(F, 0)‖ did not fall, else η_k (never below the exact floor 2e-12 ‖B‖;
    newton's notes). The schedule is rebuilt from the history's residuals; the bounds agree
    to round-off (one product of the same numbers), a wrong schedule is off by 10×."""
    from membranes.linalg.krylov import EXACT_TOL
    seen = forcing_bounds(monkeypatch)
    result = newton(disc_of("disk", 0.1), variant="inexact", krylov="amg", forcing=0.1)
    assert result.converged, result.reason
    residuals = [r["residual"] for r in result.history if r["kind"] in ("initial", "newton")]
    steps = len(residuals) - 1
    assert len(seen) == steps
    rises = [b >= a for a, b in zip(residuals[:-1], residuals[1:])]
    assert any(rises) and not all(rises)          # the schedule tells the two rules apart
    eta = 0.1
    for k, (bound, r0, norm_B) in enumerate(seen):
        assert np.isclose(bound, max(eta * r0, EXACT_TOL * norm_B), rtol=1e-12, atol=0), k
        if rises[k]:
            eta /= 10


def test_inexact_krylov_solves_stop_at_the_last_nonlinear_residual(monkeypatch):
    """Inexact Newton without forcing (§8): step k's Krylov solve stops at ‖R_alg‖/‖B‖ ≤
    ‖R_lin(X^{k-1})‖/‖(F, 0)‖ (never below the exact floor 2e-12): its bound is that of
    X^{k-1}, the previous record, not of X⁰. The residuals fall by orders of magnitude
    between steps, so a bound from another iterate is off by far more than the round-off of
    the product (rtol 1e-12)."""
    from membranes.linalg.krylov import EXACT_TOL
    seen = forcing_bounds(monkeypatch)
    result = newton(disc_of("disk", 0.1), variant="inexact", krylov="paper")
    assert result.converged, result.reason
    residuals = [r["residual"] for r in result.history if r["kind"] in ("initial", "newton")]
    assert len(seen) == len(residuals) - 1 >= 3
    assert residuals[-2] < 1e-3 * residuals[0]
    for k, (bound, _, norm_B) in enumerate(seen):
        assert np.isclose(bound, max(residuals[k], EXACT_TOL) * norm_B, rtol=1e-12, atol=0), k


def test_the_first_krylov_solve_of_each_level_is_forced_as_documented(monkeypatch):
    """A default nested solve (adaptive, amg, coarse='residual'): the first Krylov solve of
    each coarse level stops at 0.1 of its initial residual, the first of T_J at 0.01 (README,
    docs/choices.md), none at the exact floor."""
    from membranes import solve
    seen = forcing_bounds(monkeypatch)
    from membranes.app import driver
    levels = []                 # where each level's solves begin in `seen`
    original = driver.run_newton

    def counting(*args, **kwargs):
        levels.append(len(seen))
        return original(*args, **kwargs)

    monkeypatch.setattr(driver, "run_newton", counting)
    solve(scenes.disk(h=0.2, levels=2))
    assert len(levels) == 3
    firsts = [seen[i] for i in levels]
    for (bound, r0, norm_B), expect in zip(firsts, (0.1, 0.1, 0.01)):
        assert bound > 1e-6 * norm_B
        assert np.isclose(bound / r0, expect, rtol=1e-12, atol=0)


def test_adaptive_newton_stops_where_the_estimators_say():
    from membranes.estimation.equilibration import FluxEquilibration
    from membranes.estimation.estimators import Estimators
    disc = disc_of("disk", 0.1)
    est = Estimators(disc, FluxEquilibration(disc))
    calls = []

    def estimate(X, R, kind):
        calls.append(kind)
        e = est.evaluate(X, R)
        e.pop("eta_K")
        return e

    res = newton(disc, variant="adaptive", krylov="paper", estimate=estimate)
    assert res.converged, res.reason
    assert "initial" not in calls
    final = res.history[-1]["estimates"]
    assert final["eta_lin"] <= 0.3 * final["eta_disc"]
    for rec in res.history:
        if rec["kind"] == "krylov":          # not accepted: the linear criterion failed
            e = rec["estimates"]
            assert e["eta_alg"] > 0.3 * max(e["eta_disc"], e["eta_lin"])
            assert rec["i"] % 10 == 0
        if rec["kind"] == "newton":          # accepted at a ν-th iterate, or solved to 2e-12
            e = rec["estimates"]
            assert rec["i"] % 10 == 0 or rec["alg_residual"] <= 2e-12
            assert rec["i"] % 10 != 0 or e["eta_alg"] <= 0.3 * max(e["eta_disc"], e["eta_lin"])
    newton_recs = [r for r in res.history if r["kind"] == "newton"]
    # the returned iterate is the one the last record (and its estimates) describe
    sys_ = NewtonSystem(disc)
    assert sys_.relative_residual(res.X, "min") == pytest.approx(res.history[-1]["residual"],
                                                                 rel=1e-10)
    sys_.destroy()
    assert any(r["i"] % 10 == 0 and r["alg_residual"] > 2e-12 for r in newton_recs)
    for earlier in newton_recs[:-1]:
        e = earlier["estimates"]
        assert e["eta_lin"] > 0.3 * e["eta_disc"]
    # guaranteed: both the adaptive iterate and the discrete solution are within their η of
    # the (polygon's) weak solution (§7), so within the sum of each other in energy norm
    exact = solved("disk", 0.1).X
    e_exact = estimate(exact, None, "newton")
    a, b = parts(disc, res.X), parts(disc, exact)
    energy = 0.0
    for mu, d in ((disc.mu1, a[0] - b[0]), (disc.mu2, a[1] - b[1])):
        v, Sv = disc.S.createVecRight(), disc.S.createVecLeft()
        v.array[:] = d
        disc.S.mult(v, Sv)
        energy += mu * disc.comm.allreduce(float(d @ Sv.array_r), op=MPI.SUM)
    assert 0.0 < np.sqrt(energy) <= final["eta"] + e_exact["eta"]
    # the paper's point (§8): far fewer Krylov steps than the exact variant
    assert res.krylov_steps < 0.5 * solved("disk", 0.1, "paper").krylov_steps


def full_estimates(disc, more_steps, kinds=None):
    """An `estimate` callback that estimates every iterate in full (no gate) and answers
    `more_steps` as given; `kinds`, if a list, records the kinds it is asked for."""
    from membranes.estimation.equilibration import FluxEquilibration
    from membranes.estimation.estimators import Estimators
    est = Estimators(disc, FluxEquilibration(disc))

    def estimate(X, R, kind):
        if kinds is not None:
            kinds.append(kind)
        if kind == "step":
            return None
        e = est.evaluate(X, R)
        e.pop("eta_K")
        e["more_steps"] = more_steps
        return e
    return estimate

def test_adaptive_newton_with_a_forcing_term():
    """Adaptive with forcing η: a step the estimates expect not to be the last (key
    `more_steps`; always here) stops its Krylov solve at ‖R_alg‖ ≤ η ‖R_alg(X^{k,0})‖, so its
    iterate is not tested by the linear criterion; Newton may then stop there only if the
    linear criterion holds on its estimates as well. With η = 0.5 each solve is one Krylov
    step; with γ_alg = 0.01 there is an iterate whose Newton test holds but whose linear
    criterion fails, and the run goes on to the first iterate where both hold."""
    from membranes.nonlinear.newton import linear_criterion, newton_criterion
    disc = disc_of("disk", 0.1)
    estimate = full_estimates(disc, more_steps=True)
    res = newton(disc, variant="adaptive", krylov="amg", estimate=estimate, forcing=0.5,
                 gamma_alg=0.01)
    exact = newton(disc, variant="adaptive", krylov="amg", estimate=estimate, gamma_alg=0.01)
    assert res.converged and exact.converged, (res.reason, exact.reason)
    steps = [r for r in res.history if r["kind"] == "newton"]
    assert all(r["i"] == 1 for r in steps)
    assert res.krylov_steps < exact.krylov_steps
    tests = [(newton_criterion(r["estimates"], 0.3), linear_criterion(r["estimates"], 0.01))
             for r in steps]
    assert tests[-1] == (True, True) and (True, True) not in tests[:-1]
    assert (True, False) in tests            # Newton's test alone would have stopped there


def test_only_steps_expected_not_to_be_the_last_are_forced():
    """Adaptive with forcing: a step is forced (its solve stops at the forcing term, its
    iterate handed over as kind 'forced') only where the estimates expect it not to be the
    last: the first step, or after an answer with `more_steps` True. Every answer here says
    False, so only step 1 is forced (one 'forced' call); the later steps solve to the linear
    criterion as without forcing. The run has at least two steps, so forcing every step
    would show as more 'forced' calls."""
    disc = disc_of("disk", 0.1)
    kinds = []
    estimate = full_estimates(disc, more_steps=False, kinds=kinds)
    res = newton(disc, variant="adaptive", krylov="amg", estimate=estimate, forcing=0.5)
    assert res.converged, res.reason
    assert res.newton_steps >= 2 and kinds.count("step") == res.newton_steps
    assert kinds.count("forced") == 1
    first_step_ends = kinds.index("step", 1)
    assert "forced" in kinds[:first_step_ends]


def literal_estimates(kinds, answers):
    """An `estimate` callback that records the kinds it is asked for and answers each kind
    with the literal dict `answers[kind]` (None where absent): Newton's decisions on given
    numbers, no estimators."""
    def estimate(X, R, kind):
        kinds.append(kind)
        answer = answers.get(kind)
        return None if answer is None else dict(answer)
    return estimate


def test_a_forced_step_finished_to_the_floor_needs_only_the_newton_test():
    """A forced step whose 'forced' answer is None (its Newton test may hold) is solved on to
    the exact floor; it is then no longer a forced step, and its iterate stops Newton where
    η_lin ≤ γ_lin η_disc, whatever η_alg says (the linear criterion is asked only of a solve
    the forcing term cut short; newton's notes). Literal estimates: η_lin = 0 ≤ 0.3 · 1, and
    η_alg = 1 > 0.3 max(1, 0), so the run stops at step 1 only if the criterion is not asked
    (asked, it would go on to a second step)."""
    kinds = []
    answer = {"eta_disc": 1.0, "eta_lin": 0.0, "eta_alg": 1.0}
    estimate = literal_estimates(kinds, {"newton": answer, "krylov": answer})
    res = newton(disc_of("disk", 0.1), variant="adaptive", krylov="amg", estimate=estimate,
                 forcing=0.5)
    assert res.converged, res.reason
    assert kinds.count("forced") == 1 and res.newton_steps == 1
    assert res.history[-1]["alg_residual"] <= 2e-12


def test_an_iterate_accepted_in_a_forced_solve_is_the_one_returned():
    """Adaptive with forcing and ν = 1: the linear criterion holds on the first Krylov iterate
    of the forced first step (literal estimates: η_alg = 0), which stops the solve there, so
    that iterate is X^1: no 'forced' estimate follows (which, answered None, would finish the
    solve to the floor under the accepted iterate's record), and the returned X is the iterate
    the record describes: its ‖R_lin‖/‖(F, 0)‖ is the record's (the same computation on the
    same vector: 1e-10 covers the reductions' order), and far from the floor-solved step's;
    its ‖R_alg‖/‖B‖ is the solve's final ‖b - A y‖ over the step's ‖B‖ (a relative figure,
    as for every record; the same norm computed twice: 1e-10 again)."""
    from membranes.nonlinear import newton as newton_module
    kinds, ends = [], []

    class Recording(newton_module.LinearSolver):
        def solve(self, step, y, *args, **kwargs):
            out = super().solve(step, y, *args, **kwargs)
            ends.append(out[3] / step.norm_B)
            return out

    answer = {"eta_disc": 1.0, "eta_lin": 0.0, "eta_alg": 0.0}
    estimate = literal_estimates(kinds, {"newton": answer, "krylov": answer})
    disc = disc_of("disk", 0.1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(newton_module, "LinearSolver", Recording)
        res = newton(disc, variant="adaptive", krylov={"preset": "amg", "nu": 1},
                     estimate=estimate, forcing=1e-9)
    assert res.converged, res.reason
    assert "forced" not in kinds and res.newton_steps == 1
    final = res.history[-1]
    assert final["kind"] == "newton" and final["i"] == 1 and final["alg_residual"] > 1e-6
    assert len(ends) == 1 and final["alg_residual"] == pytest.approx(ends[0], rel=1e-10)
    sys_ = NewtonSystem(disc)
    assert sys_.relative_residual(res.X, "min") == pytest.approx(final["residual"], rel=1e-10)
    sys_.destroy()


def test_the_stopping_criteria_are_those_of_section_8():
    """§8's two tests on literal estimates, on both sides of each boundary and on it: Newton's
    η_lin ≤ γ_lin η_disc, Krylov's η_alg ≤ γ_alg max(η_disc, η_lin) (the tests above take
    them as given)."""
    from membranes.nonlinear.newton import linear_criterion, newton_criterion
    assert newton_criterion({"eta_lin": 0.29, "eta_disc": 1.0}, 0.3)
    assert not newton_criterion({"eta_lin": 0.31, "eta_disc": 1.0}, 0.3)
    assert not newton_criterion({"eta_lin": 0.5, "eta_disc": 1.0}, 0.3)
    assert linear_criterion({"eta_alg": 0.29, "eta_disc": 1.0, "eta_lin": 0.1}, 0.3)
    assert linear_criterion({"eta_alg": 0.59, "eta_disc": 0.1, "eta_lin": 2.0}, 0.3)
    assert not linear_criterion({"eta_alg": 0.61, "eta_disc": 0.1, "eta_lin": 2.0}, 0.3)
    assert not linear_criterion({"eta_alg": 0.31, "eta_disc": 1.0, "eta_lin": 0.1}, 0.3)
    # both tests are ≤ (§8): an iterate with every estimate 0 (the exact discrete solution of
    # data that P1 holds, solved exactly) meets them, and so stops Newton and its solve
    assert newton_criterion({"eta_lin": 0.0, "eta_disc": 0.0}, 0.3)
    assert linear_criterion({"eta_alg": 0.0, "eta_disc": 0.0, "eta_lin": 0.0}, 0.3)


def test_a_forced_step_finished_to_the_floor_keeps_the_krylov_limit():
    """A forced step whose gate answers None (its Newton test may hold) solves twice: to the
    forcing term, then on to the exact floor. max_it (--max-linear-its) is the limit of the
    Newton step's Krylov iterations (docs/cli.md), so the two solves share it: with one
    iteration less than the step needs in all, the step fails and says so, where the second
    solve, given the whole limit again, made it converge with more than the limit."""
    from membranes.estimation.equilibration import FluxEquilibration
    from membranes.estimation.estimators import Estimators
    disc = disc_of("disk", 0.1)
    est = Estimators(disc, FluxEquilibration(disc))

    def estimate(X, R, kind):
        if kind in ("step", "forced"):      # forced: finish the solve to the floor
            return None
        e = est.evaluate(X, R)
        e.pop("eta_K")
        e["more_steps"] = True
        return e

    def run(max_it):
        return newton(disc, variant="adaptive", krylov={"preset": "amg", "max_it": max_it},
                      estimate=estimate, forcing=0.5)

    free = run(10000)
    assert free.converged, free.reason
    first = next(r for r in free.history if r["kind"] == "newton")
    assert first["k"] == 1 and first["i"] >= 3   # one forced iteration, then the floor
    tight = run(first["i"] - 1)
    assert not tight.converged
    assert tight.reason.startswith("Krylov solver failed at Newton step 1: DIVERGED_MAX_IT "
                                   f"after {first['i'] - 1} iterations"), tight.reason
    assert tight.krylov_steps == first["i"] - 1


def test_adaptive_newton_with_estimates_of_the_previous_iterate():
    # the ν flux's estimates of X^{k,i} come with X^{k,i+ν} (`of_previous`): Newton must
    # return the accepted earlier iterate, never X^{k,0} = X^{k-1}
    from membranes.estimation.equilibration import FluxEquilibration
    from membranes.estimation.estimators import Estimators
    disc = disc_of("disk", 0.1)
    est = Estimators(disc, FluxEquilibration(disc))
    held = []

    def evaluate(X, R):
        e = est.evaluate(X, R)
        e.pop("eta_K")
        return e

    def estimate(X, R, kind):
        if kind == "step":
            held[:] = [X.copy(), R.copy()]
            return None
        if kind == "krylov":
            e = evaluate(*held)
            e["of_previous"] = True
            held[:] = [X.copy(), R.copy()]
            return e
        return evaluate(X, R)

    res = newton(disc, variant="adaptive", krylov="paper", estimate=estimate)
    assert res.converged, res.reason
    sys_ = NewtonSystem(disc)
    assert sys_.relative_residual(res.X, "min") == pytest.approx(res.history[-1]["residual"],
                                                                 rel=1e-10)
    sys_.destroy()
    steps = [r for r in res.history if r["kind"] == "newton"]
    before = 0
    for rec in steps:
        assert rec["i"] >= 1
        if rec["alg_residual"] > 2e-12:            # accepted: ν more iterations were run
            assert rec["i"] % 10 == 0 and rec["krylov_total"] - before == rec["i"] + 10
        before = rec["krylov_total"]
    assert any(r["alg_residual"] > 2e-12 for r in steps)



@pytest.mark.parametrize("guess", ["zero", "far"])
def test_every_estimated_iterate_has_the_dirichlet_values(guess):
    # an initial guess off the Dirichlet values (X⁰ = 0, or the stability matrix's far-off
    # guess) takes them before the first step: the Krylov iterates handed to the estimators
    # then have u1 = g, u2 = 0, λ = 0 at the boundary vertices and a residual that vanishes
    # there (§4), so the bound of §7 rests on an iterate of X_gh × X_0h × X_0h. Before,
    # the first Krylov iterates kept a boundary defect (2.6e-5 from X⁰ = 0 with 'paper').
    # The caller's X0 is not changed.
    from membranes.app.stability import far_off_guess
    disc = disc_of("square", 0.1)
    X0 = disc.vector3() if guess == "zero" else far_off_guess(disc)
    before = X0.array_r.copy()
    b, n = disc.boundary_owned, disc.n
    seen = []

    def estimate(X, R, kind):
        a = X.array_r
        seen.append(max(np.abs(a[b] - disc.g).max(initial=0.0),
                        np.abs(a[n + b]).max(initial=0.0), np.abs(a[2 * n + b]).max(initial=0.0),
                        0.0 if R is None else np.abs(R.array_r[b]).max(initial=0.0),
                        0.0 if R is None else np.abs(R.array_r[n + b]).max(initial=0.0)))
        return {"eta_disc": 1.0, "eta_lin": 0.0, "eta_alg": 0.0}

    res = newton(disc, X0=X0, variant="adaptive", krylov="paper", estimate=estimate)
    assert res.converged, res.reason
    assert seen and max(seen) == 0.0, max(seen)
    assert np.array_equal(X0.array_r, before)


# ## Options and failures

@pytest.mark.parametrize("kwargs, message", [
    ({"cfun": "max"}, "C-function"),
    ({"variant": "quick"}, "variant"),
    ({"system": "reduced"}, "system"),
    ({"krylov": "ilu"}, "preset"),
    ({"variant": "adaptive", "krylov": "paper"}, "estimators"),
    ({"variant": "inexact", "krylov": "direct"}, "iterative"),
    ({"krylov": "amg", "system": "full"}, "eliminated"),
    ({"gamma_lin": -1.0}, "gamma_lin"),
    ({"tol": 0.0}, "tol"),
    ({"tol": float("inf")}, "tol"),            # would call X⁰ converged
    ({"gamma_alg": True}, "gamma_alg"),        # a bool is no number here
    ({"variant": "adaptive", "krylov": "direct", "estimate": lambda X, R, kind: None},
     "iterative"),
    ({"max_newton": 0}, "max_newton"),
    ({"forcing": 0.1}, "inexact"),
    ({"variant": "inexact", "krylov": "amg", "forcing": 1.0}, "forcing"),
    ({"variant": "inexact", "krylov": "amg", "forcing": "x"}, "forcing"),
    ({"krylov": {"preset": "paper", "options": {"ksp_rtol": 1e-3}}}, "ksp_rtol"),
    ({"krylov": {"preset": "paper", "options": {"ksp_type": "no_such_method"}}}, "PETSc"),
])
def test_bad_options_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        newton(disc_of("disk", 0.1), **kwargs)


def test_a_wrong_initial_guess_is_refused():
    disc = disc_of("disk", 0.1)
    X0 = PETSc.Vec().createMPI((2 * disc.n, 2 * disc.n_global), comm=disc.comm)
    with pytest.raises(ValueError, match="layout"):
        newton(disc, X0=X0)


def test_a_failed_krylov_solve_is_reported():
    res = newton(disc_of("disk", 0.1), krylov={"preset": "paper", "max_it": 3})
    assert not res.converged
    assert "Krylov solver failed at Newton step 1" in res.reason
    assert "DIVERGED_MAX_IT after 3 iterations" in res.reason
    assert res.newton_steps == 1 and len(res.history) == 1       # X⁰ only


def test_a_non_finite_iterate_ends_the_run(monkeypatch):
    """A Newton step whose linear solve hands back non-finite values (here forced: the
    solver's answer overwritten with NaN) ends the run at that step, not converged, with the
    reason; the run does not go on from a NaN iterate (which no test would stop before
    max_newton)."""
    from membranes.nonlinear import newton as newton_module

    class Poisoned(newton_module.LinearSolver):
        def solve(self, step, y, *args, **kwargs):
            out = super().solve(step, y, *args, **kwargs)
            y.set(np.nan)
            return out

    monkeypatch.setattr(newton_module, "LinearSolver", Poisoned)
    res = newton(disc_of("disk", 0.1), krylov="direct", max_newton=3)
    assert not res.converged
    assert res.reason == "non-finite iterate at Newton step 1" and res.newton_steps == 1


def test_a_first_step_that_runs_away_stops_the_run(monkeypatch):
    """The divergence test holds from the first Newton iterate on: a step whose solve hands
    back its answer times 1e12 (then R_lin ≈ -1e12 E X^1 ≈ -1e12 (F, 0): ‖R_lin‖/‖(F, 0)‖ of
    order 1e12, far above DIVERGENCE · max(X⁰'s, 1), with X⁰'s of order 1) stops the run at
    step 1, not converged, as diverged; it does not take a second step from there."""
    from membranes.nonlinear import newton as newton_module

    class Scaled(newton_module.LinearSolver):
        def solve(self, step, y, *args, **kwargs):
            out = super().solve(step, y, *args, **kwargs)
            y.scale(1e12)
            return out

    monkeypatch.setattr(newton_module, "LinearSolver", Scaled)
    res = newton(disc_of("disk", 0.1), krylov="direct", max_newton=3)
    assert not res.converged and res.newton_steps == 1
    assert res.reason.startswith("diverged at Newton step 1: "), res.reason


def test_a_diverging_newton_stops_and_a_rising_one_does_not():
    """The divergence test (newton's module notes) on the stability matrix's anisotropic mesh:
    inexact Newton-min with the paper's GMRES + ILU(0) diverges there (2.7e72 times its start
    after 100 steps without the test) and stops at the first iterate above DIVERGENCE
    max(X⁰'s residual, 1); exact Newton-min with the amg preset converges after rising more
    than 100 times above its start, which the test must let through."""
    from membranes.app.stability import select
    from membranes.nonlinear.newton import DIVERGENCE
    disc = discretise(select(["anisotropic"])[0].build(0.1))
    for variant, krylov in (("inexact", "paper"), ("exact", "amg")):
        res = newton(disc, variant=variant, krylov=krylov)
        start = res.history[0]["residual"]
        residuals = [r["residual"] for r in res.history if r["kind"] == "newton"]
        limit = DIVERGENCE * max(start, 1.0)
        if variant == "inexact":
            assert not res.converged
            assert res.reason.startswith(f"diverged at Newton step {res.newton_steps}: ")
            assert residuals[-1] > limit and max(residuals[:-1]) <= limit
            assert res.newton_steps < 50
        else:
            assert res.converged, res.reason
            assert 100 * start < max(residuals) <= limit


def test_progress_prints_one_line_per_newton_step():
    lines = []
    res = newton(disc_of("disk", 0.1), krylov="amg", progress=lines.append)
    assert len(lines) == res.newton_steps
    assert lines[0].startswith("Newton   1: residual")


# ## (f) Newton steps on the paper's disk (§8): reported, not asserted against the paper

def test_newton_steps_on_the_disk_hierarchy(capsys):
    rows = []
    for levels in range(4):
        disc = disc_of("disk", 0.2, levels)
        cells = disc.comm.allreduce(disc.mesh.topology.index_map(2).size_local, op=MPI.SUM)
        amg = newton(disc, krylov="amg")
        paper = newton(disc, krylov="paper")
        assert amg.converged and paper.converged
        # exact Newton's steps do not depend on the (exact) linear solver
        assert amg.newton_steps == paper.newton_steps
        rows.append((levels, cells, amg.newton_steps, paper.krylov_steps, amg.krylov_steps))
    with capsys.disabled():
        print("\nJ  elements  Newton steps (exact, min)  GMRES+ILU(0) its  FGMRES+mean/gap its")
        for row in rows:
            print("%d  %8d  %25d  %16d  %18d" % row)
    steps = [r[2] for r in rows]
    assert all(3 <= s <= 40 for s in steps)


# ## (b) the same iterate on 1, 2 and 3 processes

def _mpirun(procs, out, scene, h, runs, extra=()):
    done = mpirun([os.path.join(ROOT, "tests", "core", "mpi_newton.py"), out, scene, h, *runs],
                  processes=procs, timeout=300, extra=extra)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [json.loads(s) for s in done.stdout.splitlines() if s.startswith("{")]
    return np.load(out), lines


@pytest.mark.parametrize("procs, scene, runs, extra", [
    (2, "disk", ["amg:min:exact", "direct:min:exact", "paper:min:exact"], ()),
    (3, "square", ["amg:min:exact", "direct:fb:exact", "paper:fb:exact"], ()),
    (2, "square", ["amg:fb:exact", "amg:min:inexact"], ("--mca", "btl", "tcp,self")),
])
def test_the_same_solution_on_several_processes(tmp_path, procs, scene, runs, extra):
    serial, _ = mpi_run(scene, 0.1, runs)
    parallel, lines = _mpirun(procs, tmp_path / "out.npz", scene, 0.1, runs, extra)
    u_data, lam_data = disc_of(scene, 0.1).data_scales()
    assert np.abs(parallel["xy"] - serial["xy"]).max() <= 1e-12     # the same vertices
    assert [line["run"] for line in lines] == runs                  # (zip stops at the shorter)
    for spec, line in zip(runs, lines):
        assert line["run"] == spec and line["converged"], line
        assert line["processes"] == procs
        key = spec.replace(":", "_") + "__X"
        a, b = parallel[key], serial[f"{spec}/X"]
        assert np.abs(a[:2] - b[:2]).max() <= SAME * u_data
        assert np.abs(a[2] - b[2]).max() <= SAME * lam_data


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches its own MPI run")
def test_the_mean_gap_split_on_a_process_without_contact(tmp_path):
    """Newton-min's mean/gap preconditioner solves for λ at the contact vertices with one
    parallel product S_D δ, made where any process has such a vertex (a collective: every
    process must take part). On the radial scene with the small contact disk r ≤ 0.1 on 3
    processes, one process owns no contact vertex: the run converges to the serial solution.
    Decided on the local contact set alone, that process skipped the product and the run
    hung."""
    scene, runs = "radial,rho=0.1", ["amg:min:exact"]
    done = mpirun([os.path.join(ROOT, "tests", "core", "mpi_newton.py"), tmp_path / "out.npz",
                   scene, 0.1, *runs], processes=3, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    line = [json.loads(s) for s in done.stdout.splitlines() if s.startswith("{")][-1]
    assert line["converged"] and line["processes"] == 3, line
    assert min(line["contact_per_process"]) == 0 < max(line["contact_per_process"]), line
    parallel = np.load(tmp_path / "out.npz")
    serial, _ = mpi_run(scene, 0.1, runs)
    u_data, lam_data = discretise(make_scene(scene, 0.1)).data_scales()
    a, b = parallel["amg_min_exact__X"], serial["amg:min:exact/X"]
    assert np.abs(a[:2] - b[:2]).max() <= SAME * u_data
    assert np.abs(a[2] - b[2]).max() <= SAME * lam_data


@pytest.mark.parametrize("nu", [1, 10])
def test_inexact_newton_does_not_stop_at_its_own_guess(nu):
    """Inexact Newton's linear test ‖R_alg‖ ≤ ‖R_lin(X^{k-1})‖ holds at X^{k,0} = X^{k-1}
    (an equality for min): it is made from the ν-th Krylov iterate on, also for ν = 1 (which
    used to end the run at step 1 as 'stalled', its solve 'at the floor')."""
    disc = discretise(scenes.disk(h=0.3, levels=1))
    result = newton(disc, cfun="min", variant="inexact", krylov={"preset": "amg", "nu": nu})
    assert result.converged, result.reason
    steps = [r for r in result.history if r["kind"] == "newton"]
    assert all(r["i"] >= nu for r in steps), [r["i"] for r in steps]
