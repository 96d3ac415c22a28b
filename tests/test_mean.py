"""The exact mean of the two membranes (membranes.mean): checked against direct solves of the
whole Newton system, which know nothing of the mean/gap split."""

import numpy as np

from membranes import mean as mean_module
from membranes import newton_system as ns
from membranes import solve
from membranes.discretisation import discretise
from membranes.krylov import Krylov
from membranes.linear_solve import solve_direct
from membranes.newton import linear_step, solve_step
from membranes.preconditioner import MeanGapAMG

from .conftest import scene

VAMG = {"pc_type": "vertex_amg"}
TIGHT = 1e-14       # ρ bound relative to ‖W F‖ for the checks: round-off level


def _square(cfun="min", steps=4):
    """The square (μ1 = 1, μ2 = 2), h = 0.1: its rows and exact Newton iterates (MUMPS on
    the eliminated system, X^0 = (g, 0, 0))."""
    rows = ns.linear_rows(discretise(scene("square", 0.1)))
    X = [ns.initial_guess(rows, 0.1)]
    for _ in range(steps):
        step = linear_step(rows, cfun, "eliminated", X[-1])
        X.append(step.expand(solve_direct(step.A, step.b)[0]))
    return rows, X


def test_exact_mean_is_the_iterates_mean():
    """Every exact Newton iterate X^k (k ≥ 1) satisfies the membrane rows, so its mean
    (μ1 u1 + μ2 u2)/(μ1 + μ2) is the solution M of the one Poisson problem of the module
    notes, whatever its contact set (they differ from step to step): to 1e-10 relative (MUMPS
    and CG to round-off, with condition numbers ~1e2 at h = 0.1), for min and fb."""
    for cfun in ("min", "fb"):
        rows, X = _square(cfun)
        disc = discretise(scene("square", 0.1))
        th = mean_module.theta(disc.problem)
        assert th == 2.0 / 3.0
        M = mean_module.exact_mean(disc, X[0], TIGHT * rows.norm_F)
        for Xk in X[1:]:
            m = mean_module.mean_of(Xk, rows.n, th)
            assert np.linalg.norm(m - M) <= 1e-10 * np.linalg.norm(M)


def test_newton_step_does_not_see_the_mean():
    """Moving X^{k-1} by a mean change alone (u1 and u2 by the same random s, λ kept) leaves
    the next exact Newton iterate unchanged (1e-10: round-off of two MUMPS solves): the
    C-functions read u1 - u2 and λ only (DESIGN §3)."""
    rng = np.random.default_rng(3)
    for cfun in ("min", "fb"):
        rows, X = _square(cfun, 2)
        n = rows.n
        s = rng.standard_normal(n)
        s[rows.boundary] = 0.0
        moved = X[1].copy()
        moved[:n] += s
        moved[n:2 * n] += s
        steps = [linear_step(rows, cfun, "eliminated", Y) for Y in (X[1], moved)]
        a, b = (st.expand(solve_direct(st.A, st.b)[0]) for st in steps)
        assert np.linalg.norm(a - b) <= 1e-10 * np.linalg.norm(a)


def test_step_with_the_mean(monkeypatch):
    """solve_step with the mean: GMRES on the gap and λ only, then M: the same iterate as the
    direct solve of the whole step (to the solve's tolerance, 1e-10 here, times the
    conditioning: 1e-7), the returned residual is b - A y of the returned iterate (recomputed
    here: 1e-12 of ‖B‖), and it meets the step's bound; the solve never sets up the mean's
    AMG (its mean part was taken out: settled)."""
    rows, X = _square("min")
    disc = discretise(scene("square", 0.1))
    M = mean_module.exact_mean(disc, X[0], TIGHT * rows.norm_F)
    level = mean_module.LevelMean(mean_module.theta(disc.problem), M)
    krylov = Krylov(dict(VAMG))
    settled = []
    original = MeanGapAMG.settle_mean

    def spy(self, r, bound, theta=None):
        original(self, r, bound, theta)
        settled.append(self.mean_settled)
    monkeypatch.setattr(MeanGapAMG, "settle_mean", spy)
    for Xk in X[:3]:
        step = linear_step(rows, "min", "eliminated", Xk)
        direct = step.expand(solve_direct(step.A, step.b)[0])
        Xn, R, its = solve_step(step, krylov, 1e-10, 1, lambda its, current: False,
                                mean=level)
        assert its >= 1
        assert np.linalg.norm(Xn - direct) <= 1e-7 * np.linalg.norm(direct)
        n = rows.n
        assert np.allclose(mean_module.mean_of(Xn, n, level.theta), M, rtol=0,
                           atol=1e-12 * np.abs(M).max())
        y = np.concatenate([Xn[:n], np.where(step.z_is_u2, Xn[n:2 * n], Xn[2 * n:])])
        weighted = rows.weighted(R)[:2 * n]
        assert np.linalg.norm(weighted - (step.b - step.A @ y)) <= \
            1e-12 * step.norm_B
        assert np.linalg.norm(weighted) <= 1e-10 * step.norm_B
    assert settled == [True] * 3 and "mean" not in krylov._cache


