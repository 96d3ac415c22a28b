"""The vertex-block AMG preconditioner (membranes.preconditioner, `pc_type vertex_amg`) on the
eliminated 2N system: the same discrete solution as the default ILU(0), GMRES iterations per
Newton step that do not grow with the mesh, independence of the row scaling, refusal of what
it cannot precondition, and for min the exact mean/gap split (recognised where it applies,
exact with exact inner solves, its mean AMG kept per mesh).

"Same solution": both runs solve every Newton step to ‖R_alg‖/‖B‖ ≤ 2e-12 and stop Newton at
‖R_lin‖/‖(F, 0)‖ ≤ 1e-10, so the two final iterates differ by what the two linear residuals
leave, amplified by the condition of the Newton matrix (λ_l moves by about R_l / D_l,
D_l ~ h²): 1e-9 relative, as for GMRES against MUMPS in test_krylov.
"""

import functools

import numpy as np
import pytest
import scipy.sparse as sp

from membranes import newton_system as ns
from membranes import solve
from membranes.krylov import Krylov
from membranes.linear_solve import solve_direct
from membranes.newton import EXACT_LINEAR_TOL, linear_step, semismooth_newton
from membranes.discretisation import discretise
from membranes.preconditioner import MeanGapAMG, VertexAMG, gap_scales, mean_gap_split, slaves

from .conftest import scene

VAMG = (("pc_type", "vertex_amg"),)


def _its(run):
    return [rec["linear_it"] for rec in run.history if rec["kind"] == "newton"]


@functools.lru_cache(maxsize=None)
def _run(h, cfun, options=(), levels=0, system="eliminated"):
    """A cached disk solve; options: PETSc options as a tuple of pairs (() for ILU(0))."""
    return solve(scene("disk", h, levels=levels), cfun=cfun, system=system, estimators=False,
                 petsc_options=dict(options) or None, nested=False)


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_same_solution_as_ilu(cfun):
    ref = _run(0.05, cfun)
    run = _run(0.05, cfun, VAMG)
    assert run.converged and ref.converged, run.reason
    assert run.newton_iterations == ref.newton_iterations
    assert np.linalg.norm(run.X - ref.X) <= 1e-9 * np.linalg.norm(ref.X)
    # steps the Fischer–Burmeister line search damped stop short of the linear solution on
    # purpose (newton: B - A X_t = (1 - t) R_lin + t R); every full step is an exact solve
    assert all(rec["alg_residual"] <= EXACT_LINEAR_TOL for rec in run.history
               if rec["kind"] == "newton" and rec["step_length"] in (None, 1.0))
    assert max(_its(run)) < 30 and np.mean(_its(ref)) > 3 * np.mean(_its(run))


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_iterations_do_not_grow_with_the_mesh(cfun):
    """Disk h = 0.1 refined 0 and 2 times (411 and ~6k vertices, h / 4). An AMG V-cycle
    contracts at a rate independent of h on the Laplacians behind the system (module
    notes), so GMRES needs a bounded number of iterations per Newton step; ILU(0)'s grow
    like 1/h (×4 here: it is checked to grow at least ×2, so that the test can tell).
    The bound is on the mean over the Newton steps: fb's worst step (the third or fourth,
    where the gap scales d_l are of order 0.1 to 0.01 all over the contact zone) grows from
    9 to 21 iterations here (23 at 1e4 vertices, BENCHMARKS.md), min's does not (9 and 9)."""
    coarse, fine = (_run(0.1, cfun, VAMG, levels) for levels in (0, 2))
    ilu = [_run(0.1, cfun, (), levels) for levels in (0, 2)]
    assert coarse.converged and fine.converged and all(r.converged for r in ilu)
    assert fine.disc.n > 12 * coarse.disc.n
    assert np.mean(_its(fine)) <= 1.5 * np.mean(_its(coarse))
    assert max(_its(fine)) <= (1.5 if cfun == "min" else 3) * max(_its(coarse))
    assert np.mean(_its(ilu[1])) >= 2 * np.mean(_its(ilu[0]))


