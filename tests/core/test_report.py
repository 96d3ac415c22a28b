"""The report (membranes.app.report) on a tiny disk: every method and both peers in one table,
the numbers are the runs' own, the peers solve the same discrete problem, the certificate of
the nested peer bounds its error, the pictures are real renderings and the CSVs are the data
behind them."""

import argparse
import csv
import os
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI

from membranes.app import report
from membranes.app.report import CURVE_COLUMNS, METHOD_NAMES, PEERS, TABLE_COLUMNS, write_report
from membranes.model import scenes
from tests.blocked import blocking_folder, with_folder_first

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="reads the files serially")

PICTURES = ["error_vs_time.png", "error_distribution.png", "contact.png"] + \
    [f"estimators_{report._slug(m)}.png" for m in METHOD_NAMES]


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "disk"
    problem = scenes.disk(h=0.3, levels=1)
    runs, rows = write_report(problem, str(out))
    return problem, out, runs, {r["method"]: r for r in rows}


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def _column(rows, name):
    return np.array([float(r[name]) for r in rows])


def test_every_file_and_nothing_else(made):
    _, out, _, _ = made
    expected = {"table.csv", "report.md", "error_vs_time.csv", "error_distribution.csv",
                "contact.csv"} | set(PICTURES) | \
        {f"estimators_{report._slug(m)}.csv" for m in METHOD_NAMES}
    assert set(os.listdir(out)) == expected
    assert [p.name for p in out.parent.iterdir()] == ["disk"]
    # the names `main` checks before the runs are those written
    assert sorted(report.output_names()) == sorted(expected)


@pytest.mark.parametrize("name", PICTURES)
def test_pictures_are_real_renderings(made, name):
    import matplotlib.image as mpimg
    _, out, _, _ = made
    path = out / name
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    pixels = mpimg.imread(str(path))[..., :3]
    assert pixels.shape[0] > 300 and pixels.shape[1] > 500
    assert pixels.std() > 0.02                                   # not a flat image
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50    # more than a few colours


def test_table_has_every_method_and_the_peers(made):
    _, out, runs, table = made
    rows = {r["method"]: r for r in _rows(out / "table.csv")}
    assert list(rows) == list(METHOD_NAMES) + list(PEERS)
    assert all(r["converged"] == "True" for r in rows.values())
    for method, sol in runs.items():
        s = sol.summary()
        assert int(rows[method]["newton_iterations"]) == s["newton_iterations"]
        assert int(rows[method]["linear_iterations"]) == s["linear_iterations"]
        for key in ("energy_error", "wall_time_s", "eta", "effectivity"):
            assert float(rows[method][key]) == s[key], (method, key)
        # the solver asked for, nested or not as the method says
        assert (s["solver"], s["nested"]) == \
            (method.split("/")[1], method.endswith("amg"))
    text = (out / "report.md").read_text()
    for name in PICTURES:
        assert f"]({name})" in text
    for method in rows:
        line = next(li for li in text.splitlines() if li.startswith(f"| {method} |"))
        cells = [c.strip() for c in line.strip("|").split("|")]
        for key in ("newton_iterations", "linear_iterations"):
            assert cells[TABLE_COLUMNS.index(key)] == rows[method][key]
    assert "## The paper's table" in text and "replay (same counts as the run)" in text
    # the software that made the numbers, as summary.json names it
    import dolfinx

    import membranes
    software = next(li for li in text.splitlines() if li.startswith("Software: "))
    assert software.startswith(f"Software: membranes {membranes.__version__}, python ")
    assert f", dolfinx {dolfinx.__version__}, " in software and ", PETSc 3." in software


