"""The CLI writes summary.json, history.csv and solution.xdmf (+ .h5) as documented (README)."""

import csv
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from membranes.cli import main
from membranes.newton_system import split
from membranes.outputs import HISTORY_COLUMNS

from .conftest import solved, write_msh

SUMMARY_KEYS = {"scene", "n_vertices", "n_cells", "h", "levels", "newton", "cfun", "converged",
                "reason", "newton_iterations", "linear_iterations", "wall_time_s",
                "energy_error"}


@pytest.fixture(scope="module")
def disk_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "disk"
    assert main(["solve", "--scene", "disk", "--h", "0.1", "--cfun", "fb", "--quiet",
                 "--out", str(out)]) == 0
    return out


def test_summary_keys_and_values(disk_run):
    summary = json.loads((disk_run / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(summary)
    reference = solved("disk", 0.1, "fb")
    assert summary["scene"] == "disk" and summary["cfun"] == "fb"
    assert summary["newton"] == "exact" and summary["levels"] == 0
    assert summary["converged"] is True
    assert summary["n_vertices"] == reference.problem.mesh.topology.index_map(0).size_global
    assert summary["newton_iterations"] == reference.newton_iterations
    assert summary["energy_error"] == pytest.approx(reference.energy_error, rel=1e-12)
    assert summary["wall_time_s"] > 0


def test_history_columns_and_rows(disk_run):
    with open(disk_run / "history.csv") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0].keys()) == HISTORY_COLUMNS
    summary = json.loads((disk_run / "summary.json").read_text())
    rows = [r for r in rows if r["kind"] != "krylov"]             # the Newton iterates
    assert len(rows) == summary["newton_iterations"] + 1          # X^0 recorded too
    assert [int(r["newton_it"]) for r in rows] == list(range(len(rows)))
    cumulative = np.cumsum([int(r["linear_it"]) for r in rows])
    assert [int(r["cumulative_linear_its"]) for r in rows] == list(cumulative)
    assert int(rows[-1]["cumulative_linear_its"]) == summary["linear_iterations"]
    times = [float(r["wall_time_s"]) for r in rows]
    assert times == sorted(times)
    assert float(rows[-1]["residual"]) <= 1e-10
    assert float(rows[-1]["energy_error"]) == pytest.approx(summary["energy_error"], rel=1e-12)


def test_solution_xdmf_reads_back(disk_run):
    import h5py
    from dolfinx.io import XDMFFile
    from mpi4py import MPI
    with XDMFFile(MPI.COMM_WORLD, str(disk_run / "solution.xdmf"), "r") as xdmf:
        mesh = xdmf.read_mesh(name="mesh")
    reference = solved("disk", 0.1, "fb")
    assert mesh.topology.index_map(2).size_global == \
        reference.problem.mesh.topology.index_map(2).size_global
    tree = ET.parse(disk_run / "solution.xdmf")
    attributes = {a.get("Name"): a for a in tree.iter("Attribute")}
    assert {"u1", "u2", "lambda"} <= set(attributes)
    ref_values = dict(zip(("u1", "u2", "lambda"), split(reference.X, reference.disc.n)))
    with h5py.File(disk_run / "solution.h5", "r") as h5:
        geometry = h5["/Mesh/mesh/geometry"][:]
        for name in ("u1", "u2", "lambda"):
            path = attributes[name].find("DataItem").text.split(":")[1]
            values = h5[path][:].ravel()
            # written in geometry-node order: compare via coordinates
            order_file = np.lexsort(geometry[:, :2].T)
            x_ref = reference.disc.V.tabulate_dof_coordinates()[:, :2]
            order_ref = np.lexsort(x_ref.T)
            assert np.allclose(values[order_file], ref_values[name][order_ref],
                               rtol=0, atol=1e-14 * np.abs(ref_values[name]).max())


def test_user_scene_on_a_gmsh_file(tmp_path):
    mesh = write_msh(tmp_path / "rect.msh", "triangles")
    out = tmp_path / "out"
    code = main(["solve", "--mesh", str(mesh), "--mu1", "2", "--mu2", "0.5", "--g", "0.1",
                 "--f1", "-1 - x", "--f2", "0.5*sin(pi*y)", "--linear-solver", "direct",
                 "--quiet", "--out", str(out)])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "user" and summary["energy_error"] is None
    assert summary["converged"] and summary["complementarity_violation"] <= 1e-12
    with open(out / "history.csv") as f:
        assert all(r["energy_error"] == "" for r in csv.DictReader(f))


def test_not_converged_exit_code(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["solve", "--h", "0.1", "--max-newton", "2", "--quiet", "--out", str(out)])
    assert code == 3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] is False and "no convergence" in summary["reason"]
    assert "not converged" in capsys.readouterr().err


def test_scenes_command(capsys):
    assert main(["scenes"]) == 0
    text = capsys.readouterr().out
    for name in ("disk", "square", "user"):
        assert name in text
