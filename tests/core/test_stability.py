"""The stability matrix of §11 (membranes.app.stability) on a quick subset: the cases are what
they claim, representative methods converge without NaN with complementarity at the Newton
tolerance and η ≥ error where the solution is known, scaled data scale the solution and keep
the counts, a run that raises is a failed row, and `membranes stability` writes its files."""

import argparse
import csv
import functools

import numpy as np
import pytest
from mpi4py import MPI

from membranes.app import report, stability
from membranes.fem import meshes

from ..conftest import aspect_ratios

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="serial subset")

H = 0.3              # the disk meshes of the quick subset
TOL = 1e-10          # the Newton tolerance of exact and inexact (§8)
# both C-functions, the three variants, the three solvers
METHODS = (("min", "exact", "direct"), ("fb", "exact", "amg"), ("min", "inexact", "amg"),
           ("fb", "inexact", "paper"), ("min", "adaptive", "paper"), ("fb", "adaptive", "amg"))


@functools.lru_cache(maxsize=None)
def matrix(names):
    cases = stability.select(list(names))
    runs = {c.name: stability.run_case(c, H, METHODS) for c in cases}
    return stability.table(cases, runs), runs


def test_case_meshes_are_what_they_claim():
    case = {c.name: c for c in stability.CASES}
    aniso = case["anisotropic"].build(H).mesh
    assert aspect_ratios(aniso).max() >= 100
    assert case["tiny"].build(H).mesh.topology.index_map(2).size_global == 18
    d = meshes.cell_diameters(case["graded"].build(H).mesh)
    assert d.max() / d.min() > 100
    assert len(stability.CASES) == 24 and len(stability.METHODS) == 14
    nested = case["nested_near_total"]
    assert nested.levels == 2 and nested.klass == "nested"
    assert len(nested.build(2 * H, nested.levels).hierarchy.meshes) == 3
    assert {m[2] for m in stability.METHODS if m[1] != "exact"} == {"paper", "amg"}


def test_select():
    assert [c.name for c in stability.select(["scaled_1e+08"])] == \
        ["mu_ratio_1", "scaled_1e+08"]                  # with the case it is a copy of
    with pytest.raises(ValueError, match="unknown stability case 'nonsense'"):
        stability.select(["tiny", "nonsense"])
    with pytest.raises(ValueError, match="stability case 'tiny' given twice"):
        stability.select(["tiny", "grazing", "tiny"])             # (it was run once)
    for bad in (0, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="positive finite"):
            stability.check_h(bad)


@pytest.mark.parametrize("names", [("tiny", "far_guess"), ("scaled_1e-08", "grazing"),
                                   ("nested_near_total",)])
def test_cases_converge_and_are_certified(names):
    rows, runs = matrix(names)
    assert len(rows) == len(METHODS) * len(stability.select(list(names)))
    for r in rows:
        label = f"{r['case']} {r['method']}"
        assert r["converged"], f"{label}: {r['reason']}"
        if "/adaptive/" not in r["method"]:
            # exact and inexact stop at ‖W R_lin‖/‖W F‖ ≤ TOL; the constraint rows are part
            # of R_lin, so their violation relative to the data is of that order (a factor
            # 10 for ‖W F‖ against the data sizes u_data, λ_data on these meshes)
            assert r["final_residual"] <= TOL, label
            assert r["complementarity_violation"] <= 10 * TOL, label
        assert r["bound_guaranteed"], label
        assert r["eta"] >= r["energy_error"] > 0, label       # the guaranteed bound (§7)


def test_scaled_data_scale_the_solution():
    """(f1, f2, g) → s (f1, f2, g): X → s X to round-off and the same counts (residuals,
    tolerances and the C-function's scale are relative to the data: nonlinear.system)."""
    rows, _ = matrix(("scaled_1e-08", "grazing"))
    scaled = [r for r in rows if r["scale_defect"] is not None]
    assert len(scaled) == len(METHODS)
    for r in scaled:
        assert r["same_counts"], r
        assert r["scale_defect"] <= 1e-10, r


