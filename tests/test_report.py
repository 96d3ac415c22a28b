"""The report runs headless, its pictures are real renderings, and its CSVs are the run's data."""

import csv

import numpy as np
import pytest

from membranes.cli import main
from membranes.report import CURVE_COLUMNS, METHODS, write_report

from .conftest import scene

PICTURES = ["error_vs_time.png", "error_distribution.png", "contact.png"] + \
    [f"estimators_{m}.png" for m in METHODS]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "disk"
    runs, peer = write_report(scene("disk", 0.3, levels=1), str(out))
    return out, runs, peer


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


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
    out, runs, peer = report
    rows = {r["method"]: r for r in _rows(out / "table.csv")}
    for method, sol in runs.items():
        s = sol.summary()
        assert int(rows[method]["newton_iterations"]) == s["newton_iterations"]
        assert int(rows[method]["linear_iterations"]) == s["linear_iterations"]
        assert float(rows[method]["energy_error"]) == pytest.approx(s["energy_error"],
                                                                    rel=1e-12)
        assert float(rows[method]["wall_time_s"]) == pytest.approx(s["wall_time_s"], rel=1e-12)
    snes = [r for m, r in rows.items() if m.startswith("SNES")][0]
    assert int(snes["newton_iterations"]) == peer[0].newton_iterations
    text = (out / "report.md").read_text()
    for name in PICTURES:
        assert name in text
    assert str(runs["exact"].summary()["linear_iterations"]) in text


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
    assert [float(r["wall_time_s"]) for r in times] == \
        [pytest.approx(r["wall_time_s"], rel=1e-12) for r in history if r["kind"] != "krylov"]


@pytest.mark.parametrize("args", [["--h", "0"], ["--h", "nan"], ["--levels", "-1"],
                                  ["--scene", "cube"]])
def test_bad_input(args, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["report", "--out", str(out), "--quiet"] + args)
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("membranes: error:") and "\n" not in err
    assert not out.exists()
