"""Several MPI processes: Newton on process 0, the estimators on the others (issue 6).

Under ``mpirun -n P membranes solve ...`` every process builds the whole problem on
``MPI.COMM_SELF`` (the mesh and its hierarchy are replicated: `parallel.check_replicated`),
and the work is split by kind, not by mesh:

* process 0 runs the method: discretisation, semismooth Newton, GMRES, the energy error and
  the progress lines; each iterate it records goes to the estimator processes (`Link`);
* processes 1 … P-1 (the *estimator processes*) discretise each level too, set up its
  estimators (DESIGN §5–§7: the flux equilibration, the multilevel flux) and evaluate them
  at every iterate they receive (`serve`): with P ≥ 3 they share the vertex patches among
  themselves (`parallel.owned_vertices`, `parallel.Summation`), patches on either side of
  the cut included.

The two kinds overlap. The set-up of a level's estimators runs while process 0 solves for
the level's exact mean (membranes.mean, with vertex_amg on the eliminated system) and takes
the first Newton step, and an iterate's estimates are computed while process 0 already
computes the next Newton step. The estimator processes assemble no stiffness matrix (X⁰'s
residual comes with X⁰).

**Waits filled.** Each side fills its waits with the mesh-only work of the levels to come
of a nested run, a part at a time (0.1-0.4 s each at 9.3e5 vertices):

* process 0, while it waits for estimates, makes the finer levels in turn: their
  discretisation (discretisation.discretise_in_parts), linear rows and prolongation
  (`Link.meanwhile`, membranes.driver._Ahead), then the next level's mean multigrid (0.18 s:
  it needs the running level's M); it solves a level's M when the level begins, and makes
  no part while it waits for the 'finish' reply, which is on its way;
* the estimator processes, when no message is waiting, discretise the level they serve
  next, which process 0 names ('ahead'). They take D, F1, F2 and the boundary vertices
  from process 0 (`Link.ship`, sent once each level's discretisation is made: the same
  numbers) and make only the space and the data measures: at 9.3e5 vertices 0.27 s instead
  of 0.87 s. Before, the estimator process was busy all of level 5 and still discretising
  when the finest level began (0.3 s late for its set-up); J = 6, alternating runs on a
  machine where the estimator process is the critical path (2026-11-22): 10.81-11.22 s
  against 11.59-12.43 s (four each; serial 17.6-17.9 s). Where the arrays have not come
  when the space and the data measures are made, the parts wait for them (SHIPMENT: no part
  of the level runs until the 'disc' message, which comes before the level's 'level'
  message) instead of making them: at first they made the missing ones, which at the finest
  level's start was most of the time D, F1 and F2 (0.18-0.28 s parts, some while level 5's
  iterates waited); waiting, J = 6 took 10.25-10.83 s against 10.70-11.27 s (seven
  alternating rounds, fourth session of 2026-11-22).

A part once begun runs to its end, so a message that comes meanwhile waits for it. The parts
lengthen the lower levels (the estimator process then waits for iterates) but shorten the
finest, where process 0 was the critical path. At 9.3e5 vertices (disk, J = 6, 2
processes, a scene run without its exact solution):

* Before (8.2-8.4 s for the finest level), process 0 spent 0.9 s discretising, 0.2 s on rows
  and prolongation and 0.8 s on the mean before its first step. Then came steps of 2.0, 1.5
  and 1.5 s, and the wait for X³'s estimate (1.05 s). The estimator process was set up
  (0.8 s discretisation + 2.8 s) 0.3-0.4 s before X¹ came.
* Now the finest level takes 6.5-7.0 s. Process 0 begins it with its parts made and solves
  M (0.6 s). The estimator process, its discretisation made or nearly, sets up in 2.8 s and
  is ready about when X¹ comes (0.2 s after). Levels 0-5 take 3.5 s instead of 3.0-3.2 s.
* The whole run: 10.75-11.1 s against 11.3-11.7 s (alternating runs, 2026-11-22).

Both kinds are now busy most of the finest level. Process 0 computes X³ while X¹'s
estimate is still to come (two steps ahead of the test: membranes.newton), and the
estimator process sets up for 2.8-4.2 s first (the longer on machines where the two
processes slow each other down most: two serial runs side by side took 21.6 s each here,
against 18.6 s alone).

What is made ahead was measured (J = 6, 2 processes). More ahead lengthens the lower
levels by more than it saves:

* Process 0 making each level's mean too, as its last part, and making parts in the wait
  for 'finish' as well: 10.81-10.83 s. The finest mean is a 0.6 s part that outlasts the
  wait, and the estimator process becomes the critical path.
* The next level's mean only, made once every finer level's parts are made: 10.93 s. The
  finest level began 0.6 s late, and the estimator process's set-up with it.
* The estimator process discretising every level it will serve from the start: 10.98-11.1
  s against 10.59-10.98 s (alternating runs). Its 0.2 s parts of the finest level delay the
  coarse levels' 0.01 s estimates.
* Making only the next level (none further): 10.75-11.06 s (two runs). Process 0 has
  little wait on level 5, so most of the finest level's parts are left for its start.
* The estimator process making the finest level's loads (its own discretisation of it,
  D, F1 and F2 included) from level 1 on, and process 0 taking F1 and F2 made (simulated:
  read from a file): 12.64 s against 12.77 s on average (five alternating rounds, third
  session of 2026-11-22; 11.78-12.89 s against 12.10-13.09 s): no gain. In one timeline
  level 2 took 1.03 s instead of 0.26 s (the estimator process busy with those parts, its
  estimates waiting), levels 3 and 4 0.95 s instead of 1.51 s.
* The next level's M itself in parts (conjugate gradients written out, one iteration a
  part, with parts also in the wait for 'finish'): in one timeline process 0 began the
  finest level with 0.13 s of M left instead of 0.64 s, but the estimator process's set-up
  then began late and the level took as long. Not kept: no gain could be shown (the
  machine's timings drifted by 10-30 % at the time).

Where to solve the exact mean was measured. Session 17 had the leader solve for it (then
1.8 s with its own AMG) before its set-up while process 0 computed the first step's
gap and λ (which do not need M): the estimator process was then the critical path, and the
run took 14.6-18.7 s where the same mean on process 0 took 13.7-15.7 s (five alternating
runs each). With the mean's multigrid (0.8 s) the leader's way was tried again: the leader
then discretised with the stiffness matrix (1.2 s instead of 0.8 s) and solved M (0.9 s)
before its set-up (2.9 s), so X¹'s estimate started 5.1 s into the finest level, and process
0, without the mean, had X² 0.7 s before that estimate was in and waited for it; the level
took 9.1 s against 8.2-8.4 s (a process 0 that computed two steps ahead of the test would
have saved the wait: about 0.2 s left, not pursued). With process 0 two steps ahead, the
estimator process making the finest level's mean multigrid and M (0.7 s) before its set-up
was simulated (fourth session of 2026-11-22, four alternating rounds): 11.73-12.13 s against
11.31-13.09 s, no gain; the estimator process became the critical path.

The data oscillation is computed where the estimators are set up, from the load moments the
flux set-up has anyway (when process 0 computed it, with moments of its own, 2.9 s of its
time, the finest level took 15.6 s instead of 14.0 s).

Only what the method decides from the estimates waits for them:

* exact and inexact Newton never wait (their stopping tests are the residual's); the
  estimates of a level are collected when its Newton run ends (`RemoteEstimates.finish`);
* adaptive Newton's stopping test at X^{k-1} needs η_lin, η_disc of X^{k-1}: process 0
  computes step k meanwhile (membranes.newton: a step computed ahead) and takes the test
  when they come; if it is met, step k is dropped. Where no Krylov iterate is handed out,
  process 0 records X^k while the test at X^{k-1} is still to come and computes step k+1
  (two steps ahead); the estimator processes take the same test at each Newton iterate
  they estimate ('level' carries γ_lin) and, once it is met, skip the level's later
  iterates, which process 0 drops (`RemoteEstimates.forget`). Where the test is likely met
  (the ratio η_lin/η_disc of the iterates before contracts below a bound) process 0 waits
  instead. The criterion that stops GMRES needs the estimates of the Krylov iterate it is
  made on, so a Krylov iterate handed out every ν steps waits for its estimates (with
  vertex_amg, GMRES reaches round-off before ν: none
  is handed out).

**Process 0's core lent.** Where the two processes of a run share a node (P = 2), process 0
that waits for a reply with nothing else to do (no part left: at the finest level, for the
estimate of the iterate that meets the adaptive test, 1.0-1.2 s at 9.3e5 vertices) tells the
estimator process so (an IDLE message with the number of replies it has taken) and waits
asleep, looking for the reply every millisecond: a blocking receive of Open MPI polls and
keeps its core busy. Until its next reply the estimator process runs the passes of its
estimates on two threads (`Lent`, Estimators.helper): the cell passes in two halves
(parallel.in_two), the classes' products a chunk ahead of their scatters
(algebraic_flux._apply_buckets). The second thread runs on process 0's cores (mpirun binds
each of two processes to a core of its own), and the compiled kernels release the GIL
(membranes.compiled). Every item is computed by the same code and every sum keeps its
order: the numbers are those of one thread. At 9.3e5 vertices (disk, J = 6) the last
estimate took 0.71-0.80 s instead of 1.01-1.07 s, and the run 10.35-11.48 s against
11.07-11.80 s (six alternating rounds, in two of which one run of the pair fell into a slow
spell of the machine: 13.37 s, 14.94 s; medians 11.14 s and 11.70 s; fifth session of
2026-11-22). The
estimator process's set-up and the estimates that run beside Newton steps keep one thread:
process 0 is busy then.

**Fresh pages.** Two processes side by side pay more for memory they take anew (a page fault
per 4 KiB at its first write: before, the estimator process spent 2.2 s of a 11.6 s run in
the kernel). The passes that run at every Newton step or estimate write into arrays kept from
one call to the next (membranes.kept): the eliminated system, σ_disc and the cell parts. J =
6 on 2 processes: 9.50-9.94 s against 10.22-10.68 s (six alternating rounds), serial runs
unchanged.

Every process runs the same code on the same data as a serial run, in the same order: with
P = 2 the iterates, the estimates and every decision taken from them are those of one
process bit for bit; with P ≥ 3 the estimates differ from them by the order in which the
patch contributions are summed (round-off). A record's wall time is that of process 0 when
it recorded the iterate, and for the iterate that stops an adaptive run, when its estimates
were in (waiting included).

**Flow.** Process 0 goes on with at most AHEAD = 3 iterates sent and not yet estimated;
beyond, it waits (exact and inexact runs hand out a Krylov iterate every ν steps, and their
estimates may take longer than the ν steps: without a bound the iterates in transit would
pile up in memory).

**Failure.** An estimator process that raises tells process 0 (through the leader), which
raises RuntimeError naming the process and its error, and every process ends the run with
it. With P ≥ 3 its partners may be waiting for its partial flux in a collective
(`parallel.Summation`): the failing process meets them there with its error
(`parallel.agree`, also the checkpoint at the end of every message), so that they stop too
instead of waiting for ever (tests/test_parallel.py injects a failure). The messages that
come after a failure, up to process 0's 'end', are taken in and not served; the leader
removes their files unread (process 0 leaves the files it sent to the leader: it once removed
those not yet read when it ended a run, and a leader that took them in after that failed
outside the loop, leaving its partner waiting in a broadcast for ever).

**Transport.** An iterate and its residual are 6N numbers (45 MB at 9.3e5 vertices). MPI
moves a large message only while both sides are inside MPI calls (measured with Open MPI 4.1
here: an `Isend` of 22 MB completed 2.9 s later, when the sender next called MPI), and
process 0 is in PETSc then. So where the processes share a node, the arrays go through a file
in shared memory (/dev/shm) that the receiver reads and removes, and the message that names
it is small (it leaves at once); across nodes they go in the message itself. Whether a
message is here is asked twice (`_here`): Open MPI's Iprobe looks before it takes in what has
come, and one look missed messages 0.1-0.35 s old.
"""