def test_a_run_that_raises_is_a_failed_row():
    case = stability.select(["tiny"])[0]
    runs = {"tiny": stability.run_case(case, H, [("min", "adaptive", "direct"),
                                                  ("min", "exact", "direct")])}
    rows = stability.table([case], runs)
    assert [r["converged"] for r in rows] == [False, True]
    assert rows[0]["reason"].startswith("ValueError: the adaptive variant stops a Krylov")
    text = stability.markdown(rows, H, 1.0, 1)
    assert "1 of 2 runs converged" in text and "tiny min/adaptive/direct: ValueError" in text


def test_a_run_that_raises_after_a_signal_ends_the_matrix():
    """An error that follows a signal is the signal's (membranes.app.interrupts): a process
    other than 0 goes on for a moment after it, and a run it then fails (its staging folder
    or compilations gone) is no failed row to go on from: the matrix ends as interrupted."""
    from membranes.app import interrupts
    case = stability.select(["tiny"])[0]
    interrupts._pending = interrupts.Terminated       # (as a handler leaves it, deferred)
    try:
        with pytest.raises(interrupts.Terminated):
            stability.run_case(case, H, [("min", "adaptive", "direct")])
    finally:
        interrupts.caught()


def test_scale_defect_measures_the_difference():
    """The defect of a run against itself times s is 0, and a planted change shows."""
    rows, runs = matrix(("tiny", "far_guess"))
    sol = runs["tiny"]["min/exact/direct"]
    assert stability.scale_defect(sol, sol, 1.0) == 0.0
    X = sol.X.copy()
    sol2 = type(sol)(**{**sol.__dict__, "X": X})
    u1, _, _ = sol.disc.split(X)
    u1[np.argmax(np.abs(u1))] *= 1.0 + 1e-6
    assert stability.scale_defect(sol2, sol, 1.0) == pytest.approx(1e-6, rel=1e-9)


def test_command_writes_the_matrix(tmp_path):
    parser = argparse.ArgumentParser()
    stability.add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "stab"
    args = parser.parse_args(["stability", "--quiet", "--cases", "tiny", "--h", str(H),
                              "--out", str(out)])
    assert stability.main(args) == 0
    rows = list(csv.DictReader(open(out / "stability.csv")))
    assert tuple(rows[0]) == stability.COLUMNS
    assert [r["method"] for r in rows] == [stability.method_name(*m) for m in stability.METHODS]
    assert all(r["converged"] == "True" for r in rows)
    text = (out / "stability.md").read_text()
    assert f"{len(rows)} of {len(rows)} runs converged" in text
    import membranes
    assert f"\nSoftware: membranes {membranes.__version__}, python " in text
    assert sorted(p.name for p in out.iterdir()) == ["stability.csv", "stability.md"]
    for bad in (["--cases", "nonsense"], ["--h", "-1"]):
        args = parser.parse_args(["stability", "--quiet", "--out", str(tmp_path / "no")] + bad)
        with pytest.raises(ValueError):
            stability.main(args)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stab"]


def test_a_size_beyond_memory_is_refused_before_any_run(tmp_path, monkeypatch):
    """A case whose disk mesh would not fit in memory (here the nested one: T_2 of T_0 at 2h,
    about 1e11 vertices) is refused before any case runs: the cases before it ran first, for
    hours at a large h, before its scene refused it."""
    def never(*args, **kwargs):
        raise AssertionError("a case was run")
    monkeypatch.setattr(stability, "run_case", never)
    with pytest.raises(ValueError, match="vertices"):
        stability.write_stability(str(tmp_path / "out"), 1e-5, ["tiny", "nested_grazing"])
    assert list(tmp_path.iterdir()) == []