def test_peers_solve_the_same_discrete_problem(made):
    """The SNES VI peers (rtol 1e-8) reach the discrete solution the exact Newton runs reach
    (2e-12): the same energy error to far below the discretisation error, 1e-8 relative; the
    certificate of the nested peer is η of that same iterate: a bound, the effectivity of
    exact Newton to the same precision, and it costs time on top of the peer's."""
    _, _, runs, table = made
    exact = runs["exact/paper"]
    for peer in PEERS:
        assert table[peer]["energy_error"] == pytest.approx(exact.energy_error, rel=1e-8)
        assert table[peer]["newton_iterations"] >= 1
        assert table[peer]["linear_iterations"] > table[peer]["newton_iterations"]
    cert, nested = table["certified nested peer"], table["nested peer"]
    assert cert["eta"] >= cert["energy_error"] and cert["bound_guaranteed"]
    assert cert["eta"] == pytest.approx(exact.estimates["eta"], rel=1e-6)
    assert cert["wall_time_s"] == pytest.approx(nested["wall_time_s"] + cert["certificate_s"],
                                                rel=1e-12)
    assert cert["eta_rem"] < 1e-4 * cert["eta"]        # the peer's residual is small
    assert nested["newton_per_level"].count("+") == 1     # two levels


def test_error_curves_are_the_histories(made):
    _, out, runs, table = made
    curves = _rows(out / "error_vs_time.csv")
    assert tuple(curves[0]) == CURVE_COLUMNS
    for method, sol in runs.items():
        mine = [r for r in curves if r["method"] == method]
        steps = [r for r in sol.history if r["kind"] != "krylov"]
        assert len(mine) == len(steps)
        assert np.array_equal(_column(mine, "wall_time_s"), [r["wall_time_s"] for r in steps])
        # errors='iterates': the energy error of every Newton iterate, decreasing to the end
        errors = _column(mine, "energy_error")
        assert np.array_equal(errors, [r["energy_error"] for r in steps])
        assert errors[-1] == sol.energy_error and errors[0] > 2 * errors[-1]
    for peer in ("nested peer", "plain peer"):
        mine = [r for r in curves if r["method"] == peer]
        t = _column(mine, "wall_time_s")
        assert np.all(np.diff(t) >= 0) and t[-1] <= table[peer]["wall_time_s"]
        assert _column(mine, "energy_error")[-1] == table[peer]["energy_error"]
    assert [r["level"] for r in curves if r["method"] == "plain peer"] == \
        ["1"] * (table["plain peer"]["newton_iterations"] + 1)
    cert = [r for r in curves if r["method"] == "certified nested peer"]
    assert len(cert) == 1 and float(cert[0]["eta"]) == table["certified nested peer"]["eta"]
    # the certified iterate is the nested peer's last on T_J: its step on that level
    last = [r for r in curves if r["method"] == "nested peer"][-1]
    assert (cert[0]["level"], cert[0]["newton_it"]) == (last["level"], last["newton_it"])


@pytest.mark.parametrize("method", METHOD_NAMES)
def test_estimator_curves(made, method):
    """Adaptive runs: the run's own history. Exact and inexact: the run's Newton records with
    the replay's estimators, which end at the run's certificate (the same iterate) and bound
    the error at every Newton iterate (X⁰ included: its residual is handed over)."""
    _, out, runs, _ = made
    sol = runs[method]
    rows = _rows(out / f"estimators_{report._slug(method)}.csv")
    if method.startswith("adaptive"):
        assert len(rows) == len(sol.history)
    else:
        assert len(rows) == sol.newton_iterations + (2 if method.endswith("amg") else 1)
        assert float(rows[-1]["eta"]) == pytest.approx(sol.estimates["eta"], rel=1e-9)
    with_both = [r for r in rows if r["eta"] and r["energy_error"]]
    # adaptive runs estimate T_J only (coarse='residual'), where the Newton gate lets them
    # (schedule.LevelEstimates: the certified rows); the others are replayed in full
    J = sol.final_record["level"]
    certified = sum(1 for r in sol.history if r["level"] == J and r["kind"] == "newton"
                    and r["bound"])
    assert sol.final_record["bound"]
    assert len(with_both) >= (certified if method.startswith("adaptive")
                              else sol.newton_iterations)
    assert all(float(r["eta"]) >= float(r["energy_error"]) for r in with_both)


def test_snapshot_data(made):
    _, out, runs, _ = made
    sol = runs["adaptive/amg"]
    cells = _rows(out / "error_distribution.csv")
    error_K = _column(cells, "error_K")
    # the cell errors add up to the energy error; η_K is the run's
    assert np.sqrt((error_K ** 2).sum()) == pytest.approx(sol.energy_error, rel=1e-12)
    assert np.array_equal(_column(cells, "eta_K"), sol.eta_K)
    vertices = _rows(out / "contact.csv")
    u1, u2, lam = sol.disc.split(sol.X)
    assert np.array_equal(_column(vertices, "gap"), u1 - u2)
    assert np.array_equal(_column(vertices, "lambda"), lam)