@functools.lru_cache(maxsize=None)
def _steps(cfun, count):
    """The first `count` eliminated Newton systems of the disk, h = 0.05 (direct solves), each
    with the vertices where u2 was eliminated (|β| < |α|) and β/α there."""
    rows = ns.linear_rows(_run(0.05, cfun).disc)
    X, steps = ns.initial_guess(rows, 0.05), []
    for _ in range(count):
        alpha, beta, _ = ns.complementarity_rows(rows, cfun, X)
        contact = np.abs(beta) < np.abs(alpha)
        step = linear_step(rows, cfun, "eliminated", X)
        steps.append((step, contact, np.where(contact, beta / np.where(contact, alpha, 1), 0)))
        X = step.expand(solve_direct(step.A, step.b)[0])
    return steps


def test_independent_of_row_scaling():
    """Scaling the two rows of each vertex (here by random factors in [0.01, 100], more than
    the 1/μ_α and κ scalings) leaves B⁻¹Ã, hence the preconditioned iteration, unchanged."""
    krylov = Krylov(dict(VAMG))
    rng = np.random.default_rng(0)
    for step, _, _ in _steps("fb", 4)[1:]:
        R = sp.diags(10.0 ** rng.uniform(-2, 2, step.A.shape[0]))
        plain = krylov.solve(step.A, step.b, step.guess, 1e-10, np.linalg.norm(step.b))
        scaled = krylov.solve((R @ step.A).tocsr(), R @ step.b, step.guess, 1e-10,
                              np.linalg.norm(R @ step.b))
        assert abs(plain[2] - scaled[2]) <= 1
        assert np.linalg.norm(plain[0] - scaled[0]) <= 1e-8 * np.linalg.norm(plain[0])


def test_fgmres_is_right_preconditioned_gmres():
    """vertex_amg runs FGMRES unless ksp_type is given: for a fixed preconditioner the same
    iterates as right-preconditioned GMRES in exact arithmetic, so the same iteration counts
    (±1 for round-off at the stopping test) and the same solutions to the tolerance's
    accuracy (1e-10 here, as in test_independent_of_row_scaling)."""
    fgmres, gmres = Krylov(dict(VAMG)), Krylov({**dict(VAMG), "ksp_type": "gmres"})
    assert fgmres.options["ksp_type"] == "fgmres" and gmres.options["ksp_type"] == "gmres"
    for step, _, _ in _steps("fb", 4)[1:]:
        f = fgmres.solve(step.A, step.b, step.guess, 1e-10, np.linalg.norm(step.b))
        g = gmres.solve(step.A, step.b, step.guess, 1e-10, np.linalg.norm(step.b))
        assert abs(f[2] - g[2]) <= 1
        assert np.linalg.norm(f[0] - g[0]) <= 1e-8 * np.linalg.norm(g[0])


def test_slaves_and_gap_scales():
    """min: the multipliers of contact vertices are slaves (u2 = u1 there, d = 0); fb: none
    are, and d_l = β_l/α_l where u2 was eliminated, read off the matrix (1 elsewhere)."""
    step, contact, _ = _steps("min", 3)[2]
    assert contact.any() and np.array_equal(slaves(step.A), contact)
    step, contact, ratio = _steps("fb", 4)[2]
    assert contact.any() and not slaves(step.A).any()
    d = gap_scales(step.A)
    assert np.allclose(d[contact], ratio[contact], rtol=1e-10)
    assert np.all(d[~contact] == 1.0)


def test_refuses_what_is_not_the_eliminated_system():
    with pytest.raises(ValueError, match="eliminated"):
        VertexAMG(sp.identity(3, format="csr"))
    singular = sp.csr_matrix(np.array([[1.0, 0, 1, 0], [0, 1, 0, 1], [1, 0, 1, 0], [0, 1, 0, 1]]))
    with pytest.raises(ValueError, match="singular"):
        VertexAMG(singular)
    with pytest.raises(ValueError, match="eliminated system only"):   # driver: before work
        _run(0.1, "min", VAMG, system="full")


def test_inner_options():
    with pytest.raises(ValueError, match="needs -pc_type vertex_amg"):
        Krylov({"vertex_amg_pc_type": "gamg"})
    with pytest.raises(ValueError, match="vertex_amg"):
        Krylov({**dict(VAMG), "vertex_amg_pc_type": "no_such_pc"})
    run = _run(0.1, "min", VAMG + (("vertex_amg_pc_type", "gamg"),))
    assert run.converged, run.reason


