"""Ctrl-C and SIGTERM end a run cleanly (membranes.app.interrupts): one line, exit 130 or 143,
nothing left in or beside the output folder, serially and under mpirun (which passes Ctrl-C
on as SIGTERM and kills the processes a moment later)."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from membranes.app import interrupts

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(autouse=True)
def signals_at_their_defaults():
    """The signals these tests send, at their defaults in this process and so in the runs it
    starts (an ignored signal stays ignored across exec, and the product keeps it ignored):
    the suite run as a background job (SIGINT ignored) or under nohup (SIGHUP) is tested as
    from a terminal."""
    defaults = {signal.SIGINT: signal.default_int_handler, signal.SIGHUP: signal.SIG_DFL,
                signal.SIGTERM: signal.SIG_DFL}
    before = {sig: signal.signal(sig, handler) for sig, handler in defaults.items()}
    yield
    for sig, handler in before.items():
        signal.signal(sig, handler)


def _env():
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=ROOT)
    return env


def test_a_swallowed_interrupt_is_not_said(capsys):
    """The interrupt dropped in a weakref callback is raised again, without Python's "Exception
    ignored in …" traceback above the one line (under mpirun -n 3, rank 0 met SIGTERM in a
    WeakKeyDictionary's callback); other dropped exceptions are still said."""
    said, hook = [], sys.unraisablehook
    previous = interrupts.install()
    sys.unraisablehook = interrupts._unsaid(said.append)
    try:
        class Dropped:
            def __init__(self, error):
                self.error = error

            def __del__(self):
                raise self.error

        interrupts._pending = interrupts.Terminated
        Dropped(interrupts.Terminated())
        Dropped(ValueError("said"))
        interrupts._pending = None
        Dropped(interrupts.Terminated())
    finally:
        interrupts.restore(previous)
    assert [type(u.exc_value) for u in said] == [ValueError, interrupts.Terminated]
    assert sys.unraisablehook is hook


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


def test_no_raise_again_while_the_interrupt_is_handled():
    """The retry must not raise while the interrupt is being handled (or propagates through a
    `finally`): it fired in the CLI's handler before its `caught()` and ended a run with two
    tracebacks instead of one line (SIGTERM during the plaza refinement of 1.7e6 vertices,
    whose unwinding outlasted RETRY). Outside a handler a pending interrupt is raised."""
    interrupts._pending = interrupts.Terminated
    try:
        try:
            raise interrupts.Terminated
        except KeyboardInterrupt:
            interrupts._raise_pending(signal.SIGALRM, None)      # handled: not again
        try:
            try:
                raise interrupts.Terminated
            finally:
                interrupts._raise_pending(signal.SIGALRM, None)  # propagating: not again
        except interrupts.Terminated as e:
            assert e.__context__ is None
        with pytest.raises(interrupts.Terminated):
            interrupts._raise_pending(signal.SIGALRM, None)      # dropped: raised again
    finally:
        interrupts._pending = None


def _raised_on(sig, exception):
    """`sig` sent to this process raises `exception` (the handlers installed), then caught."""
    with pytest.raises(exception):
        os.kill(os.getpid(), sig)
        time.sleep(5.0)
    interrupts.caught()


def test_the_handler_removes_the_staging_folder(tmp_path):
    stage = tmp_path / ".membranes-x"
    (stage / "a").mkdir(parents=True)
    previous = interrupts.install()
    interrupts.staging = str(stage)
    try:
        _raised_on(signal.SIGINT, KeyboardInterrupt)
    finally:
        interrupts.staging = None
        interrupts.restore(previous)
    assert list(tmp_path.iterdir()) == []


def interrupted(launcher, args, when, sig):
    """Run `launcher + python -m membranes.app.cli + args`, send `sig` once a progress line
    starts with `when`; (exit code, the rest of stderr)."""
    proc = subprocess.Popen(launcher + [sys.executable, "-m", "membranes.app.cli"] + args,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env=_env(), cwd=ROOT)
    for line in proc.stderr:
        if line.startswith(when):
            proc.send_signal(sig)
            break
    rest = proc.communicate(timeout=120)[1]
    return proc.returncode, rest