def test_cli_refuses_an_unwritable_folder_first(tmp_path):
    """Bad --out is refused before any mesh or run; the parser has the old options."""
    parser = argparse.ArgumentParser()
    report.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["report", "--out", "/proc/report", "--h", "0.3", "--levels",
                              "1", "--quiet"])
    assert (args.scene, args.h, args.levels) == ("disk", 0.3, 1)
    with pytest.raises(ValueError, match="cannot be written"):
        report.main(args)
    existing = tmp_path / "file"
    existing.write_text("mine\n")
    args = parser.parse_args(["report", "--out", str(existing), "--quiet"])
    with pytest.raises(ValueError, match="not a folder"):
        report.main(args)
    assert existing.read_text() == "mine\n"
    assert [p.name for p in tmp_path.iterdir()] == ["file"]
    # a folder named as an output: refused before the runs (after them, 7 s at h = 0.3,
    # before the check; a probe's, 2026-12-03), and left as it was
    (tmp_path / "out" / "contact.png").mkdir(parents=True)
    args = parser.parse_args(["report", "--out", str(tmp_path / "out"), "--quiet"])
    with pytest.raises(ValueError, match="holds a folder named contact.png"):
        report.main(args)
    assert os.listdir(tmp_path / "out") == ["contact.png"]


def test_runs_that_do_not_converge_are_reported(tmp_path, monkeypatch):
    """A method that does not converge is a row with its reason, and the report is written
    all the same (docs/cli.md: exit 3), also where adaptive/amg ended on a coarse level,
    before its certificate: error_distribution has no η_K then."""
    monkeypatch.setattr(report, "MAX_NEWTON", {"exact": 1, "inexact": 1, "adaptive": 1})
    out = tmp_path / "disk"
    runs, rows = write_report(scenes.disk(h=0.4, levels=1), str(out))
    assert not any(r["converged"] for r in rows if r["method"] in METHOD_NAMES)
    assert runs["adaptive/amg"].eta_K is None
    assert {r["eta_K"] for r in _rows(out / "error_distribution.csv")} == {""}
    text = (out / "report.md").read_text()
    assert "adaptive/amg: not converged: no convergence in 1 Newton steps" in text
    assert "no η_K: the run ended before its certificate" in text
    assert "nan" not in text
    # every run that reached T_J certifies the iterate it returns (η ≥ error)
    for m in ("exact/paper", "inexact/paper", "adaptive/paper"):
        row = next(r for r in rows if r["method"] == m)
        assert row["bound_guaranteed"] and row["eta"] >= row["energy_error"], m


