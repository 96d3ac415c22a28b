"""Ending a run on Ctrl-C, SIGTERM or SIGHUP as on any error: the staged outputs removed, one
line, no traceback (membranes.app.cli, membranes.app.outputs.staged_folder).

Python raises the exception of a signal at the next bytecode it runs, and that may be a
weakref callback or a `__del__` run by a deallocation, whose exceptions Python prints and
drops ("Exception ignored in …"): the run would go on. Under mpirun that is the common case
(a process waiting in an MPI call runs such callbacks first when the call returns, and
mpirun passes Ctrl-C on as SIGTERM, then kills the processes a moment later). So after a
signal the exception is raised again every RETRY seconds (SIGALRM) until code that handles it
says so (`caught`). And the folder a process is staging outputs in (`staging`) is removed by the
handler itself, at once: mpirun kills the processes about a second after its SIGTERM, which
may come before the exception has made its way up through MPI calls and clean-ups; so are
the C files of compilations the run leaves unfinished (membranes.fem.jit.abandon). Inside
a `deferred` block (the renames that move the outputs in, all or nothing) a signal waits for
the block's end. On several processes, the processes other than 0 (`among`) hold their raise
back FOLLOW seconds: process 0, the one that says the line, may be waiting for them in a
collective call, from which it would never come back to Python if they left it; they go on
until mpirun ends them once process 0 has gone.

Once the run's outputs are in place (`settle`: they move in all at once, at the end) a
signal no longer ends it as interrupted: what is left is printing its last lines and the
process's exit, and an exit code of 130 would say that nothing was written. The signal is
said in one line and the run ends with its own code; a second signal ends the process at
once (printing to a stream nobody reads, say). The process's exit ignores them (`restore`).
"""

import contextlib
import os
import shutil
import signal
import sys

RETRY = 0.05        # seconds between raises of a pending interrupt
FOLLOW = 2.0        # seconds before a process other than 0 raises (`among`): beyond the
                    # second mpirun gives the processes between its SIGTERM and its SIGKILL

_pending = None     # the exception class of the signal met, until `caught`
_deferring = 0      # inside `deferred` blocks: a signal is raised at the end of the outermost
staging = None      # the folder this process stages outputs in (outputs.staged_folder)
_follower = False   # one of several processes, not process 0 (`among`)
_settled = False    # the run's outputs are in place (`settle`): a signal no longer ends it
_late = None        # the exception class of the first signal after `settle` (said), if any
process_ends = False    # the process exits after the command (cli.command): `restore` then
                        # has a settled run's exit ignore the signals


class Terminated(KeyboardInterrupt):
    """SIGTERM: batch schedulers send it before they kill a job at its time limit, and Open
    MPI's mpirun passes Ctrl-C on to the processes as SIGTERM. A KeyboardInterrupt, so that
    it ends the run as Ctrl-C does."""


class HungUp(Terminated):
    """SIGHUP: the terminal or the ssh session of the run has gone. Ends the run as SIGTERM
    does (PETSc's initialisation sets a handler of its own for it, `take_back`)."""


def _raise_pending(signum, frame):
    # (not while an interrupt is being handled, or propagates through a `finally`: it has not
    # been dropped, and a raise there, e.g. in the handler before it calls `caught`, would
    # end the run with a traceback; a run whose plaza refinement met SIGTERM did)
    if _pending is not None and not _deferring and not _settled \
            and not isinstance(sys.exc_info()[1], KeyboardInterrupt):
        raise _pending


def signal_of(exception):
    """The signal whose interrupt `exception` (a class or an instance) is (`SIGNALS`; the
    exit code of a run it ends is 128 + that number, as the shell's)."""
    kind = exception if isinstance(exception, type) else type(exception)
    return next(s for s, e in reversed(SIGNALS) if issubclass(kind, e))   # (subclasses first)


def said(exception):
    """The words of the one line for the signal of `exception` (a class or an instance)."""
    return WORDS[signal_of(exception)]


def _handler(exception):
    def handler(signum, frame):
        global _pending
        if _settled:
            _after_the_outputs(exception)
            return
        if staging is not None and not _deferring:
            shutil.rmtree(staging, ignore_errors=True)
        jit = sys.modules.get("membranes.fem.jit")      # (loaded: forms may be compiling)
        if jit is not None:
            jit.abandon()
        _pending = exception
        signal.signal(signal.SIGALRM, _raise_pending)
        signal.setitimer(signal.ITIMER_REAL, FOLLOW if _follower else RETRY, RETRY)
        if not _deferring and not _follower:
            raise exception
    return handler


SIGNALS = ((signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, Terminated),
           (signal.SIGHUP, HungUp))
WORDS = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated", signal.SIGHUP: "hung up"}


def _after_the_outputs(exception):
    """A signal once the outputs are in place (`settle`): the first is said and the run goes
    on to its end; a second ends the process at once, with the signal's exit code."""
    global _late
    if _late is not None:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        os._exit(128 + signal_of(exception))
    _late = exception
    if not _follower:
        with contextlib.suppress(OSError):     # (SIGHUP: the terminal may have gone)
            print(f"membranes: {said(exception)} after the outputs were written (they are "
                  f"whole); the run ends with its own exit code", file=sys.stderr, flush=True)


