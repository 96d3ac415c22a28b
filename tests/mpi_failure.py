"""Run by tests/test_parallel.py under `mpirun -n P`: an adaptive run on the small disk in
which one process fails, and what every process makes of it.

Arguments: <out> [FAIL [slow]]. FAIL (the last rank by default) is the process that fails:
an estimator process fails at its first evaluation (an injected RuntimeError, before its
partial flux is added to the others'), while the others evaluate on; process 0 (FAIL = 0)
fails at its second Newton step, with iterates sent and not yet estimated. With `slow` the
leader (membranes.pipeline.LEADER) takes each message 0.3 s late once it has told process 0
of the failure (with FAIL = 0: from the start), so that process 0 ends the run before the
leader has taken in the iterates it sent. Every process writes what `solve` raised to
`<out>.<rank>.txt`; process 0 writes the shared-memory files of its run still there once
every process is done to `<out>.left.txt`."""

import glob
import os
import sys
import time

from mpi4py import MPI

from membranes import estimators, newton, pipeline, scenes, solve

comm = MPI.COMM_WORLD
fail = int(sys.argv[2]) if len(sys.argv) > 2 else comm.size - 1
slow = "slow" in sys.argv[3:]

if comm.rank == fail and fail > 0:
    def evaluate(self, *args, **kwargs):
        raise RuntimeError("injected failure")
    estimators.Estimators.evaluate = evaluate
elif comm.rank == fail:
    steps = []
    linear_step = newton.linear_step

    def failing_linear_step(*args, **kwargs):
        steps.append(1)
        if len(steps) == 2:
            raise RuntimeError("injected failure")
        return linear_step(*args, **kwargs)
    newton.linear_step = failing_linear_step


class LateLeader(MPI.Intracomm):
    """COMM_WORLD whose leader takes each message 0.3 s late once it has told process 0 of
    a failure (with FAIL = 0: from the start)."""
    told = fail == 0

    def send(self, obj, *args, **kwargs):
        if isinstance(obj, tuple) and obj[0] == "error":
            LateLeader.told = True
        return super().send(obj, *args, **kwargs)

    def recv(self, *args, **kwargs):
        if self.rank == pipeline.LEADER and LateLeader.told:
            time.sleep(0.3)
        return super().recv(*args, **kwargs)


try:
    solve(scenes.disk(h=0.3, levels=1, comm=MPI.COMM_SELF), newton="adaptive",
          comm=LateLeader(comm) if slow else comm)
    raised = "nothing"
except Exception as e:
    raised = f"{type(e).__name__}: {e}"
with open(f"{sys.argv[1]}.{comm.rank}.txt", "w") as f:
    f.write(raised)
pid = comm.bcast(os.getpid(), root=0)
comm.Barrier()
if comm.rank == 0:
    with open(f"{sys.argv[1]}.left.txt", "w") as f:
        f.write(" ".join(glob.glob(os.path.join(pipeline._shm_dir(), f"membranes-{pid}-*"))))