import os
import tempfile
import time

import numpy as np

from . import parallel
from .newton_system import initial_residual

WORK, REPLY = 71, 72            # message tags: process 0 → estimators, and back
IDLE = 73                       # process 0 → the leader: it waits, its core is free (`Lent`)
IDLE_POLL = 0.001               # s between process 0's looks for the reply while it waits idle
LEADER = 1                      # the estimator process that talks to process 0
AHEAD = 3                       # iterates process 0 may send before their estimates are back


def roles(comm):
    """(estimator communicator, link, lent): on process 0 (None, its Link to the estimator
    processes, None); on the others (their communicator, None, lent). Where there are two
    processes on one node, process 0 lends its core to the estimator process while it waits:
    `lent` is then the estimator process's `Lent`, else None. Collective over comm."""
    same_node = _same_node(comm)
    cores = comm.bcast(_cores(), root=0)
    lend = same_node and comm.size == 2
    est_comm = comm.Split(0 if comm.rank == 0 else 1, comm.rank)
    if comm.rank == 0:
        est_comm.Free()
        return None, Link(comm, same_node, lend), None
    return est_comm, None, Lent(comm, cores) if lend else None


def _cores():
    """The cores this process (its calling thread) may run on, None where unknown: mpirun
    binds each of two processes to a core of its own."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def _shm_dir():
    return "/dev/shm" if os.path.isdir("/dev/shm") else tempfile.gettempdir()


def _same_node(comm):
    from mpi4py import MPI
    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    same = node.size == comm.size
    node.Free()
    return comm.allreduce(same, op=MPI.LAND)


def _here(comm, source, tag):
    """Whether a message from source with tag is here. Open MPI's Iprobe (4.1, ob1) looks
    among the messages it has taken in, and only then takes in what has come since: a message
    that came while this process computed is found by the second look (measured: one look
    missed messages 0.1-0.35 s old)."""
    return comm.Iprobe(source=source, tag=tag) or comm.Iprobe(source=source, tag=tag)


def _pack(arrays, directory, name):
    """The arrays (None allowed) written to one file, one after the other (a concatenated
    copy first took 35-140 ms for an iterate and its residual at 9.3e5 vertices, this 20 ms);
    returns what `_unpack` needs."""
    sizes = [None if a is None else len(a) for a in arrays]
    path = os.path.join(directory, name)
    with open(path, "wb") as f:
        for a in arrays:
            if a is not None:
                np.ascontiguousarray(a, dtype=np.float64).tofile(f)
    return ("file", path, sizes)


def _discard(packed):
    """Remove the file of a message not read (`_pack`; none for an inline message). Called
    once the run has failed, where nothing may raise (the leader would leave `serve` and its
    partners waiting): a file already gone is left at that."""
    if packed[0] == "file":
        try:
            os.unlink(packed[1])
        except FileNotFoundError:
            pass


def _unpack(packed):
    if packed[0] != "file":
        return packed[1]
    _, path, sizes = packed
    data = np.fromfile(path, dtype=np.float64)
    os.unlink(path)
    out, at = [], 0
    for n in sizes:
        out.append(None if n is None else data[at:at + n])
        at += 0 if n is None else n
    return out


class Link:
    """Process 0's side of the messages to the estimator processes."""

    def __init__(self, comm, same_node, lend=False):
        self.comm = comm
        self.directory = _shm_dir() if same_node else None
        self.requests, self.count = [], 0
        self.meanwhile = None   # work for the waits: a call that does a part, False if none
        self.lend = lend        # tell the leader when this process waits idle (`Lent`)
        self.taken = 0          # replies received

    def post(self, kind, *payload, arrays=()):
        """Send (kind, payload, arrays) without waiting for the receiver."""
        self.count += 1
        if self.directory is not None and arrays:
            name = f"membranes-{os.getpid()}-{self.count}"
            packed = _pack(arrays, self.directory, name)
        else:
            packed = ("inline", list(arrays))
        self.requests.append(self.comm.isend((kind, payload, packed), dest=LEADER, tag=WORK))
        self.requests = [r for r in self.requests if not r.Test()]

    def ship(self, level, disc):
        """Send level's D, F1, F2 and boundary (`disc`, process 0's discretisation): the
        estimator processes then do not make them again (`serve`)."""
        self.post("disc", level, arrays=(disc.D, disc.F1, disc.F2,
                                         disc.boundary.astype(np.float64)))

    def ready(self):
        """Whether a reply is here."""
        return _here(self.comm, LEADER, REPLY)

    def receive(self, meanwhile=True):
        """The next reply's estimates; RuntimeError if the estimator processes failed. Until
        it is here, the `meanwhile` parts are done (`meanwhile`: a nested run's finer levels
        made ahead, membranes.driver._Ahead), one at a time while none has come."""
        while meanwhile and self.meanwhile is not None and not self.ready():
            if not self.meanwhile():
                self.meanwhile = None
        if self.lend and not self.ready():
            # nothing to do until the reply: the leader may use this core meanwhile (`Lent`),
            # so wait asleep (a blocking receive of Open MPI polls and keeps the core busy);
            # each call takes one reply, so the leader is told once per reply awaited
            self.requests.append(self.comm.isend(self.taken, dest=LEADER, tag=IDLE))
            while not self.ready():
                time.sleep(IDLE_POLL)
        kind, payload = self.comm.recv(source=LEADER, tag=REPLY)
        self.taken += 1
        if kind == "error":
            raise RuntimeError(f"estimator processes: {payload}")
        return payload

    def close(self):
        """End the estimator processes' loop. The leader removes every file it is sent, read
        or, after a failure, unread (`serve`), in the order of the messages, before 'end': a
        file removed here could be one it has still to take in (process 0 that fails, or that
        an estimator process's failure ends, has iterates in transit)."""
        self.post("end")
        for r in self.requests:
            r.Wait()