def test_log_picture_beside_a_panel_without_values(tmp_path):
    """error_distribution of a run that ended before its certificate has no η_K (NaN cells,
    test above): the actual errors beside it are still drawn on their own logarithmic range.
    Two cells, 1e-3 on the lower left and 1e-1 on the upper right half of the unit square,
    flat-shaded: the left panel shows two colours over half of the square each, the lower
    one the darker (viridis runs from dark to light); a colour range ending at NaN drew both
    cells in one colour."""
    import matplotlib.image as mpimg

    from membranes.app import render
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]],
                      dtype=float)
    npz, png = str(tmp_path / "cells.npz"), str(tmp_path / "cells.png")
    np.savez(npz, cells=np.array([3, 0, 1, 2, 3, 3, 4, 5]),
             types=np.full(2, render.VTK_TRIANGLE, dtype=np.uint8), points=points,
             names=np.array(["error_K", "eta_K"]), kinds=np.array(["cell", "cell"]),
             titles=np.array(["", ""]), cmap=np.array("viridis"), log=np.array(True),
             field_0=np.array([1e-3, 1e-1]), field_1=np.full(2, np.nan))
    done = subprocess.run([sys.executable, render.__file__, npz, png], capture_output=True,
                          text=True, timeout=render.RENDER_SECONDS)
    assert done.returncode == 0, done.stderr[-2000:]
    left = np.round(255 * mpimg.imread(png)[:, :700, :3]).astype(int)  # (rows, 700, 3)
    colours, counts = np.unique(left.reshape(-1, 3), axis=0, return_counts=True)
    cells = [c for c, n in zip(colours, counts) if n > 0.1 * left.shape[0] * 700
             and not (c == 255).all()]                                 # not the background
    assert len(cells) == 2
    counts = [np.count_nonzero((left == c).all(axis=2)) for c in cells]
    assert counts[0] == pytest.approx(counts[1], rel=0.02)             # half a square each
    rows, cols = np.nonzero(np.any([(left == c).all(axis=2) for c in cells], axis=0))
    r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()     # the square
    lower = left[r1 - (r1 - r0) // 3, c0 + (c1 - c0) // 3]              # the cells' centroids
    upper = left[r0 + (r1 - r0) // 3, c1 - (c1 - c0) // 3]
    assert lower.sum() < upper.sum()


def test_markdown_names_the_parallel_paper_preconditioner(made):
    """Under mpirun the paper preset is block-Jacobi ILU(0) (docs/cli.md): report.md says so
    beside the paper's counts, and a serial report says ILU(0) alone. BoomerAMG's coarsening
    and smoothing depend on the partition too: the amg runs' and the peers' counts differ by
    a few steps (disk h 0.4, levels 1: exact/amg 36 Krylov steps serial, 38 on 2 and 3
    processes), which report.md used to leave unsaid."""
    problem, _, runs, table = made
    summaries = {m: runs[m].summary() for m in METHOD_NAMES}
    cells = (np.ones(3), np.ones(3))
    sources = {m: "run" for m in METHOD_NAMES}
    serial = report.markdown(problem, runs, summaries, list(table.values()), cells, sources, 1.0)
    assert "block-Jacobi" not in serial
    two = {m: dict(s, processes=2) for m, s in summaries.items()}
    parallel = report.markdown(problem, runs, two, list(table.values()), cells, sources, 1.0)
    assert "on 2 processes block-Jacobi ILU(0)" in parallel
    # BoomerAMG is not the serial one either (its counts differ by a few steps, measured)
    assert report.PARALLEL_COUNTS in parallel and "BoomerAMG's coarsening" not in serial
    square = replace(problem, name="square")
    assert "its problem is the disk, not the square scene" in \
        report.markdown(square, runs, summaries, list(table.values()), cells, sources, 1.0)


def test_cli_json_line_has_the_table_columns(tmp_path, monkeypatch, capsys):
    """stdout's table: the rows of table.csv with each run's reason (docs/cli.md), not the
    internal extras of a row (the certified peer's eta_rem and certificate_s)."""
    rows = [{"method": "certified nested peer", "converged": True, "eta": 0.1,
             "reason": "CONVERGED", "eta_rem": 1e-9, "certificate_s": 0.2}]
    monkeypatch.setattr(report, "write_report", lambda problem, out, say: (None, rows))
    parser = argparse.ArgumentParser()
    report.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["report", "--out", str(tmp_path / "r"), "--h", "0.5",
                              "--levels", "0", "--quiet"])
    assert report.main(args) == 0
    import json
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert list(line["table"][0]) == list(TABLE_COLUMNS) + ["reason"]


def test_a_report_without_pyvista(tmp_path, monkeypatch):
    """When pyvista cannot draw (here: not importable in the rendering process), the report
    is written without the two pyvista pictures, says why in report.md and on the progress
    lines, and leaves no half-drawn picture or data file (docs/outputs.md); it used to end in
    a traceback after every run, nothing written. Written over an older report, it leaves no
    picture of that report beside its own CSVs (they used to stay), and the user's files
    alone."""
    monkeypatch.setenv("PYTHONPATH", with_folder_first(blocking_folder(tmp_path, "pyvista")))
    out, said = tmp_path / "square", []
    out.mkdir()
    for name in ("error_distribution.png", "contact.png", "notes.txt"):
        (out / name).write_text("an older report's\n")
    write_report(scenes.square(h=0.5, levels=1), str(out), said.append)
    names = set(os.listdir(out))
    assert "error_distribution.png" not in names and "contact.png" not in names
    assert (out / "notes.txt").read_text() == "an older report's\n"
    assert {"error_distribution.csv", "contact.csv", "report.md", "error_vs_time.png"} <= names
    assert not any(n.endswith(".npz") for n in names)
    text = (out / "report.md").read_text()
    for name in ("error_distribution.png", "contact.png"):
        assert f"*No picture: rendering {name} failed: ImportError: no pyvista here.*" in text
        assert f"]({name})" not in text
    assert sum("warning: rendering" in line for line in said) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["block", "square"]


def test_a_report_without_matplotlib(tmp_path, monkeypatch):
    """matplotlib is no dependency of the package (a plain `pip install` lacks it): the
    report is refused before any run, one line naming it and exit 2 from the command,
    ValueError from write_report, nothing written. It used to run every method and then end in
    a ModuleNotFoundError traceback."""
    env = dict(os.environ,
               PYTHONPATH=with_folder_first(blocking_folder(tmp_path, "matplotlib")))
    out = tmp_path / "disk"
    proc = subprocess.run([sys.executable, "-m", "membranes.app.cli", "report", "--h", "0.5",
                           "--levels", "1", "--out", str(out)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-3000:]
    err = proc.stderr.strip()
    assert err.startswith("membranes: error: ") and "\n" not in err, err
    assert "matplotlib" in err and "no matplotlib here" in err and proc.stdout == ""
    for name in ("matplotlib", "matplotlib.figure"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(ValueError, match="matplotlib"):
        write_report(scenes.disk(h=0.5, levels=1), str(out))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["block"]


def test_a_size_beyond_the_reports_memory_is_refused_before_meshing(tmp_path, monkeypatch):
    """The report runs the amg and paper solvers with the ν flux's estimators, each needing
    BASE + 10 kB per vertex (model.checks), where the scene checks the leanest method, 2.5 kB
    per vertex: with memory for the leanest but not for the report's runs, the size is
    refused before the mesh is built, nothing written. It used to be meshed and then refused
    by the first run's own check. With memory for the heaviest run it goes on to mesh."""
    from membranes.model import checks
    h, levels = 0.05, 4                   # about 4e5 vertices: never meshed here
    vertices, _ = checks.estimate_vertices(h, levels, "disk")
    lean = checks.estimate_memory(vertices, linear_solver=None)
    runs = checks.estimate_memory(vertices, linear_solver="gmres", pc_type="vertex_amg")
    assert runs > lean * 1.5
    meshed = []

    def make(*args, **kwargs):
        meshed.append(args)
        raise AssertionError("meshed")
    monkeypatch.setattr(scenes, "make", make)
    parser = argparse.ArgumentParser()
    report.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["report", "--out", str(tmp_path / "r"), "--h", str(h),
                              "--levels", str(levels), "--quiet"])
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: (lean + runs) / 2)
    with pytest.raises(ValueError, match="needs .* of memory"):
        report.main(args)
    assert meshed == [] and list(tmp_path.iterdir()) == []
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: runs * 1.001)
    with pytest.raises(AssertionError, match="meshed"):
        report.main(args)


