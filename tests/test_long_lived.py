"""The API in a long-lived process and on communicators (membranes.app.driver.solve).

* A progress callable runs on process 0 only: an exception it raises must stop the run on
  every process (`model.progress.reporter`), not leave the others waiting for process 0 in the
  run's next collective call for ever (they did: a hang under mpirun), and the processes
  must be able to solve again with the same answer.
* Scenes on sub-communicators (`comm=`): under mpirun -n 3, processes 0-1 solve one problem
  together and process 2 another alone, each as it would on its own.

Run as a script under mpirun, `main()` returns every process's figures on process 0, which
prints them as one JSON line. The figures compared are those of exact Newton with MUMPS, whose
iterates do not depend on the partition: the default adaptive run's do (BoomerAMG's Krylov
iterates depend on it, and with them where the run stops; the disk's 2-process partition is
not the same from run to run), and its Newton count once differed from the serial one.
"""

import json
import os

import pytest
from mpi4py import MPI

from membranes import scenes, solve

EXACT = {"newton": "exact", "solver": "direct"}


def figures(sol):
    return [sol.newton_iterations, sol.estimates["eta"], sol.energy_error]


def failing_progress():
    """A progress callable that raises at its third line."""
    lines = []

    def say(line):
        lines.append(line)
        if len(lines) == 3:
            raise OSError("the log is full")
    return say


def main():
    world = MPI.COMM_WORLD
    out = {"rank": world.rank}
    problem = scenes.disk(h=0.3, levels=2)
    try:
        solve(problem, progress=failing_progress())
        out["raised"] = None
    except Exception as e:
        out["raised"] = f"{type(e).__name__}: {e}"
    out["again"] = figures(solve(problem, **EXACT))
    comm = world.Split(0 if world.rank < 2 else 1, world.rank)
    out["split"] = figures(solve(scenes.disk(h=0.3, levels=2, comm=comm), **EXACT))
    comm.Free()
    return world.gather(out)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_progress_error_and_sub_communicators_on_three_processes():
    serial = figures(solve(scenes.disk(h=0.3, levels=2), **EXACT))
    from .conftest import mpirun  # (not at the top: this file runs as a script too)
    proc = mpirun([os.path.abspath(__file__)], processes=3)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    outs = json.loads(proc.stdout.strip().splitlines()[-1])
    assert [o["rank"] for o in outs] == [0, 1, 2]
    assert outs[0]["raised"] == "OSError: the log is full"
    for o in outs[1:]:
        assert o["raised"] == ("RuntimeError: the progress callable failed on process 0: "
                               "OSError: the log is full")
    # the same Newton steps end on the same active set, whose linear system MUMPS solves on
    # any partition to round-off (ε times a condition ≲ 1e3): η and the energy error, smooth
    # functions of that iterate, agree to 1e-10 (measured ≤ 2e-14)
    for o in outs:
        for run in ("again", "split"):
            n, eta, err = o[run]
            assert n == serial[0], (o["rank"], run, n)
            assert abs(eta - serial[1]) <= 1e-10 * serial[1], (o["rank"], run, eta)
            assert abs(err - serial[2]) <= 1e-10 * serial[2], (o["rank"], run, err)
    # process 2 alone: the serial run, to the round-off of MUMPS's solves (two processes'
    # factorisations may differ in their last bits: 1 ulp of η seen)
    n, eta, err = outs[2]["split"]
    assert n == serial[0] and abs(eta - serial[1]) <= 1e-12 * serial[1]
    assert abs(err - serial[2]) <= 1e-12 * serial[2]


class OneOfTwo:
    """What `reporter` asks of a communicator, as process `rank` of two sees it: process 0's
    broadcast is what process 0 sends (`sent`), the others' what process 0 sent them
    (`received`)."""
    size = 2

    def __init__(self, rank, received=None):
        self.rank, self.received, self.sent = rank, received, []

    def bcast(self, obj, root=0):
        assert root == 0
        if self.rank == 0:
            self.sent.append(obj)
            return obj
        return self.received


def test_progress_lines_and_their_failures_on_each_process():
    """`reporter` on two processes, each side alone: process 0 writes the line and sends
    None, or the failure of its callable, which it raises itself; process 1 writes nothing
    and raises what process 0 sent: a KeyboardInterrupt as one (Ctrl-C in the callable stops
    every process as Ctrl-C), anything else as a RuntimeError naming it."""
    from membranes.model.progress import reporter
    lines = []
    comm = OneOfTwo(0)
    reporter(lines.append, comm)("a line")
    assert lines == ["a line"] and comm.sent == [None]

    def interrupted(line):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        reporter(interrupted, comm)("a line")
    assert comm.sent[-1] == ("KeyboardInterrupt", "")
    say = reporter(failing_progress(), comm)
    say("1")
    say("2")
    with pytest.raises(OSError, match="^the log is full$"):
        say("3")
    assert comm.sent[-1] == ("OSError", "the log is full")

    reporter(lines.append, OneOfTwo(1))("not here")
    assert lines == ["a line"]
    with pytest.raises(KeyboardInterrupt):
        reporter(lines.append, OneOfTwo(1, ("KeyboardInterrupt", "")))("not here")
    with pytest.raises(RuntimeError, match=r"^the progress callable failed on process 0: "
                                           r"OSError: the log is full$"):
        reporter(lines.append, OneOfTwo(1, ("OSError", "the log is full")))("not here")
    assert lines == ["a line"]


def some_solve():
    """A problem of all processes, then one of processes 0-1 alone while process 2 solves
    nothing: every process's figures (None on process 2) gathered on process 0."""
    world = MPI.COMM_WORLD
    solve(scenes.disk(h=0.3, levels=1), **EXACT)
    comm = world.Split(0 if world.rank < 2 else 1, world.rank)
    out = figures(solve(scenes.disk(h=0.3, levels=1, comm=comm), **EXACT)) \
        if world.rank < 2 else None
    comm.Free()
    return world.gather(out)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_a_sub_communicator_solves_while_a_process_does_not():
    """Processes 0-1 solve on their sub-communicator after a problem of all three, while
    process 2 takes no part: their clean-ups (membranes.app.garbage) are collective on the
    communicators of the meshes whose processes all take part only, not on those of the
    earlier problem of three (that waited for process 2 for ever: a hang under mpirun). Both
    report the serial run's Newton steps."""
    serial = figures(solve(scenes.disk(h=0.3, levels=1), **EXACT))
    from .conftest import mpirun  # (not at the top: this file runs as a script too)
    proc = mpirun([os.path.abspath(__file__), "some"], processes=3)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    outs = json.loads(proc.stdout.strip().splitlines()[-1])
    assert outs[2] is None and outs[0] == outs[1] and outs[0][0] == serial[0]


if __name__ == "__main__":
    import sys
    result = some_solve() if sys.argv[1:] == ["some"] else main()
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(result), flush=True)