class Lent:
    """The leader's side of process 0's idle core (two processes on one node): called before
    each pass of an estimate (Estimators.helper), an executor with one thread (then the passes
    run on two cores: parallel.in_two) while process 0 waits for this process's next reply,
    else None. Process 0 tells it so (`Link.receive`: an IDLE message with the number of
    replies it has taken, stale once a later reply is sent); the numbers are those of one
    thread. The thread runs on process 0's cores (`cores`; mpirun binds each of two processes
    to one core, and a thread of this process would otherwise share this one)."""

    def __init__(self, comm, cores=None):
        self.comm, self.cores = comm, cores
        self.replied = 0        # replies sent
        self.idle_at = -1       # replies process 0 had taken when it last said it waits
        self.pool = None

    def __call__(self):
        while _here(self.comm, 0, IDLE):
            self.idle_at = self.comm.recv(source=0, tag=IDLE)
        if self.idle_at != self.replied:
            return None
        if self.pool is None:
            from concurrent.futures import ThreadPoolExecutor
            self.pool = ThreadPoolExecutor(1, thread_name_prefix="membranes-lent-core",
                                           initializer=self._to_cores)
        return self.pool

    def _to_cores(self):
        if self.cores is not None:
            try:
                os.sched_setaffinity(0, self.cores)     # this thread only (Linux)
            except OSError:
                pass

    def close(self):
        """Take the IDLE messages still here (none is left in transit), end the thread."""
        while _here(self.comm, 0, IDLE):
            self.comm.recv(source=0, tag=IDLE)
        if self.pool is not None:
            self.pool.shutdown()