def test_replays_leave_no_petsc_objects():
    """A replay (estimator_rows of an exact or inexact run) frees the PETSc objects it made,
    as `solve` does (membranes.app.garbage): they were parked until the end of the process,
    one replay's discretisation, Krylov solver and estimator set-up after another, about 175
    bytes per vertex each on the disk."""
    from petsc4py import PETSc

    from membranes.app.driver import solve
    from tests.test_memory_release import live_petsc_objects
    PETSc.Log.begin()
    problem = scenes.disk(h=0.3, levels=1)
    sol = solve(problem, newton="exact", solver="paper", nested=False)
    live = []
    for _ in range(3):
        rows, source = report.estimator_rows(problem, sol)
        assert source == "replay (same counts as the run)"
        live.append(live_petsc_objects())
    assert live[0] and live[1] == live[0] and live[2] == live[0], live


def _markdown_cells(text, method):
    """{heading: cell} of `method`'s line in report.md's table of steps, time and error."""
    lines = text.splitlines()
    head = next(li for li in lines if li.startswith("| method | converged |"))
    row = next(li for li in lines if li.startswith(f"| {method} |"))
    return dict(zip([c.strip() for c in head.strip("|").split("|")],
                    [c.strip() for c in row.strip("|").split("|")]))


def test_table_headings_name_their_cells_and_per_level_counts(made):
    """report.md: each heading stands over its own number (η, η / error, the counts), and
    the certified peer's effectivity is η / error (§7: ≥ 1 for a bound), recomputed here
    from its η and error (one division: exact); `per level` is each level's Newton steps,
    counted independently from the run's history (Newton rows per level), and the parts
    add up to the total. A swapped heading, error / η, or Krylov steps per level passed the
    tests that read table.csv only."""
    _, out, runs, table = made
    text = (out / "report.md").read_text()
    csv_rows = {r["method"]: r for r in _rows(out / "table.csv")}
    cert = table["certified nested peer"]
    assert cert["effectivity"] == cert["eta"] / cert["energy_error"] >= 1.0
    assert float(csv_rows["certified nested peer"]["effectivity"]) == cert["effectivity"]
    for method in ("certified nested peer", "exact/paper", "adaptive/amg"):
        r = table[method]
        cells = _markdown_cells(text, method)
        assert cells["η"] == f"{r['eta']:.4g}", method
        assert cells["η / error"] == f"{r['eta'] / r['energy_error']:.4g}", method
        assert cells["energy error"] == f"{r['energy_error']:.4g}", method
        assert cells["Newton (SNES) steps"] == str(r["newton_iterations"]), method
        assert cells["Krylov (CG) steps"] == str(r["linear_iterations"]), method
    for method, sol in runs.items():
        levels = sorted({r["level"] for r in sol.history})
        counts = [sum(1 for r in sol.history if r["level"] == j and r["kind"] == "newton")
                  for j in levels]
        assert csv_rows[method]["newton_per_level"] == "+".join(map(str, counts)), method
    for peer in PEERS:
        parts = csv_rows[peer]["newton_per_level"].split("+")
        assert sum(map(int, parts)) == int(csv_rows[peer]["newton_iterations"]), peer