def install():
    """Raise KeyboardInterrupt on SIGINT, `Terminated` on SIGTERM and `HungUp` on SIGHUP,
    again until `caught`; a signal the process was started with ignored stays ignored (`nohup`
    ignores SIGHUP so that a run outlives its terminal; a shell script's background job
    ignores SIGINT). Returns what `restore` needs (the handlers before, SIGALRM's too: a
    signal met sets it). Main thread only."""
    unsettle()
    previous = {signal.SIGALRM: signal.getsignal(signal.SIGALRM),
                "unraisablehook": sys.unraisablehook}
    sys.unraisablehook = _unsaid(sys.unraisablehook)
    for s, e in SIGNALS:
        if signal.getsignal(s) is not signal.SIG_IGN:
            previous[s] = signal.signal(s, _handler(e))
    return previous


def _unsaid(hook):
    """`hook` (sys.unraisablehook) but for the pending interrupt, dropped in a `__del__` or a
    weakref callback: it is raised again (`_raise_pending`), and its "Exception ignored in …"
    traceback stood above the one line (under mpirun; BENCHMARKS.md, "Robustness")."""
    def unraisable(unraisable):
        if not (_pending is not None and isinstance(unraisable.exc_value, KeyboardInterrupt)):
            hook(unraisable)
    return unraisable


def among(rank, size):
    """This process is process `rank` of `size` (cli.main, once MPI has started). Under mpirun
    every process gets the signal, each where it is: one that raised at once and left would
    leave the others waiting for it in their next collective call, where no Python handler
    runs, until mpirun kills them, process 0 too, before it says the line (process 0 in
    dolfinx's create_mesh or an Alltoallv, the others gone: exit 1 and no line; BENCHMARKS.md,
    "Robustness"). So the processes other than 0 go on FOLLOW seconds before they raise: a
    signal sent to one of them alone still ends the run."""
    global _follower
    _follower = size > 1 and rank != 0


def take_back():
    """Initialise PETSc, then take back the signals its initialisation took: SIGHUP (ours,
    `install`, or ignored as the process found it) and SIGPIPE, given back to Python:
    ignored, so that a write to a pipe no process reads raises BrokenPipeError (the command
    line ends silently on it). PETSc's handlers end the run with a PETSc error and MPI_Abort
    (exit 59), leaving staged outputs behind: for SIGPIPE when stdout is piped into `head`
    and its monitors print."""
    hup = signal.getsignal(signal.SIGHUP)
    from petsc4py import PETSc  # noqa: F401
    signal.signal(signal.SIGPIPE, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, hup if hup is signal.SIG_IGN else _handler(HungUp))


@contextlib.contextmanager
def deferred():
    """A block that a signal must not stop halfway (the renames that move the outputs in):
    a signal met inside is raised at its end (if it ended without an error)."""
    global _deferring
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
    if _pending is not None and not _deferring and not _settled:
        raise _pending


def settle():
    """The run's outputs are in place (membranes.app.outputs.staged_folder, every file moved
    in): from now on a signal is said and the run goes on to its end (module notes); a
    signal met during the last renames (`deferred`) is said likewise, not raised."""
    global _settled
    _settled = True             # (first: a signal from here on takes the settled path)
    met = _pending
    caught()
    if met is not None and _late is None:
        _after_the_outputs(met)


def unsettle():
    """Outputs are staged again (membranes.app.outputs.staged_folder): until they are in
    place, a signal ends the run as before `settle`."""
    global _settled, _late
    _settled, _late = False, None


def pending():
    """Whether a signal was met and its interrupt is still to be raised or handled (a
    process other than 0 goes on FOLLOW seconds after it, `among`)."""
    return _pending is not None


def raise_pending():
    """Raise the interrupt met, if one is pending: an error that follows a signal is the
    signal's (its handler removed the staging folder and abandoned the compilations under
    the run, and a process other than 0 goes on FOLLOW seconds after it, `among`, and may
    meet them): the run ends as interrupted, with its one line, not with that error."""
    if _pending is not None:
        raise _pending


def caught():
    """The interrupt reached code that handles it: no more raises (its clean-up must not be
    interrupted in turn)."""
    global _pending
    if _pending is not None:
        _pending = None
        signal.setitimer(signal.ITIMER_REAL, 0.0)


def restore(previous):
    """Stop raising and put back the handlers `install` replaced. After a settled run in a
    process that exits next (`process_ends`) the signals are ignored instead, for the exit's
    last moments (`settle`): Python's finalisation puts back the default action of a handler
    of its own before MPI and PETSc finish, and a SIGINT there ended the process with -2."""
    global _follower
    caught()
    if _settled and process_ends:
        for s, _ in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        return
    _follower = False
    unsettle()
    for s, handler in previous.items():
        if s == "unraisablehook":
            sys.unraisablehook = handler
        elif handler is not None:       # (None: a handler not set from Python, left as is)
            signal.signal(s, handler)
