"""Repeated solves in one process do not pile up memory (membranes.app.driver.release_garbage).

Since petsc4py 3.18 a PETSc object that Python drops is only parked until
`PETSc.garbage_cleanup(comm)`, and dolfinx 0.5 frees its own PETSc vectors only at an explicit
`destroy()`; before `solve` released both, every solve of a parameter study kept about its
whole footprint (the patch scatters, the Newton solvers, the assembled vectors). The heap in
use (glibc's mallinfo2: what is allocated, whatever the process's resident size) is measured
after each of four solves of one problem, the Solutions dropped: after the first solve it
may grow only by a small fraction of what that first solve left behind (compiled forms,
caches, the hierarchy's connectivity), asserted at 10 % per solve where the old behaviour
grew by about 100 %.
"""

import ctypes
import gc
from dataclasses import replace

import pytest
from mpi4py import MPI

from membranes import scenes, solve

GROWTH = 0.10


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]


def heap_in_use():
    libc = ctypes.CDLL("libc.so.6")
    libc.mallinfo2.restype = _MallInfo2
    info = libc.mallinfo2()
    return info.uordblks + info.hblkhd


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process's heap")
def test_repeated_solves_release_their_memory():
    try:
        heap_in_use()
    except (OSError, AttributeError):
        pytest.skip("not glibc 2.33 or later (no mallinfo2)")
    problem = scenes.disk(h=0.2, levels=3)
    gc.collect()
    before = heap_in_use()
    used = []
    for mu2 in (1.0, 2.0, 3.0, 4.0):
        sol = solve(replace(problem, mu2=mu2))
        assert sol.converged
        del sol
        used.append(heap_in_use())
    first = used[0] - before
    growth = [b - a for a, b in zip(used, used[1:])]
    assert first > 0
    assert max(growth) <= GROWTH * first, (first, growth)