def test_cell_sums_in_the_text_are_those_of_the_csv(made):
    """The error-distribution paragraph of report.md names the largest cell values and the
    root sums of squares of |||u - u_h|||_K and η_K: recomputed here from
    error_distribution.csv (Python's float repr reads back exactly; the same sums in the
    same order, and 4 digits printed)."""
    _, out, _, _ = made
    text = (out / "report.md").read_text()
    cells = _rows(out / "error_distribution.csv")
    a, e = _column(cells, "error_K"), _column(cells, "eta_K")
    assert f"Largest cell values {a.max():.3e} (actual), {e.max():.3e} (estimated)" in text
    assert f"root sums of squares {np.sqrt((a ** 2).sum()):.4e} and " \
           f"{np.sqrt((e ** 2).sum()):.4e}." in text


def test_paper_comparison_puts_each_count_beside_the_papers():
    """The paper's table: our paper-preset runs (not the amg ones) beside the paper's column
    nearest in elements, Newton beside Newton and GMRES beside GMRES. Made-up counts (the
    amg runs' differ) and 4000 cells: the column of 4064 elements (PAPER); exact."""
    from types import SimpleNamespace as NS
    runs = {}
    for n, v in enumerate(("exact", "inexact", "adaptive"), start=1):
        runs[f"{v}/paper"] = NS(newton_iterations=n, linear_iterations=10 * n)
        runs[f"{v}/amg"] = NS(newton_iterations=100 + n, linear_iterations=1000 + n)
    cells, theirs, lines = report.paper_comparison(runs, {"exact/paper": {"n_cells": 4000}})
    assert (cells, theirs) == (4000, 4064)
    assert lines[2:] == ["| exact | 1 | 12 | 10 | 585 |", "| inexact | 2 | 27 | 20 | 270 |",
                         "| adaptive | 3 | 11 | 30 | 120 |"]


