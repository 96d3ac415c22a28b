"""Arrays kept from one run of a pass to the next, for passes that run again and again on the
same mesh: a Newton step's eliminated system (newton_system.eliminated_system), an
evaluation's fluxes and cell parts (equilibration.FluxEquilibration.sigmas,
estimators.Estimators.evaluate).

Memory that a process takes anew is given to it page by page at its first write: a page fault
for every 4 KiB, the page zeroed by the kernel. glibc's malloc maps a block of more than
32 MiB anew at every request and unmaps it when it is freed, so a pass that makes such an
array every time pays the faults every time. At 9.3e5 vertices (disk, J = 6) the eliminated
system took 27-41 thousand faults a Newton step (up to 0.34 s of system time, besides
0.15-0.22 s for the product itself), an evaluation of the estimators 33 thousand for its σ
and 15 thousand for its cell parts; where two processes run side by side
(membranes.pipeline) the faults cost more (the estimator process spent 2.2 s of system time in a 11.6 s run). A kept
array is written again instead: once a pass's arrays are kept, its later runs take no fresh
pages for them. Measured (J = 6, alternating rounds, 2026-11-22): on 2 processes the system's
and the cell parts' arrays kept, 9.50-9.94 s against 10.22-10.68 s (six rounds, the kept code
faster in each), σ's as well, 9.14-9.62 s against 9.34-9.60 s (five); serial runs
16.46-17.00 s against 16.16-16.79 s (three rounds: no difference).

An array is handed out again only where nothing else refers to it (its reference count: no
matrix, view, PETSc object or caller holds it any more), else a new one is made, and kept if
fewer than `kept` are: results that callers keep stay theirs, and a pass whose results live
on (σ_disc's last two, which Estimators.sigma_disc keeps; FB's projection step and the step
after it in one Newton iteration) gets arrays of its own. What is handed out is the first
entries of a flat buffer, which is the base of it and of every view of it, so that the count
sees them all (newton.semismooth_newton lets a step's system go before it makes the next).
The numbers do not change: every entry is written before it is read, as in a fresh np.empty.
"""

import sys

import numpy as np


class KeptArrays:
    """A few arrays for one pass's output of one kind, handed out again once free (module
    notes)."""

    def __init__(self, kept=2):
        # flat buffers, each the base of every array handed out from it and of their views
        self.kept, self.buffers = kept, []

    def empty(self, shape, dtype=float):
        """An array of `shape` and `dtype`, its entries undefined (as np.empty): the first
        entries of a kept buffer of that dtype that nothing else refers to, else of a new one
        (np.empty: numpy asks for huge pages for it, which a populated mapping would not get),
        kept in place of a free one too small or while fewer than `kept` are kept."""
        dtype = np.dtype(dtype)
        shape = (int(shape),) if np.isscalar(shape) else tuple(shape)
        size = int(np.prod(shape))
        free = [i for i in range(len(self.buffers)) if _unreferenced(self.buffers, i)]
        for i in free:
            buffer = self.buffers[i]
            if buffer.dtype == dtype and buffer.size >= size:
                return buffer[:size].reshape(shape)
        new = np.empty(size, dtype)
        if free:
            self.buffers[free[0]] = new
        elif len(self.buffers) < self.kept:
            self.buffers.append(new)
        return new[:size].reshape(shape)


def _unreferenced(buffers, i):
    """Whether nothing but the list `buffers` refers to its flat buffer i (an array handed out
    from it, and any view of that, has it as numpy's `base`)."""
    return sys.getrefcount(buffers[i]) == 2     # the list and getrefcount's argument (CPython)