@functools.lru_cache(maxsize=None)
def _square_steps(count):
    """The first `count` eliminated min systems of the square (μ1 = 1, μ2 = 2), h = 0.1, each
    with the unweighted Ã (newton_system.eliminated_system) beside the weighted one."""
    rows = ns.linear_rows(discretise(scene("square", 0.1)))
    X, steps = ns.initial_guess(rows, 0.1), []
    for _ in range(count):
        step = linear_step(rows, "min", "eliminated", X)
        unweighted = ns.eliminated_system(rows, *ns.complementarity_rows(rows, "min", X))[0]
        steps.append((step, unweighted))
        X = step.expand(solve_direct(step.A, step.b)[0])
    return steps


def test_mean_gap_split_recognised():
    """min systems with the rows weighted by W split into mean and gap (module notes), with
    θ = μ2/(μ1 + μ2) and a ≠ 0 exactly at the contact vertices; fb systems do not, nor does the
    unweighted system when μ1 ≠ μ2 (its two blocks hold μ1 S and μ2 S)."""
    for step, contact, _ in _steps("min", 3)[1:]:
        S, a, b = mean_gap_split(step.A)
        assert np.array_equal(a != 0, contact)
        assert np.allclose(a[contact] / (a + b)[contact], 0.5, rtol=1e-12)
    for step, unweighted in _square_steps(3)[1:]:
        S, a, b = mean_gap_split(step.A)
        assert (a != 0).any()
        assert np.allclose(a[a != 0] / (a + b)[a != 0], 2.0 / 3.0, rtol=1e-12)
        assert mean_gap_split(unweighted) is None
    assert all(mean_gap_split(step.A) is None for step, _, _ in _steps("fb", 4)[1:])


def test_mean_gap_split_reference():
    """Given the S of an earlier step on the same mesh, the split returns that matrix itself
    (the same entries: no copy) with the a, b it finds without one; a reference that differs
    (another mesh's S, or S with one entry changed) is not taken, and the split is the same
    as without a reference."""
    steps = [s for s, _, _ in _steps("min", 3)]
    first, _, _ = mean_gap_split(steps[0].A)
    for step in steps[1:]:
        S, a, b = mean_gap_split(step.A)
        R, a_ref, b_ref = mean_gap_split(step.A, reference=first)
        assert R is first and np.array_equal(a_ref, a) and np.array_equal(b_ref, b)
        assert (S != R).nnz == 0
    changed = first.copy()
    changed.data[7] += 1e-3 * abs(changed.data).max()
    other = mean_gap_split(_square_steps(2)[1][0].A)[0]
    for reference in (changed, other):
        S, a, b = mean_gap_split(steps[1].A, reference=reference)
        assert S is not reference
        expected = mean_gap_split(steps[1].A)
        for x, y in zip((S.indptr, S.indices, S.data, a, b),
                        (*(getattr(expected[0], k) for k in ("indptr", "indices", "data")),
                         *expected[1:])):
            assert np.array_equal(x, y)


def test_mean_gap_split_vouched_for():
    """A min step's caller vouches for its structure (newton.LinearStep.contact: u2 eliminated
    there): the split then reads S, a and b and checks the first block (against the S of an
    earlier step too) but does not compare the second block with the model, and gives what the
    full comparison gives, to the bit (disk, μ1 = μ2, and square, μ1 ≠ μ2, several steps each,
    so the contact set changes; with and without the earlier S). fb steps vouch for nothing;
    a mask that is not where a ≠ 0 leaves the check to the comparison (here: the square's
    unweighted system, which the comparison refuses)."""
    square = _square_steps(4)
    for steps in ([s for s, _, _ in _steps("min", 4)], [s for s, _ in square]):
        first, _, _ = mean_gap_split(steps[0].A)
        for k, step in enumerate(steps):
            contact = step.contact()
            assert contact is not None and not contact.all()
            assert k == 0 or contact.any()          # the guess of step 1 may touch nowhere
            for reference in (None, first):
                S, a, b = mean_gap_split(step.A, reference=reference)
                R, a_vouched, b_vouched = mean_gap_split(step.A, reference=reference,
                                                         contact=contact)
                assert (R is first) == (reference is first)
                for x, y in zip((R.indptr, R.indices, R.data, a_vouched, b_vouched),
                                (S.indptr, S.indices, S.data, a, b)):
                    assert np.array_equal(x, y)
                assert np.array_equal(a != 0, contact)
    assert all(step.contact() is None for step, _, _ in _steps("fb", 3))
    step, unweighted = square[1]
    assert mean_gap_split(unweighted, contact=~step.contact()) is None


