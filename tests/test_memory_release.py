"""Repeated solves in one process do not pile up memory (membranes.app.garbage.release_garbage).

Since petsc4py 3.18 a PETSc object that Python drops is only parked until
`PETSc.garbage_cleanup(comm)`, and dolfinx 0.5 frees its own PETSc vectors only at an explicit
`destroy()`; before `solve` released both, every solve of a parameter study kept about its
whole footprint (the patch scatters, the Newton solvers, the assembled vectors). The heap in
use (glibc's mallinfo2: what is allocated, whatever the process's resident size) is measured
after each of four solves of one problem, the Solutions dropped: after the first solve it
may grow only by a small fraction of what that first solve left behind (compiled forms,
caches, the hierarchy's connectivity), asserted at 10 % per solve where the old behaviour
grew by about 100 %.

PETSc's own log counts the objects made and destroyed: after the first solve, the count of
live objects of every kind must stay put, whatever the estimators' algebraic flux (a ghosted
vector that dolfinx 0.5 made for the multilevel flux was never freed: one Vec pair, one
star forest and one local-to-global map per solve, about 25 kB on the disk at h 0.3,
levels 2, 190 kB at levels 4). The same when every solve is of a new problem, dropped with
its Solution (membranes.app.garbage: their objects were parked on the communicators of
meshes no later solve had, and never freed: 3.6 MB per solve on the disk at h 0.3, levels 4).
"""

import ctypes
import gc
import os
import re
import tempfile
from dataclasses import replace

import pytest
from mpi4py import MPI
from petsc4py import PETSc

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
    from membranes.app.garbage import release_garbage
    problem = scenes.disk(h=0.2, levels=3)
    release_garbage(problem)          # what earlier tests in this process left parked
    before = heap_in_use()
    used = []
    for mu2 in (1.0, 2.0, 3.0, 4.0):
        sol = solve(replace(problem, mu2=mu2, exact=None))
        assert sol.converged
        del sol
        used.append(heap_in_use())
    first = used[0] - before
    growth = [b - a for a, b in zip(used, used[1:])]
    assert first > 0
    assert max(growth) <= GROWTH * first, (first, growth)


def live_petsc_objects():
    """{kind: objects made less objects destroyed} from PETSc's log (PETSc.Log.begin() on)."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "log.txt")
        viewer = PETSc.Viewer().createASCII(path, comm=PETSc.COMM_SELF)
        PETSc.Log.view(viewer)
        viewer.destroy()
        with open(path) as f:
            table = f.read().split("Object Type", 1)[1]
    live = {}
    for m in re.finditer(r"^\s*([A-Za-z][A-Za-z ]*?)\s+(\d+)\s+(\d+)\s*$", table, re.M):
        live[m.group(1)] = live.get(m.group(1), 0) + int(m.group(2)) - int(m.group(3))
    return live


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process's log")
@pytest.mark.parametrize("alg_flux", ["nu", "multilevel"])
def test_repeated_solves_leave_no_petsc_objects(alg_flux):
    PETSc.Log.begin()
    problem = scenes.disk(h=0.3, levels=2)
    live = []
    for _ in range(3):
        assert solve(problem, alg_flux=alg_flux).converged
        gc.collect()
        live.append(live_petsc_objects())
    assert live[0] and live[1] == live[0] and live[2] == live[0], live


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process's log")
def test_dropped_problems_leave_no_petsc_objects():
    PETSc.Log.begin()
    live = []
    for _ in range(3):
        sol = solve(scenes.disk(h=0.3, levels=2))
        assert sol.converged
        del sol
        gc.collect()
        live.append(live_petsc_objects())
    assert live[0] and live[1] == live[0] and live[2] == live[0], live


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process's log")
def test_a_problem_kept_while_others_are_dropped_is_released_later():
    """A Solution kept while the problems solved after it are dropped one by one (their
    meshes' communicators let go of as they go), and dropped itself later: its objects,
    parked on its own meshes' communicators, are freed at the next solve like those of any
    dropped problem. The live objects after that solve are those after a solve whose earlier
    problem was dropped at once."""
    PETSc.Log.begin()

    def problem():
        return scenes.disk(h=0.3, levels=1)
    solve(problem())
    sol = solve(problem())
    del sol
    gc.collect()
    before = live_petsc_objects()
    kept = solve(problem())
    for _ in range(2):
        sol = solve(problem())
        del sol
    del kept
    gc.collect()
    sol = solve(problem())
    del sol
    gc.collect()
    assert live_petsc_objects() == before


def test_a_mesh_solved_on_again_is_watched_once():
    """Each mesh solved on is watched once, by one duplicate of its communicator, however
    often it is solved on (a parameter study of many solves on one hierarchy would otherwise
    duplicate its communicators at every solve, a limited resource of MPI)."""
    from membranes.app import garbage
    problem = scenes.disk(h=0.3, levels=1)
    counts = []
    for mu2 in (1.0, 2.0, 3.0):
        solve(replace(problem, mu2=mu2, exact=None), newton="exact", estimators=False)
        counts.append(sum(ref() in problem.hierarchy.meshes for ref, _ in garbage._WATCHED))
    assert counts == [2, 2, 2]