def test_nested_run_takes_the_exact_mean(monkeypatch):
    """A nested adaptive vertex_amg run solves one mean per level, and every Newton step's
    mean is settled (no mean AMG set up in the steps); its final iterate has the mean M of
    T_J (1e-12 of M: M's bound is 1e-2 of the steps' and 1e-14 of ‖W F‖ here, and the steps
    move the gap and λ only)."""
    solves, settled = [], []
    solve_mean, settle = mean_module.MeanSolve.solve, MeanGapAMG.settle_mean

    def spy_solve(self, m0, bound):
        out = solve_mean(self, m0, bound)
        solves.append((self.n, self.its))
        return out

    def spy_settle(self, r, bound, theta=None):
        settle(self, r, bound, theta)
        settled.append(self.mean_settled)
    monkeypatch.setattr(mean_module.MeanSolve, "solve", spy_solve)
    monkeypatch.setattr(MeanGapAMG, "settle_mean", spy_settle)
    run = solve(scene("disk", 0.2, levels=2), newton="adaptive", cfun="min",
                system="eliminated", petsc_options=dict(VAMG), alg_flux="nu")
    assert run.converged
    assert [n for n, _ in solves] == [lvl["n_vertices"] for lvl in run.per_level]
    assert all(1 <= its <= 30 for _, its in solves)
    assert len(settled) == run.newton_iterations and all(settled)
    M = mean_module.exact_mean(run.disc, run.X, TIGHT * ns.linear_rows(run.disc).norm_F)
    m = mean_module.mean_of(run.X, run.disc.n, mean_module.theta(run.problem))
    assert np.linalg.norm(m - M) <= 1e-12 * np.linalg.norm(M)


def test_multigrid_mean_on_nested_meshes():
    """On T_1 and T_2 of a disk hierarchy the multigrid MeanSolve (built on T_0's AMG
    MeanSolve) gives the M of a direct solve of the interior Poisson problem (scipy's spsolve,
    which shares nothing with CG or PCMG but the matrix), to the CG bound times the
    conditioning (1e-10 relative here), in as few CG iterations as a V-cycle should (≤ 15);
    the interior prolongation satisfies the Galerkin identity P^T K_j P = K_{j-1} of nested
    P1 spaces (round-off: 1e-12 of the largest entry), on which the rediscretised coarse
    operators rely."""
    import scipy.sparse.linalg as spla
    from membranes.nested import level_problem, prolongation
    from membranes.preconditioner import principal_submatrix
    problem = scene("disk", 0.3, levels=2)
    discs = [discretise(level_problem(problem, j)) for j in range(3)]
    solver = mean_module.MeanSolve(discs[0])
    for j in (1, 2):
        disc = discs[j]
        P = prolongation(discs[j - 1].V, disc.V, problem.hierarchy.parent_cells[j - 1])
        coarse_inner = solver.inner_index
        coarse_K = solver.levels[-1][0]
        solver = mean_module.MeanSolve(disc, None, solver, P)
        assert len(solver.levels) == j + 1
        P_II = mean_module.interior_prolongation(P, solver.inner_index, coarse_inner)
        K = solver.levels[-1][0]
        galerkin = (P_II.T @ K @ P_II - coarse_K).tocoo()
        assert np.abs(galerkin.data).max() <= 1e-12 * np.abs(coarse_K.data).max()
        rows = ns.linear_rows(disc)
        M = solver.solve(np.zeros(disc.n), TIGHT * rows.norm_F)
        S = disc.S1 + disc.S2
        inner = solver.inner_index
        direct = solver.boundary_value.copy()
        rhs = disc.F1 + disc.F2 - S @ solver.boundary_value
        direct[inner] = spla.spsolve(principal_submatrix(S, inner).tocsc(), rhs[inner])
        assert np.linalg.norm(M - direct) <= 1e-10 * np.linalg.norm(direct)
        assert 1 <= solver.its <= 15, solver.its
    solver.destroy()