class RemoteEstimates:
    """Process 0's stand-in for the driver's IterateEstimates of one level: the same calls,
    served by the estimator processes (`serve`). A record handed in is *awaited* until its
    estimates are back (`awaiting`, `resolve`); an adaptive run's Krylov iterates wait for
    theirs (the criterion that stops GMRES reads them at once)."""

    def __init__(self, link, level, alg_flux, adaptive, gamma_lin=None):
        self.link, self.adaptive = link, adaptive
        self.multilevel = True if alg_flux == "multilevel" else None
        self.setup_time, self.time, self.eta_K = 0.0, 0.0, None
        self.rows = None            # the level's LinearRows, once process 0 has them
        self.ids, self.waiting, self.then, self.calls, self.replied = {}, {}, {}, 0, 0
        link.post("level", level, alg_flux, gamma_lin if adaptive else None)

    def __call__(self, rec, X, R, same_as=None):
        if R is None:       # X^0: its residual needs E, which the estimator processes lack
            R = initial_residual(self.rows, X)
        rid = len(self.ids)
        self.ids[id(rec)] = rid
        self.waiting[rid] = (rec, X, R)
        self.link.post("call", rid, dict(rec), None if same_as is None else
                       self.ids[id(same_as)], arrays=(X, R))
        self.calls += 1
        if not (self.adaptive and rec["kind"] == "krylov"):
            while self.calls - self.replied > AHEAD:    # the estimator processes lag behind
                self._take()
            return []
        while True:
            call, ready = self._take()
            if call == self.calls:
                return ready

    def discretised(self, disc, rows):
        """Process 0 has the level's discretisation: keep its rows (X⁰'s residual needs E,
        which the estimator processes lack)."""
        self.rows = rows

    def _awaited(self, rec):
        """Whether rec was handed in and its estimates are not back (no reply taken)."""
        return self.ids.get(id(rec)) in self.waiting

    def awaiting(self, rec):
        """Whether rec's estimates are still to come (the replies already here applied)."""
        while self._awaited(rec) and self.link.ready():
            self._take()
        return self._awaited(rec)

    def resolve(self, rec):
        """Wait until rec's estimates are back."""
        while self._awaited(rec):
            self._take()

    def forget(self, rec):
        """rec was dropped (a step computed ahead of a test that was met: membranes.newton):
        its estimates, if they come, are not applied, and nothing waits for them."""
        rid = self.ids.get(id(rec))
        self.waiting.pop(rid, None)
        self.then.pop(rid, None)

    def when_complete(self, rec, action):
        """action(rec) now if rec is complete, else when its estimates come back."""
        if self._awaited(rec):
            self.then[self.ids[id(rec)]] = action
        else:
            action(rec)

    def finish(self):
        """Estimate the iterate still waiting for a later one, and collect every estimate."""
        self.link.post("finish")
        while True:     # no part meanwhile: the reply is on its way
            call, _ = self._take(meanwhile=False)
            if call == "finish":
                return

    def _take(self, meanwhile=True):
        """Apply the next reply of estimates: (its call number or 'finish', the records it
        completed)."""
        call, values, ready, extra = self.link.receive(meanwhile)
        if call != "finish":
            self.replied = call
        done = []
        for rid, v in values:
            if rid not in self.waiting:     # forgotten
                continue
            rec, X, R = self.waiting.pop(rid)
            rec.update(v)
            done.append((rid, (rec, X, R)))
        for rid, item in done:
            action = self.then.pop(rid, None)
            if action is not None:
                action(item[0])
        if extra is not None:
            self.setup_time, self.time, self.eta_K = extra
        done = dict(done)
        return call, [done[rid] for rid in ready if rid in done]