def test_peer_curve_times_count_the_discretisation_of_each_level():
    """A peer's curve: an iterate's time is the discretisation and solver time of the levels
    before it, its own level's discretisation and its level's solver seconds so far (the
    scope of the table's wall time). Made-up seconds (binary fractions: exact sums)."""
    from types import SimpleNamespace as NS
    curve = report.PeerCurve()
    curve.points = [(0, 0, 0.0, 3.0), (0, 1, 0.5, 2.0), (1, 0, 0.0, 1.5), (1, 2, 0.25, 1.0)]
    result = NS(levels=[NS(setup_time_s=1.0, wall_time_s=2.0),
                        NS(setup_time_s=4.0, wall_time_s=8.0)])
    records = curve.records("nested peer", result)
    assert [r["wall_time_s"] for r in records] == [1.0, 1.5, 7.0, 7.25]
    assert [r["kind"] for r in records] == ["initial", "snes", "initial", "snes"]
    assert [r["energy_error"] for r in records] == [3.0, 2.0, 1.5, 1.0]
    assert [r["level"] for r in curve.records("plain peer", result, first_level=3)] == \
        [3, 3, 4, 4]


@pytest.mark.parametrize("method", [m for m in METHOD_NAMES if not m.startswith("adaptive")])
def test_replayed_rows_carry_every_estimator(made, method):
    """Exact and inexact runs estimate their final iterate only; their figure takes η and
    its parts η_disc, η_lin, η_alg from the replay at every Newton iterate (only η taken left
    the parts of the earlier rows empty). The last row is the run's certificate: the same
    iterate, the same parts to 1e-9 (test_estimator_curves)."""
    _, out, runs, _ = made
    rows = _rows(out / f"estimators_{report._slug(method)}.csv")
    assert len(rows) == runs[method].newton_iterations + (2 if method.endswith("amg") else 1)
    for r in rows:
        assert all(r[k] != "" for k in ("eta", "eta_disc", "eta_lin", "eta_alg")), r
    est = runs[method].estimates
    for k in ("eta_disc", "eta_lin"):
        assert float(rows[-1][k]) == pytest.approx(est[k], rel=1e-9), k


# a snapshot of one cell field on a 2 × 2 square, on every process of an mpirun: each
# process's outcome gathered on process 0, which prints them as one JSON line (argv: the
# folder put in front of PYTHONPATH for the rendering process, the picture's path)
SNAPSHOT_ON_EVERY_PROCESS = "\n".join([
    "import json, os, sys", "import numpy as np", "from dolfinx import fem, mesh",
    "from mpi4py import MPI", "from membranes.app.render import snapshot",
    "comm = MPI.COMM_WORLD",
    "square = mesh.create_unit_square(comm, 2, 2, ghost_mode=mesh.GhostMode.none)",
    "V = fem.FunctionSpace(square, ('Lagrange', 1))",
    "cells = np.ones(square.topology.index_map(2).size_local)",
    "os.environ['PYTHONPATH'] = os.pathsep.join([sys.argv[1], os.environ['PYTHONPATH']])",
    "try:",
    "    snapshot(V, [('c', 'cell', cells, '')], sys.argv[2])",
    "    said = 'drawn'",
    "except Exception as e:",
    "    said = f'{type(e).__name__}: {e}'",
    "said = comm.gather(said, root=0)",
    "if comm.rank == 0:",
    "    print(json.dumps(said), flush=True)"])