def test_mean_gap_split_is_exact():
    """With exact inner solves (LU) the split is Ã⁻¹ itself: FGMRES meets 1e-10 after one
    iteration, also for μ1 ≠ μ2."""
    krylov = Krylov({**dict(VAMG), "vertex_amg_pc_type": "lu"})
    systems = [s for s, _, _ in _steps("min", 3)[1:]] + [s for s, _ in _square_steps(3)[1:]]
    for step in systems:
        x, r, its = krylov.solve(step.A, step.b, step.guess, 1e-10, np.linalg.norm(step.b))
        assert its == 1 and np.linalg.norm(r) <= 1e-10 * np.linalg.norm(step.b)


def test_mean_amg_kept_per_mesh():
    """The mean's AMG is set up once per mesh, by the first solve that needs it (the first
    step, from X^0 = (g, 0, 0)): the next steps on the same mesh keep it (their mean is settled:
    they leave it out), a system of another mesh drops it, and sets up its own only where its
    mean is not settled (the square's step from a direct solve's iterate is; its step from
    (g, 0, 0) is not)."""
    krylov = Krylov(dict(VAMG))
    kept = []
    for step in [s for s, _, _ in _steps("min", 3)] + [_square_steps(2)[1][0],
                                                         _square_steps(2)[0][0]]:
        krylov.solve(step.A, step.b, step.guess, 1e-10, np.linalg.norm(step.b))
        kept.append(krylov._cache.get("mean"))
    assert kept[0] is not None and kept[0] is kept[1] is kept[2]
    assert kept[3] is None and kept[4] is not None and kept[4] is not kept[0]


def _settled(monkeypatch):
    """Record (N, mean_settled) of every solve's mean/gap split."""
    seen = []
    settle = MeanGapAMG.settle_mean

    def spy(self, r, bound, theta=None):
        settle(self, r, bound, theta)
        seen.append((self.S.shape[0], self.mean_settled))
    monkeypatch.setattr(MeanGapAMG, "settle_mean", spy)
    return seen


def test_settled_mean(monkeypatch):
    """A correction with m = 0 leaves the mean part ρ = (1 - θ) r1 + θ r2 of the residual
    unchanged (round-off: 1e-12 of the correction's residual). From the solution plus such a
    correction (ρ at round-off) the solve leaves the mean's V-cycles out and still meets its
    bound; from the solution plus a change of the mean it does not leave them out."""
    seen = _settled(monkeypatch)
    krylov = Krylov(dict(VAMG))
    rng = np.random.default_rng(1)
    for step, contact, _ in _steps("min", 3)[1:]:
        S, a, b = mean_gap_split(step.A)
        n, theta = S.shape[0], (a / (a + b))[contact][0]
        x = krylov.solve(step.A, step.b, step.guess, 1e-13, np.linalg.norm(step.b))[0]
        delta = np.where(contact, 0.0, rng.standard_normal(n))
        gap_only = np.concatenate([-theta * delta, np.where(contact, rng.standard_normal(n),
                                                            (1 - theta) * delta)])
        moved = step.A @ gap_only
        rho = (1 - theta) * moved[:n] + theta * moved[n:]
        assert np.linalg.norm(rho) <= 1e-12 * np.linalg.norm(moved)
        bound = 1e-10 * np.linalg.norm(step.b)
        for change, settled in ((1e-3 * gap_only, True),
                                (1e-3 * np.concatenate([np.ones(n), np.where(contact, 0, 1)]),
                                 False)):
            seen.clear()
            _, r, its = krylov.solve(step.A, step.b, x + change, 1e-10, np.linalg.norm(step.b))
            assert seen == [(n, settled)] and its >= 1 and np.linalg.norm(r) <= bound


