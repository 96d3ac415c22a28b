"""Run by tests/test_parallel.py under `mpirun -n P`: an adaptive run on the small disk in
which the estimator process of rank FAIL (the last by default) fails at its first evaluation
(an injected RuntimeError, before its partial flux is added to the others'), while the others
evaluate on. Every process writes what `solve` raised to `<out>.<rank>.txt` (the first command
line argument is <out>; the second, if given, is FAIL)."""

import sys

from mpi4py import MPI

from membranes import estimators, scenes, solve

comm = MPI.COMM_WORLD
fail = int(sys.argv[2]) if len(sys.argv) > 2 else comm.size - 1

if comm.rank == fail:
    def evaluate(self, *args, **kwargs):
        raise RuntimeError("injected failure")
    estimators.Estimators.evaluate = evaluate

try:
    solve(scenes.disk(h=0.3, levels=1, comm=MPI.COMM_SELF), newton="adaptive", comm=comm)
    raised = "nothing"
except Exception as e:
    raised = f"{type(e).__name__}: {e}"
with open(f"{sys.argv[1]}.{comm.rank}.txt", "w") as f:
    f.write(raised)
