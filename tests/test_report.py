"""The report runs headless, its pictures are real renderings, and its CSVs are the run's data."""

import csv

import numpy as np
import pytest

from membranes.cli import main
from membranes.decoupled import solve_decoupled
from membranes.report import CURVE_COLUMNS, METHODS, PEER, TABLE_COLUMNS, write_report

from .conftest import scene, solved

PICTURES = ["error_vs_time.png", "error_distribution.png", "contact.png"] + \
    [f"estimators_{m}.png" for m in METHODS]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "disk"
    runs, rows = write_report(scene("disk", 0.3, levels=1), str(out))
    return out, runs, {r["method"]: r for r in rows}


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def _column(rows, name):
    return np.array([float(r[name]) for r in rows])


@pytest.mark.parametrize("name", PICTURES)
def test_pictures_are_real_renderings(report, name):
    import matplotlib.image as mpimg
    out, _, _ = report
    path = out / name
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size > 10_000
    pixels = mpimg.imread(str(path))[..., :3]
    assert pixels.shape[0] > 300 and pixels.shape[1] > 500
    assert pixels.std() > 0.02                    # not a flat image
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50   # more than a few colours


def test_table_matches_the_summaries(report):
    out, runs, table = report
    rows = {r["method"]: r for r in _rows(out / "table.csv")}
    assert list(rows) == list(METHODS) + [PEER]
    for method, sol in runs.items():
        s = sol.summary()
        assert int(rows[method]["newton_iterations"]) == s["newton_iterations"]
        assert int(rows[method]["linear_iterations"]) == s["linear_iterations"]
        for key in ("energy_error", "wall_time_s", "eta"):
            assert float(rows[method][key]) == pytest.approx(s[key], rel=1e-12)
    peer = rows[PEER]
    assert peer["converged"] == "True"
    assert int(peer["newton_iterations"]) == table[PEER]["newton_iterations"] >= 1
    assert int(peer["linear_iterations"]) == table[PEER]["linear_iterations"] > \
        int(peer["newton_iterations"])                       # CG steps, several per SNES step
    # the peer solves the same discrete problem: the same error as exact Newton's
    assert float(peer["energy_error"]) == pytest.approx(runs["exact"].energy_error, rel=1e-8)
    text = (out / "report.md").read_text()
    for name in PICTURES:
        assert f"]({name})" in text
    for method in list(METHODS) + [PEER]:
        line = next(li for li in text.splitlines() if li.startswith(f"| {method} |"))
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[TABLE_COLUMNS.index("newton_iterations")] == \
            rows[method]["newton_iterations"]
        assert cells[TABLE_COLUMNS.index("linear_iterations")] == \
            rows[method]["linear_iterations"]


@pytest.mark.parametrize("method", METHODS)
def test_curves_are_the_histories(report, method):
    out, runs, _ = report
    rows = _rows(out / f"estimators_{method}.csv")
    history = runs[method].history
    assert len(rows) == len(history)
    for row, rec in zip(rows, history):
        for c in CURVE_COLUMNS:
            if rec.get(c) is None:
                assert row[c] == ""
            elif isinstance(rec[c], str):
                assert row[c] == rec[c]
            else:
                assert float(row[c]) == pytest.approx(rec[c], rel=1e-12, abs=0)
    times = [r for r in _rows(out / "error_vs_time.csv") if r["method"] == method]
    steps = [r for r in history if r["kind"] != "krylov"]
    assert list(_column(times, "wall_time_s")) == \
        [pytest.approx(r["wall_time_s"], rel=1e-12) for r in steps]
    assert list(_column(times, "energy_error")) == \
        [pytest.approx(r["energy_error"], rel=1e-12) for r in steps]


def test_peer_curve(report):
    out, runs, table = report
    rows = [r for r in _rows(out / "error_vs_time.csv") if r["method"] == PEER]
    assert [int(r["newton_it"]) for r in rows] == \
        list(range(table[PEER]["newton_iterations"] + 1))        # its initial guess too
    t = _column(rows, "wall_time_s")
    assert np.all(np.diff(t) >= 0) and t[-1] <= table[PEER]["wall_time_s"]
    assert _column(rows, "energy_error")[-1] == pytest.approx(table[PEER]["energy_error"],
                                                              rel=1e-12)
    assert _column(rows, "energy_error")[0] > 2 * table[PEER]["energy_error"]


def test_snapshot_data(report):
    out, runs, _ = report
    sol = runs["adaptive"]
    cells = _rows(out / "error_distribution.csv")
    error_K = _column(cells, "error_K")
    # the actual per-cell errors add up to the energy error, and eta_K is the run's
    assert np.sqrt((error_K ** 2).sum()) == pytest.approx(sol.energy_error, rel=1e-8)
    assert np.allclose(_column(cells, "eta_K"), sol.eta_K, rtol=1e-12, atol=0)
    vertices = _rows(out / "contact.csv")
    n = sol.disc.n
    assert np.allclose(_column(vertices, "gap"), sol.X[:n] - sol.X[n:2 * n], rtol=0,
                       atol=1e-15)
    assert np.allclose(_column(vertices, "lambda"), sol.X[2 * n:], rtol=0, atol=1e-15)


def test_peer_monitor_sees_every_iterate():
    run = solved("disk", 0.1)
    seen = []
    peer = solve_decoupled(run.disc, monitor=lambda its, t, u1, u2, lam: seen.append(
        (its, t, u1.copy(), u2.copy(), lam.copy())))
    assert [s[0] for s in seen] == list(range(peer.newton_iterations + 1))
    assert all(a[1] <= b[1] for a, b in zip(seen, seen[1:]))
    assert seen[-1][1] <= peer.wall_time_s
    for got, want in zip(seen[-1][2:], (peer.u1, peer.u2, peer.lam)):
        assert np.array_equal(got, want)


@pytest.mark.parametrize("args", [["--h", "0"], ["--h", "nan"], ["--levels", "-1"],
                                  ["--scene", "cube"], ["--scene", "user"], ["--bogus"]])
def test_bad_input(args, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["report", "--out", str(out), "--quiet"] + args)
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("membranes: error:") and "\n" not in err
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_out_must_be_given_and_be_a_folder(tmp_path, capsys):
    assert main(["report", "--quiet", "--h", "0.3", "--levels", "0"]) == 2
    existing = tmp_path / "file"
    existing.write_text("mine\n")
    code = main(["report", "--quiet", "--h", "0.3", "--levels", "0", "--out", str(existing)])
    assert code == 2 and existing.read_text() == "mine\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    assert "membranes: error:" in capsys.readouterr().err
