"""PETSc objects that Python dropped, freed between solves: `release_garbage` (§12).

Since petsc4py 3.18 a PETSc object that Python drops without `destroy()` is only parked, on
its communicator, until `PETSc.garbage_cleanup(comm)` (destroying is collective, dropping is
not). A process that solves many problems would keep every solve's matrices, vectors and
preconditioners; `solve` cleans up at its start and at its end.

The objects a caller keeps outlive the solve: a Solution's matrices and iterate, a problem's
prolongations. They are parked when the caller drops them, on the communicators of their
meshes (dolfinx gives each mesh its own), and a caller who drops a problem together with its
Solution (`sol = solve(scenes.disk(h=h))` in a loop over h) drops those meshes too: no later
solve has them, and their objects stayed allocated for the life of the process (about 240
bytes per vertex and problem). So the PETSc communicator of every mesh solved on is watched
(`_WATCHED`, a counted reference that keeps it valid once the mesh has gone): each clean-up
cleans it too, and after the mesh has gone on all its processes, once more for the last time.
"""

import gc
import weakref

from mpi4py import MPI
from petsc4py import PETSc

# [(weak reference to a mesh solved on, a counted reference to its PETSc communicator)]
_WATCHED = []


def _within(comm, group):
    """Whether every process of `comm` (a PETSc Comm) belongs to `group`: then all of them
    take part in a clean-up on a communicator of that group (collective calls on it are
    safe)."""
    mine = comm.tompi4py().Get_group()
    try:
        return MPI.Group.Intersection(mine, group).Get_size() == mine.Get_size()
    finally:
        mine.Free()


def _watch(mesh):
    if not any(ref() is mesh for ref, _ in _WATCHED):
        _WATCHED.append((weakref.ref(mesh), PETSc.Comm(mesh.comm).duplicate()))


def release_garbage(problem, collect=True):
    """Free the memory of objects nothing refers to any more, collectively on the problem's
    communicator: Python's reference cycles (`gc.collect`), then the PETSc objects they and
    others held. Called at the end of `solve` (a small cost, most of it the collection) and,
    without the collection, at its start: what a Solution the caller dropped since holds is
    freed by reference counting (it is in no cycle) and only its parked PETSc objects are
    left. The communicators are COMM_SELF (the sequential objects: patch blocks, index sets,
    the processes' own parts of the preconditioners), those of the hierarchy's meshes (each
    refinement has its own) and those of the meshes of earlier problems (module notes) whose
    processes all take part in this one: watched in the order they were first solved on, so
    that the processes of each meet in the same order; one whose mesh has gone on all of its
    processes is cleaned once more and let go."""
    if collect:
        gc.collect()
    PETSc.garbage_cleanup(MPI.COMM_SELF)
    for mesh in problem.hierarchy.meshes:
        _watch(mesh)
    group = problem.mesh.comm.Get_group()
    try:
        gone = []
        for ref, comm in list(_WATCHED):
            if _within(comm, group):
                PETSc.garbage_cleanup(comm)
                if comm.tompi4py().allreduce(ref() is None, op=MPI.LAND):
                    gone.append(comm)
    finally:
        group.Free()
    # (let go only once out of the list: an interrupt above leaves no destroyed one in it)
    _WATCHED[:] = [(ref, comm) for ref, comm in _WATCHED if all(comm is not g for g in gone)]
    for comm in gone:
        comm.destroy()