@pytest.mark.parametrize("command, when, sig, code, said", [
    # Ctrl-C once Newton runs on a coarse level (it was a KeyboardInterrupt traceback)
    (["solve", "--h", "0.2", "--levels", "5"], "level 2: Newton", signal.SIGINT, 130,
     "membranes: interrupted"),
    # SIGTERM (a batch scheduler's time limit) while a report's outputs are staged (it was
    # killed at once, the staging folder left beside the output folder)
    (["report", "--h", "0.5", "--levels", "0"], "report: exact/amg", signal.SIGTERM, 143,
     "membranes: terminated"),
    # SIGHUP (the terminal or ssh session gone): PETSc's handler ended the run with a PETSc
    # error and MPI_Abort (exit 59), the staging folder left behind
    (["solve", "--h", "0.2", "--levels", "5"], "level 2: Newton", signal.SIGHUP, 129,
     "membranes: hung up")], ids=["ctrl-c solve", "sigterm report", "sighup solve"])
def test_an_interrupted_run_says_so_and_leaves_nothing(tmp_path, command, when, sig, code,
                                                        said):
    """One line, the exit code of the signal, neither the output folder nor the staging
    folder beside it."""
    returncode, rest = interrupted([], command + ["--out", str(tmp_path / "out")], when, sig)
    assert returncode == code, rest
    assert rest.strip().splitlines()[-1] == said and "Traceback" not in rest
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("sig, code, said", [(signal.SIGINT, 130, "membranes: interrupted"),
                                             (signal.SIGTERM, 143, "membranes: terminated")])