def test_a_rendering_that_fails_raises_on_every_process(tmp_path):
    """`snapshot` is collective and process 0 renders: where it fails (here pyvista not
    importable in the rendering process) every process raises the same RuntimeError, so
    that all of them go without the picture together (a caller such as the report goes on
    to its next collective step on every process), and no picture or data file is left."""
    import json

    from tests.conftest import mpirun
    picture = tmp_path / "out" / "c.png"
    picture.parent.mkdir()
    proc = mpirun(["-c", SNAPSHOT_ON_EVERY_PROCESS, blocking_folder(tmp_path, "pyvista"),
                   picture], processes=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    said = "RuntimeError: rendering c.png failed: ImportError: no pyvista here"
    assert json.loads(proc.stdout) == [said, said]
    assert not any(picture.parent.iterdir())


def rendering_exits_with_3(tmp_path, monkeypatch):
    """Python processes started from here on exit with code 3 at their end, as a rendering
    process whose GL driver crashes at exit does."""
    folder = tmp_path / "exit3"
    folder.mkdir()
    (folder / "sitecustomize.py").write_text(
        "import atexit, os\natexit.register(lambda: os._exit(3))\n")
    monkeypatch.setenv("PYTHONPATH", with_folder_first(folder))


def test_a_picture_whose_rendering_failed_is_removed(tmp_path, monkeypatch):
    """A rendering process that fails after it wrote its picture (here it exits with code 3
    at its end, as a GL driver crashing at exit does): the picture may be half drawn, so it
    is removed, with the data file, and `snapshot` raises, naming the exit code."""
    from dolfinx import fem, mesh

    from membranes.app.render import snapshot
    rendering_exits_with_3(tmp_path, monkeypatch)
    square = mesh.create_unit_square(MPI.COMM_SELF, 2, 2)
    V = fem.FunctionSpace(square, ("Lagrange", 1))
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(RuntimeError, match=r"^rendering c.png failed: exit code 3$"):
        snapshot(V, [("c", "cell", np.ones(8), "")], str(out / "c.png"))
    assert not any(out.iterdir())


def test_pictures_drawn_together_fail_one_by_one(tmp_path):
    """`snapshots` draws several pictures in one rendering process: one that fails there
    (here an unknown colour map) is missing with its own reason, and the others are drawn; no
    data file is left."""
    from dolfinx import fem, mesh

    from membranes.app.render import snapshots
    square = mesh.create_unit_square(MPI.COMM_SELF, 2, 2)
    V = fem.FunctionSpace(square, ("Lagrange", 1))
    panels = [("c", "cell", np.arange(8.0), "")]
    drawn, bad = str(tmp_path / "drawn.png"), str(tmp_path / "bad.png")
    errors = snapshots(V, [(panels, bad, dict(cmap="no_such_map")), (panels, drawn, {})])
    assert errors[0].startswith("rendering bad.png failed: ") and "no_such_map" in errors[0]
    assert errors[1] is None
    assert sorted(os.listdir(tmp_path)) == ["drawn.png"]


def test_a_crash_after_one_failed_picture_names_the_crash(tmp_path, monkeypatch):
    """A rendering process in which one picture failed (an unknown colour map) and which
    then crashes (exit code 3 at its end): the failed picture keeps its own reason, and the
    other, spoilt by the crash, names the crash, not the first picture's failure."""
    from dolfinx import fem, mesh

    from membranes.app.render import snapshots
    rendering_exits_with_3(tmp_path, monkeypatch)
    square = mesh.create_unit_square(MPI.COMM_SELF, 2, 2)
    V = fem.FunctionSpace(square, ("Lagrange", 1))
    panels = [("c", "cell", np.arange(8.0), "")]
    out = tmp_path / "out"
    out.mkdir()
    bad, spoilt = str(out / "bad.png"), str(out / "spoilt.png")
    errors = snapshots(V, [(panels, bad, dict(cmap="no_such_map")), (panels, spoilt, {})])
    assert errors[0].startswith("rendering bad.png failed: ") and "no_such_map" in errors[0]
    assert errors[1] == "rendering spoilt.png failed: exit code 3"
    assert not any(out.iterdir())


def test_a_data_file_that_cannot_be_written_fails_on_every_process(tmp_path):
    """Where process 0 cannot write the rendering's data file (here its folder is missing;
    a full disk alike) every process raises the same RuntimeError, naming the error. It was
    an OSError on process 0 alone, the others waiting for it in `snapshot`'s broadcast for
    ever (a hang under mpirun)."""
    import json

    from tests.conftest import mpirun
    picture = tmp_path / "missing" / "c.png"
    proc = mpirun(["-c", SNAPSHOT_ON_EVERY_PROCESS, tmp_path, picture], processes=2,
                  timeout=60)
    assert proc.returncode == 0, proc.stderr[-3000:]
    said = ("RuntimeError: rendering c.png failed: FileNotFoundError: [Errno 2] No such file "
            f"or directory: '{picture}.npz'")
    assert json.loads(proc.stdout) == [said, said]
    assert sorted(p.name for p in tmp_path.iterdir()) == []
