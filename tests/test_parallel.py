"""Several processes (membranes.parallel, issue 6): the patches of the estimators shared out
between MPI processes give the results of one process.

Runs under `mpirun -n 2` compare with the same runs in this process. The solution may differ
only by the order in which patch contributions are summed: the partial fluxes of two processes
are added where one process adds them patch by patch. That changes σ (and so η and, for the
adaptive variant, the estimates that stop GMRES and Newton) by round-off, a few ulps of
the flux: η agrees to far better than the 1e-8 asked, and the iterates, whose every
operation is otherwise the same, to 1e-10 relative. Iteration counts agree exactly: a
round-off change of an estimate does not move a stopping test here (the test would say so).
"""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from membranes.parallel import owned_vertices

HERE = os.path.dirname(__file__)


class _Comm:
    def __init__(self, rank, size):
        self.rank, self.size = rank, size


@pytest.mark.parametrize("n,size", [(1, 1), (10, 2), (11, 3), (2, 3), (1000, 7)])
def test_owned_vertices_are_a_partition(n, size):
    masks = np.array([owned_vertices(n, _Comm(r, size)) for r in range(size)])
    assert (masks.sum(axis=0) == 1).all()
    counts = masks.sum(axis=1)
    assert counts.max() - counts.min() <= 1


def _mpirun(args, timeout=900):
    mpirun = shutil.which("mpirun")
    assert mpirun is not None          # python3-dolfinx depends on Open MPI
    # this process initialised MPI as a singleton: its OMPI_/PMIX_ variables would confuse
    # the new mpirun
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    return subprocess.run([mpirun, "--allow-run-as-root", "--oversubscribe", "-n", "2",
                           sys.executable] + args, capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_two_processes_give_the_results_of_one(tmp_path):
    sys.path.insert(0, HERE)
    try:
        import mpi_variants
    finally:
        sys.path.remove(HERE)
    out = tmp_path / "mpi.npz"
    proc = _mpirun([os.path.join(HERE, "mpi_variants.py"), str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    two = np.load(out)
    for name, scene, options in mpi_variants.VARIANTS:
        one = mpi_variants.run(name, scene, options, None)
        for key in ("newton", "linear"):
            assert two[f"{name}/{key}"][0] == one[f"{name}/{key}"][0], (name, key)
        X1, X2 = one[f"{name}/X"], two[f"{name}/X"]
        assert np.abs(X2 - X1).max() <= 1e-10 * np.abs(X1).max(), name
        eta1, eta2 = one[f"{name}/eta"][0], two[f"{name}/eta"][0]
        assert eta1 is not None and np.isfinite(eta1), name
        assert abs(eta2 - eta1) <= 1e-8 * eta1, name
        K1, K2 = one[f"{name}/eta_K"], two[f"{name}/eta_K"]
        assert np.abs(K2 - K1).max() <= 1e-8 * np.abs(K1).max(), name


def test_cli_under_mpirun_writes_once(tmp_path):
    out = tmp_path / "run"
    proc = _mpirun(["-m", "membranes.cli", "solve", "--h", "0.3", "--levels", "1",
                    "--newton", "adaptive", "--quiet", "--out", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1                      # process 0 prints the summary line
    summary = json.loads((out / "summary.json").read_text())
    assert summary["processes"] == 2 and summary["converged"]
    assert sorted(os.listdir(out)) == ["history.csv", "solution.h5", "solution.xdmf",
                                       "summary.json"]
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".membranes-")]
    from membranes import scenes, solve
    one = solve(scenes.disk(h=0.3, levels=1), newton="adaptive")
    assert summary["newton_iterations"] == one.newton_iterations
    assert abs(summary["eta"] - one.final_record["eta"]) <= 1e-8 * summary["eta"]


def test_bad_input_under_mpirun(tmp_path):
    """Every process meets the bad input; process 0 says it on one line; exit 2; nothing
    written."""
    out = tmp_path / "run"
    proc = _mpirun(["-m", "membranes.cli", "solve", "--mu1", "-1", "--h", "0.3",
                    "--out", str(out)])
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("membranes:")]
    assert len(errors) == 1 and "mu1" in errors[0]
    assert not out.exists()


def test_only_solve_runs_under_mpirun(tmp_path):
    proc = _mpirun(["-m", "membranes.cli", "stability", "--out", str(tmp_path / "s")])
    assert proc.returncode == 2
    assert "only `membranes solve` runs on several processes" in proc.stderr
