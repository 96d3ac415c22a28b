"""Shared against unshared patch solves on P processes: the script of tests/core/test_patches.py.

`mpirun -n P python tests/core/mpi_patches.py` builds the disk refined twice from h = 0.3 on P
processes, solves the vertex patches of §5 for a random right-hand side with the engine
sharing inverses between congruent patches and without, and prints on rank 0 one `OK` line:
the largest difference of the two solutions (over all colours and processes) against the
largest entry, the global numbers of patches, classes and key collisions, and the number of
patches whose cells lie on several processes.
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

    from membranes.estimation.equilibration import vertex_patches
    from membranes.estimation.patches import colour_vertices
    from membranes.fem.discretisation import boundary_dofs
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


def straddling(comm, groups):
    """Global number of patches (all groups) whose cells lie on more than one process; each
    group an array over the owned cells of their patch's global id (-1: none)."""
    from membranes.estimation.patches import reduce_by_key
    total = 0
    for pid in groups:
        ids = np.unique(pid[pid >= 0])
        ranks = reduce_by_key(comm, ids, np.full(ids.shape, 1 << comm.rank, dtype=np.int64),
                              np.bitwise_or)
        lowest = (ranks & -ranks) == (1 << comm.rank)       # counted by its lowest rank
        many = np.array([bin(int(v)).count("1") > 1 for v in ranks], dtype=bool)
        total += int(np.count_nonzero(many & lowest))
    return comm.allreduce(total, op=MPI.SUM)


def _full_matrix(W, signs):
    """The signed A over the whole mesh (every owned cell), as the engine assembled it before
    (the reference of the partial assembly and of the action)."""
    from membranes.estimation.homes import assemble_on
    mesh = W.mesh
    return assemble_on(W, np.arange(mesh.topology.index_map(mesh.topology.dim).size_local),
                       signs)


def _random_signs(W, seed):
    n = W.dofmap.index_map.size_local
    return np.where(np.random.default_rng(seed).random(n) < 0.5, -1.0, 1.0)


def _marked(mesh):
    """Owned cells of every third patch of the first group (bool per owned cell), and the
    owned W dofs all of whose cells are marked (bool per owned dof), for the space W."""
    from dolfinx import fem
    from dolfinx.la import ScatterMode

    from membranes.estimation.patches import mixed_space
    W = mixed_space(mesh)
    pid = vertex_groups(mesh)[0][0]
    marked = (pid >= 0) & (pid % 3 == 0)
    # dofs of unmarked owned cells, summed over the processes: 0 = inside
    count = fem.Function(W)
    dofs = W.dofmap.list.array.reshape(-1, W.dofmap.dof_layout.num_dofs)[:marked.size]
    np.add.at(count.x.array, dofs[~marked].ravel(), 1.0)
    count.x.scatter_reverse(ScatterMode.add)
    return W, marked, count.x.array[:W.dofmap.index_map.size_local] == 0


def partial_assembly_error(mesh, seed=2):
    """(largest difference on the dofs inside the marked cells, largest difference anywhere,
    largest entry, number of inside dofs) between A assembled on the cells of every third
    patch of the first group (`homes.assemble_on`) and A over the whole mesh, over all
    processes. A dof is inside if all its cells are marked: there the principal submatrices
    must agree; elsewhere they differ."""
    import scipy.sparse as sp

    from membranes.estimation.homes import assemble_on
    comm = mesh.comm
    W, marked, owned_inside = _marked(mesh)
    signs = _random_signs(W, seed + comm.rank)
    full, part = _full_matrix(W, signs), assemble_on(W, np.flatnonzero(marked), signs)
    imap = W.dofmap.index_map
    n, start = imap.size_local, imap.local_range[0]
    inside = np.concatenate(comm.allgather(np.flatnonzero(owned_inside) + start))
    mask = np.zeros(imap.size_global, dtype=bool)
    mask[inside] = True
    diffs = []
    for M in (full, part):
        ia, ja, a = M.getValuesCSR()
        diffs.append(sp.csr_matrix((a, ja, ia), shape=(n, imap.size_global)))
    d = (diffs[0] - diffs[1]).tocsr()
    d_inside = d[np.flatnonzero(owned_inside)][:, mask]
    local = [abs(d_inside).max() if d_inside.nnz else 0.0, abs(d).max() if d.nnz else 0.0,
             abs(diffs[0]).max() if diffs[0].nnz else 0.0]
    full.destroy()
    part.destroy()
    out = [comm.allreduce(float(v), op=MPI.MAX) for v in local]
    return (*out, int(inside.size))


def main():
    comm = MPI.COMM_WORLD
    mesh = refined_disk(comm, 0.3, 2)
    shared, _, scale, diff = random_solutions(mesh)
    stats = shared.stats()
    count = straddling(mesh.comm, vertex_groups(mesh)[0])
    inside, outside, entry, ninside = partial_assembly_error(mesh)
    if comm.rank == 0:
        print(f"OK P={comm.size} patches={stats['patches']} classes={stats['classes']} "
              f"straddling={count} scale={scale:.6e} diff={diff:.3e} "
              f"collisions={stats['collisions']} inside={inside:.3e} "
              f"outside={outside:.3e} entry={entry:.6e} ninside={ninside}", flush=True)


if __name__ == "__main__":
    main()
