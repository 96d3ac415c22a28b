"""Ctrl-C and SIGTERM end a run cleanly (membranes.app.interrupts): one line, exit 130 or 143,
nothing left in or beside the output folder, serially and under mpirun (which passes Ctrl-C
on as SIGTERM and kills the processes a moment later)."""

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest

from membranes.app import interrupts

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _env():
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=ROOT)
    return env


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # (the drop)
def test_a_swallowed_interrupt_is_raised_again():
    """A signal whose exception Python drops (raised inside a `__del__` or a weakref callback:
    "Exception ignored in …") is raised again until code handles it; before, the run went on."""
    class Dropped:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)     # the handler runs here: dropped

    previous = interrupts.install()
    try:
        with pytest.raises(interrupts.Terminated):
            Dropped()
            time.sleep(5.0)                            # raised again in here
        interrupts.caught()
        time.sleep(3 * interrupts.RETRY)              # and no more once caught
    finally:
        interrupts.restore(previous)


def test_the_handler_removes_the_staging_folder(tmp_path):
    stage = tmp_path / ".membranes-x"
    (stage / "a").mkdir(parents=True)
    previous = interrupts.install()
    interrupts.staging = str(stage)
    try:
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5.0)
        interrupts.caught()
    finally:
        interrupts.staging = None
        interrupts.restore(previous)
    assert list(tmp_path.iterdir()) == []


def _report(command, out):
    return subprocess.Popen(command + [sys.executable, "-m", "membranes.app.cli", "report",
                                       "--h", "0.5", "--levels", "0", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=_env(), cwd=ROOT)


def test_sigterm_ends_a_report_cleanly(tmp_path):
    """SIGTERM (a batch scheduler's time limit) while a report runs, its outputs staged: one
    line 'membranes: terminated', exit 143, nothing in or beside the output folder (before:
    killed at once, the staging folder left beside it)."""
    proc = _report([], tmp_path / "out")
    for line in proc.stderr:                  # once the methods run (outputs staged)
        if line.startswith("report: exact/amg"):
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stderr.read()
    proc.wait(timeout=120)
    assert proc.returncode == 143, rest
    assert rest.strip().splitlines()[-1] == "membranes: terminated" and "Traceback" not in rest
    assert os.listdir(tmp_path) == []


def test_ctrl_c_under_mpirun_leaves_nothing(tmp_path):
    """Ctrl-C to mpirun -n 2 during a report: mpirun sends the processes SIGTERM and kills
    them about a second later, while they wait in MPI calls or run clean-ups; the staging
    folder beside the output folder was left behind (with some of the report's files)."""
    proc = _report([shutil.which("mpirun"), "--allow-run-as-root", "--oversubscribe", "-n",
                    "2"], tmp_path / "out")
    for line in proc.stderr:
        if line.startswith("report: inexact/amg"):
            proc.send_signal(signal.SIGINT)
            break
    proc.communicate(timeout=120)
    assert proc.returncode != 0
    assert os.listdir(tmp_path) == []
