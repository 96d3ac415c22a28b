"""Shared against unshared patch solves on P processes: the script of tests/core/test_patches.py.

`mpirun -n P python tests/core/mpi_patches.py` builds the disk refined twice from h = 0.3 on P
processes, solves the vertex patches of §5 for a random right-hand side with the engine
sharing inverses between congruent patches and without, and prints on rank 0 one `OK` line:
the largest difference of the two solutions (over all colours and processes) against the
largest entry, the global numbers of patches and classes, the largest relative difference of a
shared block from its class's, and the number of patches whose cells lie on several processes.
"""

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc


def refined_disk(comm, h, J):
    """The finest mesh of the disk scene refined J times (boundary vertices on the circle)."""
    from membranes.model import scenes
    return scenes.disk(h=h, levels=J, comm=comm).hierarchy.finest


def vertex_groups(mesh):
    from dolfinx import fem

    from membranes.estimation.equilibration import boundary_dofs, vertex_patches
    from membranes.estimation.patches import colour_vertices
    V = fem.FunctionSpace(mesh, ("Lagrange", 1))
    nc = mesh.topology.index_map(2).size_local
    cells = V.dofmap.list.array.reshape(-1, 3)[:nc]
    colour, ncolours, _ = colour_vertices(cells, V.dofmap.index_map, mesh.comm)
    return vertex_patches(V, colour, ncolours, boundary_dofs(V))


def random_solutions(mesh, seed=0):
    """(shared, unshared, scale, diff): the engines with and without sharing, and for a random
    W vector b the largest entry of the unshared solutions of all colours and the largest
    difference of the shared ones, over all processes."""
    from membranes.estimation.patches import PatchSystems, mixed_space
    patches, interior = vertex_groups(mesh)
    W = mixed_space(mesh)
    engines = [PatchSystems(mesh, patches, interior, W, share=share) for share in (True, False)]
    b = PETSc.Vec().createMPI((W.dofmap.index_map.size_local, PETSc.DECIDE), comm=mesh.comm)
    b.array[:] = np.random.default_rng(seed + mesh.comm.rank).standard_normal(b.getLocalSize())
    diff = scale = 0.0
    for c in range(len(patches)):
        out = []
        for systems in engines:
            x = systems.solve(c, b)
            out.append(x.array.copy())
            x.destroy()
        diff = max(diff, np.abs(out[0] - out[1]).max(initial=0.0))
        scale = max(scale, np.abs(out[1]).max(initial=0.0))
    comm = mesh.comm
    return (engines[0], engines[1], comm.allreduce(scale, op=MPI.MAX),
            comm.allreduce(diff, op=MPI.MAX))


def straddling(mesh, patches):
    """Global number of patches (all groups) whose cells lie on more than one process."""
    from membranes.estimation.patches import reduce_by_key
    comm = mesh.comm
    total = 0
    for pid in patches:
        ids = np.unique(pid[pid >= 0])
        ranks = reduce_by_key(comm, ids, np.full(ids.shape, 1 << comm.rank, dtype=np.int64),
                              np.bitwise_or)
        lowest = (ranks & -ranks) == (1 << comm.rank)
        many = np.array([bin(int(v)).count("1") > 1 for v in ranks], dtype=bool)
        total += int(np.count_nonzero(many & lowest))
    return comm.allreduce(total, op=MPI.SUM)


def main():
    comm = MPI.COMM_WORLD
    mesh = refined_disk(comm, 0.3, 2)
    shared, _, scale, diff = random_solutions(mesh)
    stats = shared.stats()
    count = straddling(mesh, vertex_groups(mesh)[0])
    if comm.rank == 0:
        print(f"OK P={comm.size} patches={stats['patches']} classes={stats['classes']} "
              f"straddling={count} scale={scale:.6e} diff={diff:.3e} worst={stats['worst']:.3e}",
              flush=True)


if __name__ == "__main__":
    main()
