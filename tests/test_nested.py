"""Nested iteration on the mesh hierarchy (membranes.nested, `solve(nested=...)`).

The claim of issue 6 (item 1): solving T_0, ..., T_J in turn, each level from the prolonged
solution of the one below, keeps the Newton steps per level bounded (≤ 6) as h → 0. Checked
here on the disk, h0 = 0.2, up to J = 3 (6913 vertices) for exact Newton (MUMPS and GMRES),
min and Fischer–Burmeister (FB with its active-set steps: newton), and up to J = 2 for the
adaptive variant (its multilevel flux set-up is the cost); J = 4 is measured by
benchmarks/bench_nested.py.
"""

import functools
import json

import numpy as np
import pytest

from membranes import solve
from membranes.newton import LS_SIGMA
from membranes.nested import level_problem, prolong, prolongation

from .conftest import cli_bad_input, scene

H = 0.2
MAX_STEPS = 6


@functools.lru_cache(maxsize=None)
def run(levels, nested=True, **options):
    """A cached disk solve (estimators only where the variant uses them)."""
    return solve(scene("disk", H, levels=levels), nested=nested,
                 estimators=options.get("newton") == "adaptive", **options)


def _spaces(problem):
    from dolfinx import fem
    return [fem.FunctionSpace(m, ("Lagrange", 1)) for m in problem.hierarchy.meshes]


def _steps(sol):
    return [r["newton_iterations"] for r in sol.per_level]


# ## The prolongation

def test_prolongation_reproduces_linear_functions_exactly():
    """P1 interpolation on a Plaza refinement: weights 1 (old vertex) or 1/2, 1/2 (edge
    midpoint), so linear functions and constants come through to round-off, and the boundary
    values of the membranes (u1 = g, u2 = λ = 0) exactly."""
    problem = scene("disk", 0.3, levels=3)
    V = _spaces(problem)
    rng = np.random.default_rng(0)
    for j in range(1, len(V)):
        P = prolongation(V[j - 1], V[j], problem.hierarchy.parent_cells[j - 1])
        xc = V[j - 1].tabulate_dof_coordinates()[:, :2]
        xf = V[j].tabulate_dof_coordinates()[:, :2]
        assert P.shape == (len(xf), len(xc))
        assert set(np.unique(P.data)) <= {0.5, 1.0}
        assert np.array_equal(np.asarray(P.sum(axis=1)).ravel(), np.ones(len(xf)))
        for _ in range(3):
            a, b, c = rng.normal(size=3)
            assert np.abs(P @ (a + b * xc[:, 0] + c * xc[:, 1])
                          - (a + b * xf[:, 0] + c * xf[:, 1])).max() <= 1e-14
        # a coarse vertex keeps its value, the other fine vertices are edge midpoints
        kept = np.isclose(np.asarray(P.max(axis=1).todense()).ravel(), 1.0)
        assert kept.sum() == len(xc)


def test_prolonged_guess_keeps_the_boundary_values_and_the_order():
    sol = run(1)
    coarse = run(0, nested=False)
    d = sol.disc
    P = prolongation(coarse.disc.V, d.V, sol.problem.hierarchy.parent_cells[0])
    n, b = d.n, d.boundary
    Y = prolong(P, coarse.X)
    assert np.all(Y[:n][b] == sol.problem.g) and np.all(Y[n:2 * n][b] == 0.0)
    assert np.all(Y[2 * n:][b] == 0.0)
    # the fine level starts from the coarse solution: the same function (nested P1 spaces),
    # its energy error integrated on the fine mesh (the composite rule on the cells the circle
    # cuts is another rule there: measured 5e-7 relative apart)
    first = next(rec for rec in sol.history if rec["level"] == 1)
    assert first["kind"] == "initial" and first["energy_error"] == pytest.approx(
        sol.per_level[0]["energy_error"], rel=1e-5)
    with pytest.raises(ValueError, match="values"):
        prolong(P, coarse.X[:-1])


def test_level_problem_truncates_the_hierarchy():
    problem = scene("disk", H, levels=2)
    for j in range(3):
        pj = level_problem(problem, j)
        assert pj.levels == j and pj.mesh is problem.hierarchy.meshes[j]
        assert (pj.mu1, pj.mu2, pj.g, pj.exact) == (problem.mu1, problem.mu2, problem.g,
                                                    problem.exact)
    assert level_problem(problem, 2) is problem
    with pytest.raises(ValueError):
        level_problem(problem, 3)


# ## Newton steps per level

