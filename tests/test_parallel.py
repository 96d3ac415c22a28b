"""Several processes (membranes.pipeline, issue 6): Newton on process 0, the estimators on the
others, give the results of one process.

Runs under `mpirun -n P` compare with the same runs in this process. With P = 2 process 1
evaluates the estimators exactly as a serial run does and process 0 runs the serial Newton on
the same data: iterates, estimates and iteration counts are the same bit for bit (asserted:
any difference would be a fault of the pipeline, e.g. an iterate sent before it was final or
an estimate paired with the wrong record). With P = 3 processes 1 and 2 share the patches
(membranes.parallel): the partial fluxes of two processes are added where one process adds
them patch by patch. That changes σ (and so η and, for the adaptive variant, the estimates
that stop GMRES and Newton) by round-off, a few ulps of the flux: η agrees to far better than
the 1e-8 asked, and the iterates, whose every operation is otherwise the same, to 1e-10
relative. Iteration counts agree exactly: a round-off change of an estimate does not move a
stopping test here (the test would say so).
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


def _mpirun(args, timeout=900, processes=2):
    """`mpirun -n processes python args` (args: a script and its arguments, or -m module ...),
    run to its end; one still running after `timeout` seconds fails the test with the Python
    stacks of its processes (tests/mpi_stacks.py), and is ended with all its processes."""
    mpirun = shutil.which("mpirun")
    assert mpirun is not None          # python3-dolfinx depends on Open MPI
    # this process initialised MPI as a singleton: its OMPI_/PMIX_ variables would confuse
    # the new mpirun
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    proc = subprocess.Popen([mpirun, "--allow-run-as-root", "--oversubscribe", "-n",
                             str(processes), sys.executable, os.path.join(HERE, "mpi_stacks.py")]
                            + args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        pytest.fail(f"mpirun -n {processes} {' '.join(args)} still ran after {timeout} s; "
                    f"the stacks of its processes:\n{_stacks_and_end(proc)}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def _stacks_and_end(proc):
    """The stderr of the mpirun `proc` after its processes were asked for their Python stacks
    (SIGUSR1), once it is ended: SIGTERM (mpirun ends its processes), then SIGKILL for any
    left (a killed mpirun would leave its processes running)."""
    import signal
    import time
    children = _children(proc.pid)
    for pid in children:
        _signal(pid, signal.SIGUSR1)
        time.sleep(1)              # one after the other: their stacks do not interleave
    time.sleep(2)
    proc.terminate()
    try:
        _, err = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    for pid in children:
        _signal(pid, signal.SIGKILL)
    return err[-20000:]


def _children(pid):
    """The processes whose parent is pid (Linux: /proc)."""
    kids = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                stat = f.read()
            if int(stat[stat.rindex(")") + 2:].split()[1]) == pid:
                kids.append(int(entry))
        except (OSError, ValueError):
            continue
    return kids


def _signal(pid, sig):
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def _variants():
    sys.path.insert(0, HERE)
    try:
        import mpi_variants
    finally:
        sys.path.remove(HERE)
    return mpi_variants


# P = 3 on the variants whose estimators need most patches: the multilevel flux (patches of
# T_0 and T_1) and the ν flux with vertex_amg
SHARED_PATCHES = ("adaptive-min", "adaptive-fb-amg")


@pytest.mark.parametrize("processes", [2, 3])
def test_several_processes_give_the_results_of_one(tmp_path, processes):
    mpi_variants = _variants()
    names = [v[0] for v in mpi_variants.VARIANTS] if processes == 2 else SHARED_PATCHES
    out = tmp_path / "mpi.npz"
    proc = _mpirun([os.path.join(HERE, "mpi_variants.py"), str(out)] +
                   ([] if processes == 2 else list(names)), processes=processes)
    assert proc.returncode == 0, proc.stderr[-3000:]
    many = np.load(out)
    for name, scene, options in mpi_variants.VARIANTS:
        if name not in names:
            continue
        one = mpi_variants.run(name, scene, options, None)
        assert many[f"{name}/same_on_all"][0], name
        for key in ("newton", "linear"):
            assert many[f"{name}/{key}"][0] == one[f"{name}/{key}"][0], (name, key)
        X1, X2 = one[f"{name}/X"], many[f"{name}/X"]
        eta1, eta2 = one[f"{name}/eta"][0], many[f"{name}/eta"][0]
        K1, K2 = one[f"{name}/eta_K"], many[f"{name}/eta_K"]
        assert eta1 is not None and np.isfinite(eta1), name
        etas1, etas2 = one[f"{name}/etas"], many[f"{name}/etas"]
        assert etas1.shape == etas2.shape, name          # the same records
        if processes == 2:
            # every record's η (X^0 of each level, whose residual process 0 sends, included)
            assert np.array_equal(X1, X2) and eta1 == eta2 and np.array_equal(K1, K2), name
            assert np.array_equal(etas1, etas2, equal_nan=True), name
        else:
            assert np.abs(X2 - X1).max() <= 1e-10 * np.abs(X1).max(), name
            assert abs(eta2 - eta1) <= 1e-8 * eta1, name
            assert np.abs(K2 - K1).max() <= 1e-8 * np.abs(K1).max(), name
            assert np.allclose(etas2, etas1, rtol=1e-8, atol=0.0, equal_nan=True), name


def test_process_0_lends_its_core_while_it_waits(tmp_path):
    """Two processes on one node (membranes.pipeline, Lent): while process 0 waits for a reply
    with nothing else to do, the estimator process gets a thread that runs on process 0's
    cores; once it has replied, none (tests/mpi_lent.py)."""
    out = tmp_path / "lent.json"
    proc = _mpirun([os.path.join(HERE, "mpi_lent.py"), str(out)], timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = json.loads(out.read_text())
    assert seen["lent"]
    assert seen["thread_cores"] == seen["process_0_cores"]
    assert seen["after_reply_none"] and seen["end_kind"] == "end"


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


@pytest.mark.parametrize("processes, fail, slow", [(2, 1, False), (3, 1, False), (3, 2, False),
                                                   (3, 1, True), (2, 0, True), (3, 0, True)])
def test_a_failed_process_stops_the_run(tmp_path, processes, fail, slow):
    """A process that fails (mpi_failure.py) ends the run on every process with its error: an
    estimator process at its first evaluation, also with P = 3 when its partner waits for its
    partial flux in a collective (it hung there before `parallel.agree`); process 0 at its
    second Newton step. With `slow` the leader takes its messages late, after process 0 has
    ended the run: the leader hung its partner (P = 3) or failed with FileNotFoundError when
    process 0 removed the files of the iterates it had not taken in yet (pipeline.Link.close
    before 2026-11-27; seen in CI). No file of the run is left in shared memory."""
    out = tmp_path / "failed"
    proc = _mpirun([os.path.join(HERE, "mpi_failure.py"), str(out), str(fail)] +
                   (["slow"] if slow else []), timeout=300, processes=processes)
    assert proc.returncode == 0, proc.stderr[-3000:]
    expected = "RuntimeError: " + ("injected failure" if fail == 0 else
                                   f"estimator processes: estimator process {fail}: "
                                   "RuntimeError: injected failure")
    for rank in range(processes):
        raised = (tmp_path / f"failed.{rank}.txt").read_text()
        assert raised == expected, (rank, raised)
    assert (tmp_path / "failed.left.txt").read_text() == ""