def test_gap_solved_alone(monkeypatch):
    """Where the mean is settled the correction is solved on the gap's own system S_ff δ = g
    (membranes.krylov, module notes; taken: `_GapSolve` made), with the same iteration counts
    as GMRES on the 2N system with the mean/gap split as PC (θ = 1/2 on the disk: both
    minimise the same residual; ±1 for round-off at the test) and the same solution to the
    tolerance's accuracy (1e-10 here, as in test_independent_of_row_scaling); its residual,
    that of the 2N system, meets the bound. With a mean not settled the 2N system is solved."""
    from membranes import krylov as krylov_module
    made = []
    original = krylov_module._GapSolve.__init__

    def spy(self, *args):
        original(self, *args)
        made.append(self.context.free.size)
    monkeypatch.setattr(krylov_module._GapSolve, "__init__", spy)
    rng = np.random.default_rng(2)
    for step, contact, _ in _steps("min", 3)[1:]:
        S, a, b = mean_gap_split(step.A)
        n, theta = S.shape[0], (a / (a + b))[contact][0]
        assert theta == pytest.approx(0.5, rel=1e-12)
        x = solve_direct(step.A, step.b)[0]
        delta = np.where(contact, 0.0, rng.standard_normal(n))
        guess = x + 1e-3 * np.concatenate([-theta * delta, np.where(
            contact, rng.standard_normal(n), (1 - theta) * delta)])
        scale = np.linalg.norm(step.b)
        made.clear()
        alone = Krylov(dict(VAMG)).solve(step.A, step.b, guess, 1e-10, scale)
        assert made == [np.count_nonzero(~contact)]
        monkeypatch.setattr(krylov_module, "GAP_KSP_TYPES", ())
        whole = Krylov(dict(VAMG)).solve(step.A, step.b, guess, 1e-10, scale)
        monkeypatch.setattr(krylov_module, "GAP_KSP_TYPES", ("fgmres", "gmres"))
        assert len(made) == 1 and alone[2] >= 1 and abs(alone[2] - whole[2]) <= 1
        assert np.linalg.norm(alone[1]) <= 1e-10 * scale
        assert np.array_equal(alone[1], step.b - step.A @ alone[0])
        assert np.linalg.norm(alone[0] - whole[0]) <= 1e-8 * np.linalg.norm(whole[0])
        made.clear()       # the mean moved: not settled, the 2N system
        Krylov(dict(VAMG)).solve(step.A, step.b, guess + 1e-3, 1e-10, scale)
        assert made == []


def test_gap_solved_alone_with_unequal_moduli(monkeypatch):
    """θ ≠ 1/2 (the square: μ1 = 1, μ2 = 2, θ = 2/3): the gap's GMRES minimises the gap's
    residual, not the whole system's, whose test it still takes (gated through bounds on the
    whole residual: membranes.krylov). An exact Newton run with the exact mean solves every
    step on the gap's system alone and ends as the run on the 2N systems does: the same
    Newton steps, GMRES within one iteration a step, iterates 1e-8 apart (relative; the
    linear solves stop at 2e-12 of ‖B‖ each)."""
    from membranes import krylov as krylov_module
    made = []
    original = krylov_module._GapSolve.__init__

    def spy(self, *args):
        original(self, *args)
        made.append(self.context.theta)
    monkeypatch.setattr(krylov_module._GapSolve, "__init__", spy)
    problem = scene("square", 0.03)       # 1437 vertices
    options = dict(newton="exact", cfun="min", system="eliminated",
                   petsc_options=dict(VAMG), estimators=False)
    alone = solve(problem, **options)
    monkeypatch.setattr(krylov_module, "GAP_KSP_TYPES", ())
    steps = len(made)
    whole = solve(problem, **options)
    assert alone.converged and whole.converged and len(made) == steps
    assert steps == alone.newton_iterations >= 3
    assert all(theta == pytest.approx(2.0 / 3.0, rel=1e-12) for theta in made)
    assert alone.newton_iterations == whole.newton_iterations
    assert abs(alone.linear_iterations - whole.linear_iterations) <= alone.newton_iterations
    assert np.linalg.norm(alone.X - whole.X) <= 1e-8 * np.linalg.norm(whole.X)


def test_mean_settled_after_the_first_step(monkeypatch):
    """Solving whole Newton steps (no exact mean given, membranes.mean), the mean is not
    settled at the first step from (g, 0, 0), whose guess does not solve the mean's equation,
    and settled at most later steps: their guess keeps the mean of the iterate before
    (newton.mean_keeping_shift), so what is left is the mean part of the last solve's
    residual, settled where that is below half the bound. Disk, h = 0.05, exact Newton."""
    seen = _settled(monkeypatch)
    problem = scene("disk", 0.05)
    rows = ns.linear_rows(discretise(problem))
    result = semismooth_newton(rows, problem.g, "min", "eliminated", "exact", Krylov(dict(VAMG)))
    assert result.converged and result.newton_iterations >= 3
    settled = [s for _, s in seen]
    assert len(settled) == result.newton_iterations and not settled[0]
    assert sum(settled[1:]) >= len(settled[1:]) / 2