def test_a_signal_while_mpi_starts_says_so(sig, code, said):
    """A signal in MPI's start (mpi4py's import, the first few tenths of a second of a run),
    sent here by an import hook as the import begins: the handlers were installed after it,
    and Ctrl-C printed a KeyboardInterrupt traceback."""
    source = "\n".join([
        "import os, sys",
        "class Hook:",
        "    def find_spec(self, name, path=None, target=None):",
        "        if name == 'mpi4py.MPI':",
        f"            os.kill(os.getpid(), {int(sig)})",
        "sys.meta_path.insert(0, Hook())",
        "from membranes.app.cli import main",
        "sys.exit(main(['scenes']))"])
    proc = subprocess.run([sys.executable, "-c", source], env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert (proc.returncode, proc.stderr, proc.stdout) == (code, said + "\n", "")


@pytest.mark.parametrize("sig", [signal.SIGHUP, signal.SIGINT], ids=["nohup", "background"])
def test_a_signal_ignored_at_the_start_stays_ignored(tmp_path, sig):
    """A run started with a signal ignored goes on when it comes: `nohup membranes solve ...`
    ignores SIGHUP so that the run outlives its terminal, and a shell script's background job
    ignores SIGINT. Our handlers replaced both, and the nohup run ended as hung up (129)."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "membranes.app.cli", "solve", "--h", "0.2",
                             "--levels", "3", "--out", str(out)],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT,
                            preexec_fn=lambda: signal.signal(sig, signal.SIG_IGN))
    for line in proc.stderr:
        if line.startswith("level 1: Newton"):
            proc.send_signal(sig)
            break
    rest = proc.communicate(timeout=120)[1]
    assert proc.returncode == 0, rest
    assert "summary.json" in os.listdir(out)


def test_ctrl_c_under_mpirun_leaves_nothing(tmp_path):
    """Ctrl-C to mpirun -n 2 during a report: mpirun sends the processes SIGTERM and kills
    them about a second later, while they wait in MPI calls or run clean-ups; the staging
    folder beside the output folder was left behind (with some of the report's files)."""
    mpirun = [shutil.which("mpirun"), "--allow-run-as-root", "--oversubscribe", "-n", "2"]
    returncode, _ = interrupted(mpirun, ["report", "--h", "0.5", "--levels", "0", "--out",
                                         str(tmp_path / "out")], "report: inexact/amg",
                                signal.SIGINT)
    assert returncode != 0
    assert os.listdir(tmp_path) == []


def _sigterm_both(body):
    """Run `body` (the source lines of a function `waits(world)`, indented, with `world`
    MPI.COMM_WORLD) as the command of `membranes.app.cli.main` under mpirun -n 2; once both
    processes have said "ready PID", wait 0.5 s and send SIGTERM to both, as mpirun passes
    Ctrl-C on. (The signals go to the processes, not to mpirun, which now and then left a
    SIGINT of its own unanswered.) Returns mpirun's exit code and the lines of its stderr
    after the "ready" lines; a run still going after 60 s is killed and fails the test."""
    source = "\n".join([
        "import os, sys, time",
        "from mpi4py import MPI",
        "from membranes.app import cli, interrupts, outputs",
        "def waits(world):"] + body + [
        "def command(argv):",
        "    world = MPI.COMM_WORLD",
        "    os.write(2, f'ready {os.getpid()}\\n'.encode())    # (one write: whole)",
        "    return waits(world)",
        "cli._main = command",
        "sys.exit(cli.main([]))"])
    mpirun = [shutil.which("mpirun"), "--allow-run-as-root", "--oversubscribe", "-n", "2"]
    proc = subprocess.Popen(mpirun + [sys.executable, "-c", source], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT,
                            start_new_session=True)
    pids = []
    for line in proc.stderr:           # (mpirun may still run two processes' lines together)
        pids += [int(pid) for pid in re.findall(r"ready (\d+)", line)]
        if len(pids) == 2:
            time.sleep(0.5)
            for pid in pids:
                os.kill(pid, signal.SIGTERM)
            break
    try:
        rest = proc.communicate(timeout=60)[1]
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail("the processes still ran 60 s after the signal")
    return proc.returncode, rest.strip().splitlines()


def test_under_mpirun_process_0_says_it_while_the_others_wait_for_it():
    """SIGTERM to every process of mpirun -n 2 while process 0 waits in a collective call for
    process 1, which runs Python: process 1 raised at once and left, process 0 never came
    back from the call to run its handler, and mpirun killed it: exit 1 and no line (6 of 30
    Ctrl-C's into `membranes solve`). Process 1 now goes on into the call (`among`)."""
    code, lines = _sigterm_both([
        "    if world.rank != 0:",
        "        end = time.monotonic() + 60",
        "        while interrupts._pending is None and time.monotonic() < end:",
        "            time.sleep(0.01)              # (Python: the signal is handled here)",
        "    world.Barrier()                       # (process 0: in C, until process 1 comes)",
        "    return 0"])
    assert code != 0          # (then mpirun's lines on a process's exit 143)
    assert lines[:1] == ["membranes: terminated"] and lines.count(lines[0]) == 1, lines


def test_under_mpirun_a_signal_inside_staged_outputs_ends_process_0_at_once(tmp_path):
    """`report` and `stability` stage their outputs around all their runs. Process 0 met the
    signal there and went into the staging's collective clean-up, while process 1 went on
    with its run (`among`) into a collective of the run's: the two calls did not match
    (process 0 took process 1's data for its own: "membranes: error: The truth value of an
    array ... is ambiguous", or waited), and under mpirun 16 of 20 Ctrl-C's into a report
    ended without a line (11 of 20 before `among`). Process 0 now leaves the staging at once
    and says the line; nothing is left in or beside the output folder."""
    out = tmp_path / "out"
    code, lines = _sigterm_both([
        f"    with outputs.staged_folder({str(out)!r}, world):",
        "        end = time.monotonic() + 60",
        "        while interrupts._pending is None and time.monotonic() < end:",
        "            time.sleep(0.01)              # (Python: the signal is handled here)",
        "        world.bcast(list(range(100000)), root=1)     # (process 1: the run goes on)",
        "    return 0"])
    assert code != 0
    assert lines[:1] == ["membranes: terminated"] and lines.count(lines[0]) == 1, lines
    assert os.listdir(tmp_path) == []


def test_a_process_other_than_0_raises_after_follow(monkeypatch):
    """A process other than 0 of several holds its raise back FOLLOW seconds (`among`), then
    raises as process 0 does: a signal sent to it alone still ends the run."""
    monkeypatch.setattr(interrupts, "FOLLOW", 0.3)
    previous = interrupts.install()
    interrupts.among(1, 2)
    try:
        start = time.monotonic()
        with pytest.raises(interrupts.Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5.0)
        assert time.monotonic() - start >= 0.25
        interrupts.caught()
    finally:
        interrupts.restore(previous)
    assert not interrupts._follower        # (restore: a later run in this process leads)


@pytest.mark.parametrize("error", [FileNotFoundError(2, "No such file or directory"),
                                   ValueError("a staged file is gone"), RuntimeError("x")])
def test_an_error_after_a_signal_is_the_signals(monkeypatch, capsys, error):
    """A process that met a signal and goes on (a process other than 0 for FOLLOW seconds,
    `interrupts.among`) may then meet an error the handler made: its staging folder removed,
    its compilations abandoned. The run ends as the signal's, in one line, not with that
    error (a traceback, exit 1; a ValueError was said as bad input, exit 2)."""
    from membranes.app import cli

    def run(argv):
        interrupts._pending = interrupts.Terminated   # (as the handler leaves it, deferred)
        raise error

    monkeypatch.setattr(cli, "_main", run)
    assert cli.main([]) == cli.EXIT_TERMINATED
    assert capsys.readouterr().err == "membranes: terminated\n"
    assert interrupts._pending is None


def test_main_puts_back_the_signal_handlers_it_replaced():
    """`cli.main` raises KeyboardInterrupt and Terminated from SIGINT and SIGTERM while it
    runs and then puts back the handlers it found: a program or notebook that calls it keeps
    its own (here: SIGTERM's default, which ends the process, not an exception)."""
    import signal

    from membranes.app import cli
    mine = lambda signum, frame: None  # noqa: E731
    before = signal.signal(signal.SIGINT, mine), signal.getsignal(signal.SIGTERM)
    try:
        assert cli.main(["scenes"]) == 0
        assert signal.getsignal(signal.SIGINT) is mine
        assert signal.getsignal(signal.SIGTERM) is before[1]
    finally:
        signal.signal(signal.SIGINT, before[0])


def test_restore_puts_back_the_alarm_handler_a_signal_set():
    """A signal met makes `interrupts` raise again on SIGALRM until `caught`; `restore` then
    puts back SIGALRM's handler as well, so a program whose run was interrupted and handled
    keeps its own alarm."""
    import signal

    from membranes.app import interrupts
    mine = lambda signum, frame: None  # noqa: E731
    before = signal.signal(signal.SIGALRM, mine)
    try:
        previous = interrupts.install()
        try:
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
            assert signal.getsignal(signal.SIGALRM) is not mine
        finally:
            interrupts.restore(previous)
        assert signal.getsignal(signal.SIGALRM) is mine
        assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
    finally:
        signal.signal(signal.SIGALRM, before)


@pytest.mark.parametrize("args, stderr_too", [
    # PETSc's monitors print to stdout: PETSc's own SIGPIPE handler ended this run with
    # "PETSC ERROR: Caught signal number 13 Broken Pipe" and MPI_Abort (exit 59)
    (["solve", "--h", "0.4", "--levels", "1", "--quiet", "--petsc-options", "-ksp_monitor"],
     False),
    # progress on stderr into a closed pipe (`2>&1 | head`): a BrokenPipeError traceback
    (["solve", "--h", "0.4", "--levels", "1"], True),
    # a report's and the stability matrix's progress: the staging folder took the
    # BrokenPipeError for a failed write of the outputs, whose one line failed in turn (exit 1)
    (["report", "--h", "0.5", "--levels", "0"], True),
    (["stability", "--cases", "far_guess"], True),
    (["scenes"], False)], ids=["petsc monitor", "progress", "report", "stability", "scenes"])
def test_a_closed_pipe_ends_the_run_silently(tmp_path, args, stderr_too):
    """`membranes ... | head`: the reader of stdout (here closed before the first write)
    goes away; the run ends as the shell's tools do, exit 141 (128 + SIGPIPE), nothing on
    stderr. A run cut short writes nothing (the progress case); one whose stdout broke only
    in PETSc's monitors (which ignore failed writes) runs to its end and writes its outputs."""
    out = tmp_path / "out"
    if args[0] != "scenes":
        args = args + ["--out", str(out)]
    proc = subprocess.Popen([sys.executable, "-m", "membranes.app.cli"] + args,
                            stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT if stderr_too else subprocess.PIPE,
                            env=_env(), cwd=ROOT)
    proc.stdout.close()
    said = b"" if stderr_too else proc.stderr.read()
    assert proc.wait(timeout=120) == 141, said
    assert said == b""
    if stderr_too:
        assert os.listdir(tmp_path) == []
    elif args[0] == "solve":
        assert sorted(os.listdir(out)) == ["history.csv", "solution.h5", "solution.xdmf",
                                           "summary.json"]


def test_gmsh_leaves_the_ctrl_c_handler_in_place():
    """gmsh 4.8's first import sets SIGINT to its default (put back by gmsh.finalize only
    where a gmsh session ran): a run on an XDMF mesh (gmsh imported by dolfinx.io.gmshio
    alone), the processes other than rank 0, and Ctrl-C during the first meshing ended at
    once, without a word, their staging folders left behind. In a fresh process."""
    code = "\n".join([
        "import signal", "import numpy as np", "from mpi4py import MPI",
        "from membranes.app import interrupts", "from membranes.fem import meshes",
        "interrupts.install()", "mine = signal.getsignal(signal.SIGINT)",
        "meshes.distribute(MPI.COMM_WORLD, np.array([[0, 1, 2]], dtype=np.int64),",
        "                  np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))",
        "assert signal.getsignal(signal.SIGINT) is mine, 'after gmshio'",
        "with meshes.gmsh_session():", "    pass",
        "assert signal.getsignal(signal.SIGINT) is mine, 'after a gmsh session'"])
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_ctrl_c_is_ours_while_gmsh_loads_its_library():
    """gmsh.py sets SIGINT to its default before it loads libgmsh (0.75-0.9 s): the handler
    was put back only after the import, and Ctrl-C in that window killed the run without a
    word (exit -2; a probe's, 2026-12-03). The handler in place when libgmsh is loaded (seen
    by a spy on ctypes.CDLL, which gmsh.py calls) is ours. In a fresh process."""
    code = "\n".join([
        "import ctypes, signal", "from membranes.app import interrupts",
        "from membranes.fem import meshes", "interrupts.install()",
        "mine = signal.getsignal(signal.SIGINT)", "seen = []", "real = ctypes.CDLL",
        "class Spy(real):", "    def __init__(self, name, *args, **kwargs):",
        "        if 'gmsh' in str(name):",
        "            seen.append(signal.getsignal(signal.SIGINT))",
        "        super().__init__(name, *args, **kwargs)", "ctypes.CDLL = Spy",
        "with meshes.keeping_sigint():", "    import gmsh",
        "assert seen and all(h is mine for h in seen), seen",
        "assert signal.getsignal(signal.SIGINT) is mine"])
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr


def test_a_signal_while_the_outputs_move_in_waits_for_the_last_rename(tmp_path, monkeypatch,
                                                                      capsys):
    """SIGTERM after the first rename of the outputs into a folder of an older run: the
    renames go on to the last, every output the new one (the signal used to stop the moves
    halfway, old and new outputs side by side and the older copies of the moved ones
    deleted); the outputs are then in place, so the signal is said and does not end the run
    (it ended as terminated, exit 143 with whole outputs)."""
    from mpi4py import MPI

    from membranes.app import outputs
    out = tmp_path / "out"
    out.mkdir()
    names = ("a.txt", "b.txt", "c.txt")
    for name in names:
        (out / name).write_text("old")
    real, renames = os.replace, []

    def replace(source, target):
        real(source, target)
        if os.path.dirname(target) == str(out) and os.path.basename(target) in names:
            renames.append(target)
            if len(renames) == 1:
                os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(4 * interrupts.RETRY)      # (slow renames: SIGALRM's retries come)

    monkeypatch.setattr(os, "replace", replace)
    previous = interrupts.install()
    try:
        with outputs.staged_folder(str(out), MPI.COMM_SELF) as tmp:
            for name in names:
                with open(os.path.join(tmp, name), "w") as f:
                    f.write("new")
        time.sleep(0.3)                   # (no raise again either: SIGALRM's retries stopped)
    finally:
        interrupts.restore(previous)
    assert len(renames) == len(names)
    assert {p.name: p.read_text() for p in out.iterdir()} == dict.fromkeys(names, "new")
    assert os.listdir(tmp_path) == ["out"]
    assert capsys.readouterr().err.startswith("membranes: terminated after the outputs were "
                                              "written (they are whole)")


def test_ctrl_c_in_staged_outputs_without_the_handlers_leaves_nothing(tmp_path):
    """A KeyboardInterrupt inside `staged_folder` where the handlers are not installed (the
    API in a script or a notebook: Python's own Ctrl-C) removes the staging folder too."""
    from mpi4py import MPI

    from membranes.app import outputs
    with pytest.raises(KeyboardInterrupt):
        with outputs.staged_folder(str(tmp_path / "out"), MPI.COMM_SELF) as tmp:
            open(os.path.join(tmp, "a.txt"), "w").close()
            raise KeyboardInterrupt
    assert os.listdir(tmp_path) == []


def test_under_mpirun_staged_outputs_end_with_the_signal_of_one_process(tmp_path):
    """mpirun -n 2. First a staging that succeeds: no process keeps pointing its handler at
    the staging folder (after a move that could not be undone, the older files are kept in
    it, and a later signal would have removed them). Then SIGTERM to process 1 alone, while
    both write: its handler removes the shared staging folder, so its write fails; process 0,
    which met no signal, ends as terminated, not with the failed write as bad input."""
    script = tmp_path / "one_signalled.py"
    script.write_text("\n".join([
        "import os, signal, sys, time",
        "from mpi4py import MPI",
        "from membranes.app import interrupts, outputs",
        "world = MPI.COMM_WORLD",
        "previous = interrupts.install()",
        "interrupts.among(world.rank, world.size)",
        "with outputs.staged_folder(os.path.join(sys.argv[1], 'first'), world):",
        "    pass",
        "say = lambda *words: os.write(1, (' '.join(map(str, words)) + ';').encode())",
        "say(world.rank, 'staging', interrupts.staging)       # (one write: whole)",
        "try:",
        "    with outputs.staged_folder(os.path.join(sys.argv[1], 'second'), world) as tmp:",
        "        world.Barrier()",
        "        if world.rank == 1:",
        "            os.kill(os.getpid(), signal.SIGTERM)   # (this process alone)",
        "            time.sleep(0.1)",
        "            open(os.path.join(tmp, 'a.txt'), 'w').close()",
        "    say(world.rank, 'ended', 'without an error')",
        "except BaseException as e:",
        "    say(world.rank, 'ended', type(e).__name__)",
        "finally:",
        "    interrupts.caught()",
        "    interrupts.restore(previous)"]) + "\n")
    mpirun = [shutil.which("mpirun"), "--allow-run-as-root", "--oversubscribe", "-n", "2"]
    run = subprocess.run(mpirun + [sys.executable, str(script), str(tmp_path)], env=_env(),
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    said = re.findall(r"(\d [a-z]+ [A-Za-z ]+);", run.stdout)   # (mpirun may join the lines)
    assert sorted(w for w in said if "staging" in w) == ["0 staging None",
                                                         "1 staging None"], run.stdout
    assert "0 ended Terminated" in said, run.stdout + run.stderr
    assert sorted(os.listdir(tmp_path)) == ["first", "one_signalled.py"]


def test_a_signal_once_the_outputs_are_in_place_is_said_and_the_run_ends_as_it_would():
    """After `settle` a signal is said in one line and nothing is raised; a process that
    starts the handlers again (`install`) is back to raising."""
    previous = interrupts.install()
    try:
        interrupts.settle()
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.3)
    finally:
        interrupts.restore(previous)
    previous = interrupts.install()
    try:
        _raised_on(signal.SIGINT, KeyboardInterrupt)
    finally:
        interrupts.restore(previous)


def test_a_second_signal_once_the_outputs_are_in_place_ends_the_process_at_once():
    """The first signal after `settle` is said and the run goes on to its end; the second
    ends the process with the signal's code (an exit that would hang stays stoppable)."""
    script = ("import os, signal, time\n"
              "from membranes.app import interrupts\n"
              "interrupts.install()\n"
              "interrupts.settle()\n"
              "os.kill(os.getpid(), signal.SIGTERM)\n"
              "time.sleep(0.2)\n"
              "print('went on', flush=True)\n"
              "os.kill(os.getpid(), signal.SIGTERM)\n"
              "time.sleep(5.0)\n"
              "print('not here')\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         env=_env(), cwd=ROOT, timeout=60)
    assert run.returncode == 143, run.stderr
    assert run.stdout == "went on\n"
    assert run.stderr.strip().splitlines() == [
        "membranes: terminated after the outputs were written (they are whole); the run ends "
        "with its own exit code"]


def test_ctrl_c_after_the_outputs_are_written_leaves_the_exit_code_the_runs(tmp_path):
    """Ctrl-C as the summary line comes (the outputs moved in just before): the run used to
    end with 130 and `membranes: interrupted`, which say that nothing was written, or with
    -2 from the interpreter's exit (Python's finalisation puts back SIGINT's default action
    before MPI and PETSc finish); its outputs are whole and it ends with 0. The signal is
    said in one line where it comes before the exit has begun; the exit ignores it."""
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "membranes.app.cli", "solve", "--h", "0.2",
                             "--levels", "2", "--out", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    for line in proc.stdout:
        if line.startswith("{"):
            proc.send_signal(signal.SIGINT)
            break
    err = proc.communicate(timeout=120)[1]
    assert proc.returncode == 0, err
    assert sorted(os.listdir(out)) == ["history.csv", "solution.h5", "solution.xdmf",
                                       "summary.json"]
    assert json.loads((out / "summary.json").read_text())["converged"] is True
    last = err.strip().splitlines()[-1]
    assert last.startswith(("membranes: interrupted after the outputs", "writing the outputs"))
    assert "Traceback" not in err


@pytest.mark.parametrize("fd", [0, 1, 2], ids=["stdin", "stdout", "stderr"])
def test_a_closed_standard_stream_is_as_if_discarded(tmp_path, fd):
    """`membranes ... >&-` (and `<&-`, `2>&-`): the run goes on as with /dev/null there; with
    stdout closed ufl's import failed on sys.stdout None (a traceback, exit 1); with stderr
    closed the progress lines went to stdout (print's default for a file of None), before
    the summary line that is stdout's only line."""
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "membranes.app.cli", "solve", "--h", "0.4",
                           "--levels", "0", "--out", str(out)], env=_env(), cwd=ROOT,
                          preexec_fn=lambda: os.close(fd), timeout=120,
                          stdin=subprocess.DEVNULL if fd else None,
                          stdout=subprocess.PIPE if fd != 1 else None,
                          stderr=subprocess.DEVNULL if fd != 2 else None, text=True)
    assert proc.returncode == 0
    if fd != 1:
        assert len(proc.stdout.splitlines()) == 1 and json.loads(proc.stdout)["converged"]
    assert sorted(os.listdir(out)) == ["history.csv", "solution.h5", "solution.xdmf",
                                       "summary.json"]