def serve(problem, comm, est_comm, lent=None):
    """The estimator processes' loop (module notes): build each level's IterateEstimates when
    process 0 starts the level, evaluate them at the iterates it sends, reply with the
    estimates; while no message waits, discretise the level process 0 named next ('ahead'),
    a part at a time (the leader decides, the partners follow: P ≥ 3); with `lent` (`roles`)
    use process 0's core too while it waits; returns (level, discretisation) of the
    last level served ((None, None) if none) when process 0 ends the run."""
    from .discretisation import SHIPMENT, completed, discretise, discretise_in_parts
    from .driver import RECORD_KEYS, IterateEstimates
    from .nested import level_problem
    from .newton import newton_criterion
    from .newton_system import linear_rows
    leader = est_comm.rank == 0
    shared = est_comm if est_comm.size > 1 else None
    est = disc = failed = level = None
    stopped = False
    ahead = parts = made = None     # the level served next, its discretisation's parts, it
    shipment_due = False            # its parts wait for process 0's arrays (SHIPMENT)
    shipped = {}                    # level -> (D, F1, F2, boundary) from process 0 (Link.ship)

    def given(j):
        return lambda: shipped.get(j)

    def reply(call, ready, extra=None):
        # every record handed in is complete after a call, except the one IterateEstimates
        # keeps waiting for its later iterate ('nu' flux)
        waiting = None if est.pending is None else id(est.pending[0])
        values = [(rid, {k: rec.get(k) for k in RECORD_KEYS})
                  for rid, rec in unsent.items() if id(rec) != waiting]
        for rid, _ in values:
            del unsent[rid]
        if leader:
            comm.send(("values", (call, values, [rid_of[id(r[0])] for r in ready], extra)),
                      dest=0, tag=REPLY)
            if lent is not None:
                lent.replied += 1

    while True:
        if leader:      # no message waiting: a part of the next level's discretisation
            # (none while it waits for process 0's arrays: they come as a message)
            idle = parts is not None and not (shipment_due and ahead not in shipped) and \
                not _here(comm, 0, WORK)
            message = ("part", None, None) if idle else comm.recv(source=0, tag=WORK)
        else:
            message = None
        if shared is not None:
            message = shared.bcast(message, root=0)
        kind, payload, packed = message
        if kind == "end":
            if lent is not None:
                lent.close()
            return level, disc
        if failed is not None:      # the run is over: messages are taken in, not served
            if leader:
                if kind != "part":
                    _discard(packed)
                if kind in ("call", "finish"):
                    comm.send(("error", failed), dest=0, tag=REPLY)
            continue
        arrays = _unpack(packed) if leader and kind != "part" else None  # the file first
        if shared is not None and kind != "part":
            arrays = shared.bcast(arrays, root=0)
        try:
            if kind == "disc":
                D, F1, F2, boundary = arrays
                shipped[payload[0]] = (D, F1, F2, boundary.astype(np.int32))
            elif kind == "ahead":
                ahead, made, shipment_due = payload[0], None, False
                parts = discretise_in_parts(level_problem(problem, ahead), stiffness=False,
                                            given=given(ahead))
            elif kind == "part":
                try:
                    shipment_due = next(parts) == SHIPMENT
                except StopIteration as done:
                    made, parts, shipment_due = done.value, None, False
            elif kind == "level":
                level, alg_flux, gamma_lin = payload
                stopped = False     # adaptive: a Newton iterate of this level met the test
                est = None          # the level below: freed before this one is built
                # no stiffness matrix: E's residuals come made (RemoteEstimates)
                if ahead == level:
                    disc = made if parts is None else completed(parts)
                else:
                    disc = discretise(level_problem(problem, level), stiffness=False,
                                      given=given(level))
                ahead = parts = made = None
                for j in [j for j in shipped if j <= level]:
                    del shipped[j]
                est = IterateEstimates(disc, linear_rows(disc), alg_flux, shared)
                est.est.helper = lent
                recs, rid_of, unsent, calls = {}, {}, {}, 0
                parallel.agree(shared)
            elif kind == "call":
                rid, rec, same_as = payload
                calls += 1
                if stopped:     # process 0 ends the level at an earlier iterate: not estimated
                    parallel.agree(shared)
                    reply(calls, [])
                    continue
                X, R = arrays
                recs[rid] = unsent[rid] = rec
                rid_of[id(rec)] = rid
                ready = est(rec, X, R, None if same_as is None else recs[same_as])
                # the adaptive test, as process 0 takes it at this level's Newton iterates in
                # order: once it is met, process 0 stops there (membranes.newton), and the
                # iterates it computed ahead meanwhile need no estimates
                stopped = gamma_lin is not None and any(
                    r["kind"] == "newton" and r.get("eta_lin") is not None and
                    newton_criterion(r, gamma_lin) for r in [rec] + [t[0] for t in ready])
                parallel.agree(shared)      # all went well everywhere: then reply
                reply(calls, ready)
            elif kind == "finish":
                est.finish()
                parallel.agree(shared)
                reply("finish", [], (est.setup_time, est.time, est.eta_K))
        except Exception as e:
            # agree on the failure with the partners (P ≥ 3: they may be waiting in a
            # collective for this process), tell process 0, then wait for its end
            parts = made = None
            failed = str(e) if isinstance(e, parallel.PartnerFailed) else \
                f"estimator process {comm.rank}: {type(e).__name__}: {e}"
            if not isinstance(e, parallel.PartnerFailed):
                try:
                    parallel.agree(shared, failed)
                except parallel.PartnerFailed as first:      # the first by rank
                    failed = str(first)
            if leader:
                comm.send(("error", failed), dest=0, tag=REPLY)