@pytest.mark.parametrize("cfun", ["min", "fb"])
@pytest.mark.parametrize("levels,options", [
    (3, (("linear_solver", "direct"),)),                     # exact, MUMPS
    (3, ()),                                                 # exact, GMRES + ILU(0)
    (2, (("newton", "adaptive"),)),                          # adaptive, multilevel flux
], ids=["exact-mumps", "exact-gmres", "adaptive"])
def test_newton_steps_per_level_are_bounded(levels, options, cfun):
    options += (("cfun", cfun),) if cfun != "min" else ()      # min: the cached default runs
    sol = run(levels, **dict(options))
    print(f"disk h0 = {H}, J = {levels}, {dict(options)}: Newton steps per level {_steps(sol)}, "
          f"linear {[r['linear_iterations'] for r in sol.per_level]}")
    assert sol.converged, sol.reason
    assert [r["level"] for r in sol.per_level] == list(range(levels + 1))
    assert all(r["converged"] for r in sol.per_level)
    assert max(_steps(sol)) <= MAX_STEPS
    assert [r["n_vertices"] for r in sol.per_level] == \
        [m.topology.index_map(0).size_global for m in sol.problem.hierarchy.meshes]
    # totals, history and the finest level's figures
    assert sol.newton_iterations == sum(_steps(sol))
    assert sol.linear_iterations == sum(r["linear_iterations"] for r in sol.per_level)
    levels_seen = [rec["level"] for rec in sol.history]
    assert levels_seen == sorted(levels_seen) and set(levels_seen) == set(range(levels + 1))
    cumulative = [rec["cumulative_linear_its"] for rec in sol.history]
    assert cumulative == sorted(cumulative) and cumulative[-1] == sol.linear_iterations
    times = [rec["wall_time_s"] for rec in sol.history]
    assert times == sorted(times)
    assert sol.wall_time_s == times[-1] == pytest.approx(
        sum(r["wall_time_s"] for r in sol.per_level), rel=1e-9)
    assert sol.disc.n == sol.per_level[-1]["n_vertices"]
    assert sol.energy_error == sol.per_level[-1]["energy_error"]
    if sol.options["newton"] == "adaptive":
        # the multilevel flux on T_J only; the levels below take the ν flux (driver)
        assert [r["alg_flux"] for r in sol.per_level] == ["nu"] * levels + ["multilevel"]
        assert sol.final_record["eta"] is not None
        assert sol.summary()["effectivity"] >= 1.0
    else:
        assert all(r["alg_flux"] is None for r in sol.per_level)
        assert sol.final_record["residual"] <= 1e-10


def test_nested_steps_stay_flat_where_single_mesh_steps_grow():
    """The single-mesh method from X^0 = (g, 0, 0) on T_3 (GMRES, Newton-min) needs more
    steps than any level of the nested run."""
    nested, plain = run(3), run(3, nested=False)
    assert plain.converged and plain.newton_iterations > max(_steps(nested))
    print(f"J = 3: single mesh {plain.newton_iterations} Newton steps, "
          f"{plain.linear_iterations} GMRES; nested {_steps(nested)}, "
          f"{nested.linear_iterations} GMRES")


def test_fischer_burmeister_active_set_steps():
    """How FB meets the bound (newton: active-set steps; without them 10, 7, 7, 7 here): every
    level starts with FB's own step at the iterate; an active-set step (FB linearised at the
    projection onto the complementarity set) comes only after a step that decreased the merit
    θ = ½‖Φ‖² by the factor 1 - 2σ, and is kept only if it decreases it by that factor too;
    the last one lands on the discrete solution (min's active set step: once the active set
    is right the residual is round-off, ≤ 1e-13 against the tolerance 1e-10)."""
    sol = run(3, cfun="fb", linear_solver="direct")
    assert sol.converged, sol.reason
    for level in range(4):
        recs = [r for r in sol.history if r["level"] == level and r["kind"] != "krylov"]
        assert recs[1]["linearised_at"] == "iterate"
        r = [rec["residual"] for rec in recs]
        projected = [k for k in range(1, len(recs)) if recs[k]["linearised_at"] == "projection"]
        assert projected and projected[-1] == len(recs) - 1 and r[-1] <= 1e-13
        for k in projected:
            assert r[k] ** 2 <= (1 - 2 * LS_SIGMA) * r[k - 1] ** 2
            assert r[k - 1] ** 2 <= (1 - 2 * LS_SIGMA) * r[k - 2] ** 2
        # a rejected active-set solve counts: MUMPS solves per step, 1 or 2
        assert all(rec["linear_it"] in (1, 2) for rec in recs[1:])


# ## The same discrete solution

