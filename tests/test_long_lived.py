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


if __name__ == "__main__":
    result = main()
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(result), flush=True)