def test_a_folder_named_as_an_output_is_refused_before_any_run(tmp_path, monkeypatch):
    """A folder stability.md in --out: the outputs could not move in; refused after every
    case had run (a probe's, 2026-12-03), now before any, the folder left as it was."""
    def never(*args, **kwargs):
        raise AssertionError("a case was run")
    monkeypatch.setattr(stability, "run_case", never)
    (tmp_path / "out" / "stability.md").mkdir(parents=True)
    args = argparse.Namespace(out=str(tmp_path / "out"), h=0.3, cases="tiny", quiet=True)
    with pytest.raises(ValueError, match="holds a folder named stability.md"):
        stability.main(args)
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["stability.md"]


def test_markdown_names_the_parallel_paper_preconditioner():
    """Under mpirun the paper preset is block-Jacobi ILU(0) (docs/cli.md), and the page says so."""
    row = dict.fromkeys(stability.COLUMNS)
    row.update(case="tiny", method="min/exact/paper", converged=True, klass="mesh",
               description="d", **{"class": "mesh"})
    assert "paper: GMRES + ILU(0)" in stability.markdown([row], 0.1, 1.0, 1)
    assert "paper: GMRES + block-Jacobi ILU(0)" in stability.markdown([row], 0.1, 1.0, 2)
    # and the amg counts (BoomerAMG), which differ by a few steps too
    assert "BoomerAMG's coarsening" not in stability.markdown([row], 0.1, 1.0, 1)
    assert report.PARALLEL_COUNTS in stability.markdown([row], 0.1, 1.0, 2)


def test_a_size_beyond_a_methods_memory_is_refused_before_any_run(tmp_path, monkeypatch):
    """With memory for the iterative solvers' runs (BASE + 10 kB per vertex with the
    estimators, model.checks) but not for MUMPS's (c N^p beside them), a selection with a
    direct method is refused before any run, one without it is not. The check used to be
    the scenes' (the leanest method): every case ran, and each direct run was a failed row
    ("ValueError: ... needs ... of memory"), exit 3."""
    from membranes.model import checks
    def never(*args, **kwargs):
        raise AssertionError("a case was run")
    monkeypatch.setattr(stability, "run_case", never)
    h = 0.004                             # about 2.3e5 vertices: never meshed here
    vertices, _ = checks.estimate_vertices(h, 0, "disk")
    iterative = checks.estimate_memory(vertices, linear_solver="gmres", pc_type="vertex_amg")
    direct = checks.estimate_memory(vertices, linear_solver="direct")
    assert direct > 1.5 * iterative
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: iterative * 1.001)
    with pytest.raises(ValueError, match="needs .* of memory"):
        stability.write_stability(str(tmp_path / "out"), h, ["mu_ratio_1"])
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(AssertionError, match="a case was run"):
        stability.write_stability(str(tmp_path / "out"), h, ["mu_ratio_1"],
                                  methods=[m for m in stability.METHODS if m[2] != "direct"])


def test_same_counts_needs_both_counts_equal():
    """same_counts: Newton and Krylov steps both equal to those of the unscaled run. The
    scaled run of a real matrix with one count changed by one step (integers: exact)."""
    from dataclasses import replace
    _, runs = matrix(("scaled_1e-08", "grazing"))
    case = next(c for c in stability.select(["scaled_1e-08"]) if c.name == "scaled_1e-08")
    m = stability.method_name(*METHODS[1])
    sol, ref = runs["scaled_1e-08"][m], runs["mu_ratio_1"][m]
    for newton, linear, same in ((0, 0, True), (0, 1, False), (1, 0, False)):
        changed = replace(sol, newton_iterations=sol.newton_iterations + newton,
                          linear_iterations=sol.linear_iterations + linear)
        row = stability.table([case], {case.name: {m: changed}, "mu_ratio_1": {m: ref}})[0]
        assert row["same_counts"] is same, (newton, linear)


