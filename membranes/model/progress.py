"""Progress lines of a long collective phase: a run of `solve`, the refinements of a scene's
hierarchy. One convention for every `progress` argument: False or None for none, True for
lines on stderr, or a callable given each line; either way written on process 0 only
(`reporter`)."""

import sys


def reporter(progress, comm):
    """The progress lines: None without `progress`, else a function that every process
    calls with each line, at the same points of the run (the lines are made of global
    figures), and that hands the line on process 0 to `progress` (a callable) or to stderr.
    An exception raised there is raised at once on every process: as itself on process 0,
    on the others as a RuntimeError naming it (a KeyboardInterrupt as one), since they would
    otherwise wait for process 0 in the run's next collective call for ever (one broadcast
    per line). Anything else than those values is refused (ValueError)."""
    if not (progress is None or isinstance(progress, bool) or callable(progress)):
        raise ValueError(f"progress must be True, False, None or a callable taking a line, "
                         f"got {progress!r}")
    if not progress:
        return None
    write = progress if callable(progress) else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    if comm.size == 1:
        return write

    def say(line):
        error = None
        if comm.rank == 0:
            try:
                write(line)
            except BaseException as e:
                error = e
        failed = comm.bcast(None if error is None else (type(error).__name__, str(error)),
                            root=0)
        if error is not None:
            raise error
        if failed is not None:
            if failed[0] == "KeyboardInterrupt":
                raise KeyboardInterrupt
            raise RuntimeError(f"the progress callable failed on process 0: {failed[0]}: "
                               f"{failed[1]}")
    return say