@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_nested_solution_is_the_single_mesh_solution(cfun):
    """Exact Newton (MUMPS) on T_3, nested or not. Both runs stop at a relative residual
    ‖W R_lin‖/‖W F‖ ≤ 1e-10 of the same discrete problem, whose solution is unique; Newton-min
    (the primal-dual active set method) ends at the exact discrete solution once the active
    set is right (its final residual is at round-off, ~1e-15), and Fischer–Burmeister ends at
    most 1e-10 away in residual (its last step here is an active-set step, min's: newton,
    and ends at round-off too; a last FB step at the iterate stops where the tolerance is
    met). The difference in X is the inverse Jacobian (norm ~ h^-2 ~ 1e3 relative here)
    times a residual below 1e-10: 1e-8 relative bounds it with margin (measured: 0 for both,
    the same active set step on the same MUMPS system; ~1e-11 for fb before its active-set
    steps)."""
    nested = run(3, cfun=cfun, linear_solver="direct")
    plain = run(3, nested=False, cfun=cfun, linear_solver="direct")
    assert nested.converged and plain.converged
    diff = np.linalg.norm(nested.X - plain.X) / np.linalg.norm(plain.X)
    print(f"{cfun}: |X_nested - X| / |X| = {diff:.1e}")
    assert diff <= 1e-8
    assert nested.energy_error == pytest.approx(plain.energy_error, rel=1e-8)


def test_levels_made_ahead_give_the_same_run(monkeypatch):
    """Process 0 of a run on several processes makes the finer levels of a nested run (their
    discretisation, linear rows and prolongation, then the next level's mean multigrid:
    driver._Ahead) while it waits for estimates, as far as the waits go (membranes.pipeline).
    Made all before level 1 runs, the run is the same bit for bit as with each level made at
    its turn: nothing made ahead depends on when it is made (the exact mean, with vertex_amg,
    chains through the levels too)."""
    from membranes import driver, scenes
    problem = scenes.disk(h=0.3, levels=2)
    options = {"newton": "adaptive", "system": "eliminated",
               "petsc_options": {"pc_type": "vertex_amg"}}
    plain = solve(problem, **options)
    made, start = [], driver._Ahead.start

    def all_at_once(self, first):
        start(self, first)
        while self.step():
            made.append(sorted(self.made))
    monkeypatch.setattr(driver._Ahead, "start", all_at_once)
    early = solve(problem, **options)
    assert made[-1] == [1, 2]           # both finer levels made before level 1 ran
    assert np.array_equal(early.X, plain.X)
    assert (early.newton_iterations, early.linear_iterations) == \
        (plain.newton_iterations, plain.linear_iterations)
    assert [r["eta"] for r in early.history] == [r["eta"] for r in plain.history]


# ## The option

def test_nested_is_the_default_with_a_hierarchy_only():
    assert run(1).options["nested"] is True and run(1).summary()["nested"] is True
    single = solve(scene("disk", 0.3), estimators=False)
    assert single.options["nested"] is False
    assert [r["level"] for r in single.per_level] == [0]
    assert single.per_level[0]["newton_iterations"] == single.newton_iterations
    plain = run(1, nested=False)
    assert len(plain.per_level) == 1 and plain.per_level[0]["level"] == 1
    assert {rec["level"] for rec in plain.history} == {1}


def test_bad_nested_options():
    with pytest.raises(ValueError, match="hierarchy"):
        solve(scene("disk", 0.3), nested=True)
    with pytest.raises(ValueError, match="nested"):
        solve(scene("disk", 0.3, levels=1), nested="yes")
    problem = scene("disk", 0.3, levels=1)
    n = problem.mesh.topology.index_map(0).size_global
    with pytest.raises(ValueError, match="T_0"):
        solve(problem, initial_guess=np.zeros(3 * n))
    # a function of the discretisation is the guess on T_0
    sol = solve(problem, estimators=False, initial_guess=lambda d: np.zeros(3 * d.n))
    assert sol.converged and sol.options["initial_guess"] == "given"


def test_cli_nested(tmp_path, capsys):
    from membranes.cli import main
    code = main(["solve", "--quiet", "--h", "0.3", "--levels", "1", "--no-estimators",
                 "--out", str(tmp_path / "out")])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and line["nested"] is True and len(line["newton_per_level"]) == 2
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["nested"] is True and [r["level"] for r in summary["per_level"]] == [0, 1]
    assert (tmp_path / "out" / "history.csv").read_text().startswith("level,")
    code = main(["solve", "--quiet", "--h", "0.3", "--levels", "1", "--no-estimators",
                 "--no-nested"])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert code == 0 and line["nested"] is False and len(line["newton_per_level"]) == 1
    err = cli_bad_input(["--nested"], tmp_path / "bad", capsys)
    assert "hierarchy" in err