def test_a_non_finite_value_makes_a_failed_row():
    """A run whose history holds a NaN is not converged in the matrix, whatever the driver
    said (stability.finite), with that reason; the same run unchanged is converged."""
    from dataclasses import replace
    _, runs = matrix(("tiny", "far_guess"))
    case = stability.select(["tiny"])[0]
    m = stability.method_name(*METHODS[0])
    sol = runs["tiny"][m]
    history = [dict(r) for r in sol.history]
    history[-1]["residual"] = float("nan")
    bad = replace(sol, history=history)
    good_row, bad_row = (stability.table([case], {"tiny": {m: s}})[0] for s in (sol, bad))
    assert good_row["converged"] is True
    assert bad_row["converged"] is False
    assert bad_row["reason"] == "non-finite value in the output"


def test_cases_run_from_their_own_guess_and_mesh():
    """run_case hands a case's initial guess to every method (far_guess: a function of the
    discretisation, recorded as 'given'; the default for the others), and a nested case
    solves on the hierarchy of T_0 at size 2h: the same cell count as the case built here at
    2h with its levels (gmsh is deterministic: exact). h = 0.15, one direct method: at
    H = 0.3 gmsh makes the same coarsest disk at h and 2h (117 cells), which hid a run at h;
    at 0.15 and 0.3 T_2 has 5440 and 1872 cells."""
    _, runs = matrix(("tiny", "far_guess"))
    assert all(sol.options["initial_guess"] == "given" for sol in runs["far_guess"].values())
    assert all(sol.options["initial_guess"] is None for sol in runs["tiny"].values())
    case = stability.select(["nested_near_total"])[0]
    h = 0.15
    expected = case.build(2 * h, case.levels).mesh.topology.index_map(2).size_global
    assert expected != case.build(h, 0).mesh.topology.index_map(2).size_global * 16
    sol = stability.run_case(case, h, [("min", "exact", "direct")])["min/exact/direct"]
    assert sol.converged
    assert sol.disc.mesh.topology.index_map(2).size_global == expected
    assert len(sol.per_level) == case.levels + 1


def test_bound_and_effectivity_lines_of_the_markdown():
    """stability.md's bound section lists every run with η < error, failed ones included
    (the bound holds at any iterate, §7), and gives per case the smallest and then the
    largest effectivity of the converged runs. Made-up rows; exact."""
    rows = [{"case": "a", "class": "c", "method": f"m{k}", "converged": ok,
             "effectivity": eff, "reason": "r", "description": "d"}
            for k, (ok, eff) in enumerate(((False, 0.5), (True, 2.5), (True, 1.5)))]
    f = stability.findings(rows)
    assert [r["method"] for r in f["below_one"]] == ["m0"]
    text = stability.markdown(rows, 0.1, 1.0, 1)
    assert "η < error in: a m0 (0.500)" in text
    assert "over the converged runs): a 1.5 – 2.5." in text


def test_not_robust_above_an_effectivity_of_three():
    """stability.md lists as not robust the cases whose effectivity exceeds 3 in a converged
    run (docs/theory.md: 'the stability matrix lists the cases whose effectivity exceeds 3
    as not robust'); a failed run's effectivity does not count, and an effectivity of 1
    exactly (η = error) is a bound, not below one. Made-up rows; exact."""
    rows = [{"case": c, "class": "k", "method": "m", "converged": ok, "effectivity": eff,
             "reason": "r", "description": "d"}
            for c, ok, eff in (("a", True, 2.9), ("b", True, 3.5), ("c", False, 5.0),
                               ("d", True, 1.0))]
    f = stability.findings(rows)
    assert [r["case"] for r in f["not_robust"]] == ["b"] and f["below_one"] == []
    text = stability.markdown(rows, 0.1, 1.0, 1)
    assert "Not robust (effectivity above 3): b." in text
    assert "η ≥ |||u - u_h||| in all 4 runs where both are known" in text


