"""Run by tests/test_parallel.py under `mpirun` in front of each program it tests (a script's
path, or `-m module`, then its arguments): on SIGUSR1 every thread's Python stack goes to
stderr (faulthandler), so that a run that does not end says where each process waits (the
test sends the signal before it ends such a run, and shows what came)."""

import faulthandler
import runpy
import signal
import sys

faulthandler.register(signal.SIGUSR1, all_threads=True)
args = sys.argv[1:]
if args[0] == "-m":
    sys.argv = args[1:]
    runpy.run_module(args[1], run_name="__main__", alter_sys=True)
else:
    sys.argv = args
    runpy.run_path(args[0], run_name="__main__")
