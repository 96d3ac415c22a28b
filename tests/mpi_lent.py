"""Run by tests/test_parallel.py under `mpirun -n 2`: the lent core (membranes.pipeline). Process
0 waits for a reply with nothing else to do (Link.receive): it tells the estimator process so,
which then gets an executor (Lent) whose thread runs on process 0's cores, and gets none once
it has replied (process 0 is busy again). Process 0 writes what both saw, as JSON, to the file
named on the command line."""

import json
import os
import sys
import time

from mpi4py import MPI

from membranes import pipeline

comm = MPI.COMM_WORLD
est_comm, link, lent = pipeline.roles(comm)
if comm.rank == 0:
    seen = link.receive()                  # no reply yet: process 0 says it waits, asleep
    seen["process_0_cores"] = sorted(os.sched_getaffinity(0))
    link.close()
    with open(sys.argv[1], "w") as f:
        json.dump(seen, f)
else:
    before = lent()                        # nothing said yet (or already: either is right)
    start, pool = time.perf_counter(), None
    while pool is None and time.perf_counter() - start < 60:
        pool = lent()
    thread_cores = None if pool is None else \
        sorted(pool.submit(os.sched_getaffinity, 0).result())
    comm.send(("values", {"lent": pool is not None, "thread_cores": thread_cores,
                          "own_cores": sorted(os.sched_getaffinity(0))}),
              dest=0, tag=pipeline.REPLY)
    lent.replied += 1
    after = lent()                         # stale: process 0 has its reply
    kind, _, _ = comm.recv(source=0, tag=pipeline.WORK)
    comm.send(("after", after is None, kind), dest=0, tag=99)
    lent.close()
    est_comm.Free()
if comm.rank == 0:
    after_none, kind = comm.recv(source=1, tag=99)[1:]
    with open(sys.argv[1]) as f:
        seen = json.load(f)
    seen.update(after_reply_none=after_none, end_kind=kind)
    with open(sys.argv[1], "w") as f:
        json.dump(seen, f)