def test_the_command_exits_3_when_a_run_fails(tmp_path, monkeypatch, capsys):
    """`membranes stability` returns EXIT_NOT_CONVERGED (3) when a run failed, with its files
    written (the docstring: 'the files are written in any case, with the reasons') and its
    one stdout line (docs/cli.md: 'stability: C of R runs converged; path of stability.md'); the
    names of --cases are read with the blanks after the commas left out. run_case is
    replaced by one whose every run raises: no solve here."""
    from membranes.app.cli import EXIT_NOT_CONVERGED
    ran = []

    def failing(case, h, methods, say):
        ran.append(case.name)
        return {stability.method_name(*m): RuntimeError("planted") for m in methods}
    monkeypatch.setattr(stability, "run_case", failing)
    parser = argparse.ArgumentParser()
    stability.add_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "stab"
    args = parser.parse_args(["stability", "--quiet", "--cases", "tiny, grazing", "--h",
                              str(H), "--out", str(out)])
    assert stability.main(args) == EXIT_NOT_CONVERGED
    assert capsys.readouterr().out == (f"stability: 0 of {2 * len(stability.METHODS)} runs "
                                       f"converged; {out / 'stability.md'}\n")
    assert ran == ["grazing", "tiny"]                         # (in the order of CASES)
    rows = list(csv.DictReader(open(out / "stability.csv")))
    assert len(rows) == 2 * len(stability.METHODS)
    assert all(r["converged"] == "False" and r["reason"] == "RuntimeError: planted"
               for r in rows)
    assert f"0 of {len(rows)} runs converged" in (out / "stability.md").read_text()


def test_the_cases_hold_the_designs_extremes():
    """The matrix covers the ranges of DESIGN.md §11 at their ends: μ1/μ2 = 1e-6 … 1e6 (μ2 =
    1), g = 1e-12 … 1e3, data scaled by 1e-8 and 1e8 (g = 0.05 s: the radial loads are
    proportional to g), near-total contact at ρ = 0.95 (its level set vanishes there).
    The numbers are the specification's; the scenes are built at a coarse h."""
    case = {c.name: c for c in stability.CASES}
    h = 0.5
    for r in (1e-6, 1e-3, 1.0, 1e3, 1e6):
        p = case[f"mu_ratio_{r:g}"].build(h)
        assert (p.mu1, p.mu2, p.g) == (r, 1.0, 0.05)
    for g in (1e-12, 1e-6, 1e3):
        assert case[f"g_{g:g}"].build(h).g == g
    for s in (1e-8, 1e8):
        scaled = case[f"scaled_{s:g}"]
        assert (scaled.scaled_from, scaled.factor) == ("mu_ratio_1", s)
        assert scaled.build(h).g == 0.05 * s
    near = case["near_total"].build(h)
    assert abs(near.interface(np.array([[0.95], [0.0]]))[0]) <= 1e-15


def test_the_far_off_guess_violates_every_constraint():
    """far_off_guess: u1 - u2 = -2e3 u_data < 0 (the gap constraint) and λ = -1e3 max(λ_data,
    1) < 0 at every vertex, three orders of magnitude beyond the data's sizes (exact
    multiples of u_data and λ_data)."""
    from membranes.fem.discretisation import discretise
    disc = discretise(stability.select(["far_guess"])[0].build(H))
    u_data, lam_data = disc.data_scales()
    X = stability.far_off_guess(disc)
    u1, u2, lam = (np.asarray(a) for a in disc.split(X))
    assert np.all(u1 == -1e3 * u_data) and np.all(u2 == 1e3 * u_data)
    assert np.all(u1 - u2 < 0) and np.all(lam == -1e3 * max(lam_data, 1.0))


