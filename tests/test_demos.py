"""The literate demos of demos/ run in their quick mode, as a user runs them: as scripts in a
fresh process (serially, and the user-mesh demo on 2 processes), exiting 0, drawing their
pictures and writing outputs whose certificate is a bound."""

import json
import math
import os
import shutil
import struct
import subprocess
import sys

import pytest
from mpi4py import MPI

from tests.blocked import blocking_folder, with_folder_first

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEMOS = os.path.join(ROOT, "demos")

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="runs the demos in processes of their own")


def run_demo(name, out, processes=1, pythonpath=None):
    """Run demos/NAME --quick --out OUT (`pythonpath`: a folder put first on PYTHONPATH);
    returns its stdout (asserting exit code 0)."""
    command = [sys.executable, os.path.join(DEMOS, name), "--quick", "--out", str(out)]
    if processes > 1:
        mpirun = shutil.which("mpirun")
        if mpirun is None:
            pytest.skip("no mpirun")
        command = [mpirun, "--allow-run-as-root", "--oversubscribe", "-n", str(processes)] + \
            command
    # this process is an MPI singleton: its Open MPI variables would confuse a new mpirun
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    if pythonpath is not None:
        env["PYTHONPATH"] = with_folder_first(pythonpath, env.get("PYTHONPATH", ""))
    proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    return proc.stdout


def png_size(path):
    """(width, height) of a PNG file, from its signature and IHDR chunk."""
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR", f"{path} is no PNG"
    return struct.unpack(">II", head[16:24])


def summary(folder):
    with open(os.path.join(folder, "summary.json")) as f:
        return json.load(f)


def test_demo_disk(tmp_path):
    out = tmp_path / "disk"
    stdout = run_demo("demo_disk.py", out)
    width, height = png_size(out / "error_vs_time.png")
    assert width >= 600 and height >= 400
    assert os.path.getsize(out / "error_vs_time.png") > 20_000      # curves, not a blank plot
    # the three methods printed their certificates, and each bounds the measured error
    verdicts = [line for line in stdout.splitlines() if ">= error" in line]
    assert [v.split(":")[0] for v in verdicts] == ["exact", "inexact", "adaptive"]
    assert all(v.endswith(": True") for v in verdicts), verdicts
    s = summary(out / "adaptive")
    assert s["converged"] and s["newton"] == "adaptive" and s["bound_guaranteed"]
    assert s["eta"] >= s["energy_error"] > 0
    # adaptive stopping (theory §8): η_lin ≤ γ_lin η_disc at the returned iterate
    assert s["eta_lin"] <= s["gamma_lin"] * s["eta_disc"]
    for name in ("history.csv", "solution.xdmf", "solution.h5"):
        assert (out / "adaptive" / name).stat().st_size > 0


def test_demo_sweep(tmp_path):
    """The load sweep: one row per load, each with its bound; no contact below the onset
    t = g / max w ≈ 0.68 (the demo's equations), contact above it, growing with the load."""
    out = tmp_path / "sweep"
    stdout = run_demo("demo_sweep.py", out)
    width, height = png_size(out / "sweep.png")
    assert width >= 600 and height >= 400
    rows = [line.split() for line in stdout.splitlines()
            if line.split() and line.split()[-1] in ("True", "False")]
    assert [float(r[0]) for r in rows] == [0.5, 2.0, 8.0]
    assert all(r[-1] == "True" for r in rows)
    share = [float(r[5].rstrip("%")) for r in rows]
    assert share[0] == 0.0 and 0.0 < share[1] < share[2]


@pytest.mark.parametrize("processes", [1, 2])
def test_demo_user_mesh(tmp_path, processes):
    out = tmp_path / "user_mesh"
    stdout = run_demo("demo_user_mesh.py", out, processes)
    assert (out / "l_shape.msh").stat().st_size > 0
    for picture, panels in (("contact.png", 2), ("eta_K.png", 1)):
        width, height = png_size(out / picture)
        assert width == 700 * panels and height == 650     # render.py's window per panel
    s = summary(out / "solution")
    assert s["converged"] and s["scene"] == "user" and s["processes"] == processes
    assert s["energy_error"] is None            # user data: no exact solution, η alone
    assert math.isfinite(s["eta"]) and s["eta"] > 0 and s["bound_guaranteed"]
    assert "guaranteed bound" in stdout
    again = [line for line in stdout.splitlines() if "on T_J read back" in line]
    assert len(again) == 1 and f"({s['n_vertices']} vertices)" in again[0]


def test_demo_user_mesh_without_pyvista(tmp_path):
    """When pyvista cannot draw (here: not importable in the rendering process), the demo
    says so in one line and goes on to its outputs (it ended in a traceback, no outputs)."""
    out = tmp_path / "user_mesh"
    stdout = run_demo("demo_user_mesh.py", out,
                      pythonpath=blocking_folder(tmp_path, "pyvista"))
    skipped = [line for line in stdout.splitlines() if "pictures skipped" in line]
    assert len(skipped) == 1 and "no pyvista here" in skipped[0]
    assert not (out / "contact.png").exists() and not (out / "eta_K.png").exists()
    assert summary(out / "solution")["bound_guaranteed"]


@pytest.mark.parametrize("name, picture", [("demo_disk.py", "error_vs_time.png"),
                                           ("demo_sweep.py", "sweep.png")])
def test_demo_without_matplotlib(tmp_path, name, picture):
    """matplotlib is no dependency of the package (a plain `pip install` lacks it): the demo
    says so in one line and goes on to its results and outputs without its picture (it ended
    in a traceback after every run, demo_disk's outputs unwritten)."""
    out = tmp_path / "demo"
    stdout = run_demo(name, out, pythonpath=blocking_folder(tmp_path, "matplotlib"))
    skipped = [line for line in stdout.splitlines() if "picture skipped" in line]
    assert len(skipped) == 1 and "no matplotlib here" in skipped[0], stdout
    assert "pip install matplotlib numpy==" in skipped[0]
    assert not (out / picture).exists()
    if name == "demo_disk.py":
        assert summary(out / "adaptive")["bound_guaranteed"]
    else:
        assert sum(1 for line in stdout.splitlines() if line.endswith(" True")) == 3


@pytest.mark.parametrize("out", ["/proc/x", ""])
def test_demo_refuses_an_unwritable_folder(out):
    """An --out the demo cannot write: one error line and exit 2, as the CLI (it was a
    FileNotFoundError traceback), before any mesh is made."""
    command = [sys.executable, os.path.join(DEMOS, "demo_disk.py"), "--quick", "--out", out]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    proc = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("demo_disk.py: error: ")
    assert "Traceback" not in proc.stderr and proc.stdout == ""
