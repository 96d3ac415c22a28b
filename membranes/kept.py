"""Arrays kept from one run of a pass to the next, for passes that run again and again on the
same mesh: a Newton step's eliminated system (newton_system.eliminated_system), an
evaluation's fluxes and cell parts (equilibration.FluxEquilibration.sigmas,
estimators.Estimators.evaluate).

Memory that a process takes anew is given to it page by page at its first write: a page fault
for every 4 KiB, the page zeroed by the kernel. glibc's malloc maps a block of more than
32 MiB anew at every request and unmaps it when it is freed, so a pass that makes such an
array every time pays the faults every time. At 9.3e5 vertices (disk, J = 6) the eliminated
system took 27-41 thousand faults a Newton step (up to 0.34 s of system time, besides 0.18-0.2
s for the product itself), an evaluation of the estimators 33 thousand for its σ and 15
thousand for its cell parts; where two processes run side by side (membranes.pipeline) the
faults cost more (the estimator process spent 2.2 s of system time in a 11.6 s run). A kept
array is written again instead: once a pass's arrays are kept, its later runs take no fresh
pages for them. Measured (J = 6, alternating rounds, 2026-11-22): on 2 processes the system's
and the cell parts' arrays kept, 9.50-9.94 s against 10.22-10.68 s (six rounds, the kept code
faster in each), σ's as well, 9.14-9.62 s against 9.34-9.60 s (five); serial runs
16.46-17.00 s against 16.16-16.79 s (three rounds: no difference).

An array is handed out again only where nothing else refers to it (its reference count: no
matrix, view, PETSc object or caller holds it any more), else a new one is made, and kept if
fewer than `kept` are: results that callers keep stay theirs, and a pass whose results live
on (the system before the step's, alive while the next is made) gets arrays of its own. The
numbers do not change: every entry is written before it is read, as in a fresh np.empty.
"""

import sys

import numpy as np


class KeptArrays:
    """A few arrays for one pass's output of one kind, handed out again once free (module
    notes)."""

    def __init__(self, kept=2):
        self.kept, self.arrays = kept, []

    def empty(self, shape, dtype=float, at_least=False):
        """An array of `shape` and `dtype`, its entries undefined (as np.empty): a kept one
        that nothing else refers to, else a new one, kept in place of a free one of another
        size or while fewer than `kept` are kept. at_least (one dimension): an array of at
        least `shape` entries (the caller writes a prefix)."""
        dtype = np.dtype(dtype)
        shape = (shape,) if np.isscalar(shape) else tuple(shape)
        free = [i for i in range(len(self.arrays)) if _unreferenced(self.arrays, i)]
        for i in free:
            a = self.arrays[i]
            if a.dtype == dtype and (a.shape == shape or
                                     (at_least and a.ndim == 1 and a.size >= shape[0])):
                return a
        new = np.empty(shape, dtype)
        if free:
            self.arrays[free[0]] = new
        elif len(self.arrays) < self.kept:
            self.arrays.append(new)
        return new


def _unreferenced(arrays, i):
    """Whether nothing but the list `arrays` refers to its array i (a view refers to the array
    it views: numpy's `base`)."""
    return sys.getrefcount(arrays[i]) == 2      # the list and getrefcount's argument (CPython)