def test_sizes_are_checked_at_the_size_each_case_is_meshed(monkeypatch):
    """check_sizes checks a nested case's T_0 … T_2 at size 2h (as run_case builds it) and a
    single mesh at h, the structured square meshes (no gmsh size) not at all: checked at h,
    the nested hierarchy was estimated 16 times larger and refused at sizes that fit."""
    seen = []
    monkeypatch.setattr(report, "check_memory",
                        lambda h, levels, domain, comm, solvers: seen.append((h, levels)))
    stability.check_sizes(stability.select(["tiny", "grazing", "nested_grazing"]), 0.2,
                          MPI.COMM_WORLD)
    assert seen == [(0.2, 0), (0.4, 2)]


def test_scale_defect_of_a_component_zero_in_the_reference():
    """Where a component is identically 0 in the unscaled run, the defect is the scaled
    run's size of it, ‖X_s/s‖∞ (relative to nothing): a λ that appears only under scaling
    shows. Planted on a real run (λ of the reference set to 0, s = 1); exact. A component
    0 in both adds nothing (s = 2: u1, u2 give |X/2 - X|/|X| = 1/2, exact in binary)."""
    _, runs = matrix(("tiny", "far_guess"))
    sol = runs["tiny"]["min/exact/direct"]
    X = sol.X.copy()
    ref = type(sol)(**{**sol.__dict__, "X": X})
    lam_ref = sol.disc.split(X)[2]
    lam_ref[:] = 0.0
    lam = np.asarray(sol.disc.split(sol.X)[2])
    assert np.abs(lam).max() > 0
    assert stability.scale_defect(sol, ref, 1.0) == np.abs(lam).max()   # (u1, u2: 0)
    assert stability.scale_defect(ref, ref, 2.0) == 0.5      # |X/2 - X|/|X|, λ = 0 in both


def test_a_non_finite_iterate_makes_a_failed_row():
    """A NaN in the final iterate (not only in the history) makes the run a failed row with
    that reason (stability.finite: 'no NaN or infinity in the iterate nor in any recorded
    number'); planted in a real run's copy."""
    from dataclasses import replace
    _, runs = matrix(("tiny", "far_guess"))
    case = stability.select(["tiny"])[0]
    m = stability.method_name(*METHODS[0])
    sol = runs["tiny"][m]
    X = sol.X.copy()
    X.array[0] = np.inf
    row = stability.table([case], {"tiny": {m: replace(sol, X=X)}})[0]
    assert row["converged"] is False and row["reason"] == "non-finite value in the output"


def test_iterative_runs_are_capped_at_max_linear_its():
    """Every Krylov run of the matrix is allowed MAX_LINEAR_ITS = 2000 iterations a Newton
    step (docs/cli.md: 'at most 2000 Krylov iterations a Newton step'), not the solver's
    default of 10000; a direct run has no such limit."""
    _, runs = matrix(("tiny", "far_guess"))
    assert stability.MAX_LINEAR_ITS == 2000
    for method in METHODS:
        name = stability.method_name(*method)
        limit = runs["tiny"][name].options["max_linear_its"]
        assert limit == (None if method[2] == "direct" else 2000), name


def test_the_command_needs_out(capsys):
    """`membranes stability` without --out is bad input (docs/cli.md: --out required): exit
    2, one line naming the option, before any run."""
    from membranes.app import cli
    assert cli.main(["stability", "--quiet", "--cases", "tiny"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert err == "membranes: error: the following arguments are required: --out\n"


def test_scale_invariance_line_gives_the_largest_defect():
    """stability.md's scale-invariance section gives the largest defect over the scaled runs
    and how many kept both counts (made-up rows; exact)."""
    rows = [{"case": "s", "class": "scaling", "method": f"m{k}", "converged": True,
             "effectivity": None, "reason": "r", "description": "d", "scale_defect": d,
             "same_counts": same}
            for k, (d, same) in enumerate(((1e-14, True), (3e-12, False), (None, None)))]
    text = stability.markdown(rows, 0.1, 1.0, 1)
    assert "Largest defect 3.0e-12; iteration counts equal in 1 of 2 scaled runs." in text
