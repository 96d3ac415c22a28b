"""Shared against unshared patch solves on P processes: the script of tests/core/test_patches.py.

`mpirun -n P python tests/core/mpi_patches.py` builds the disk refined twice from h = 0.3 on P
processes, solves the vertex patches of §5 for a random right-hand side with the engine
sharing inverses between congruent patches and without, and prints on rank 0 one `OK` line:
the largest difference of the two solutions (over all colours and processes) against the
largest entry, the global numbers of patches, classes and key collisions, the number of
patches whose cells lie on several processes, and the home entries that the gathers of all
colours leave unwritten (`uncovered`), and whether the distinct keys of the classes over all
processes are those of a serial run (`same_keys`, `keys_as_serial`).
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
    difference of the shared ones, over all processes. Each solve into a vector that holds
    other values gives the same entries, bit for bit (zeros where the group keeps no dof:
    no test gave `solve` such a vector)."""
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
            x.set(7.0)
            assert np.array_equal(systems.solve(c, b, x).array, out[-1])
            x.destroy()
        diff = max(diff, np.abs(out[0] - out[1]).max(initial=0.0))
        scale = max(scale, np.abs(out[1]).max(initial=0.0))
    comm = mesh.comm
    return (engines[0], engines[1], comm.allreduce(scale, op=MPI.MAX),
            comm.allreduce(diff, op=MPI.MAX))


def uncovered(systems, ngroups, every=True):
    """(entries, home size) over all processes and groups: the entries of a group's part of
    the home vector (its first `group_starts[c + 1] - group_starts[c]`) that its gather leaves
    as they were (NaN before; a W vector b of ones gathered), and those entries in all.
    σ_disc reuses its home vector from one colour to the next without zeroing it
    (equilibration), which is right only where this is 0. `every=False`: the gather of group
    0 into each group's part (it leaves entries where the other groups are larger)."""
    W = systems.W
    b = PETSc.Vec().createMPI((W.dofmap.index_map.size_local, PETSc.DECIDE), comm=systems.comm)
    b.set(1.0)
    left = total = 0
    home = systems.home_vector()
    for c in range(ngroups):
        home[:] = np.nan
        systems.gather(c if every else 0, b, home)
        size = systems.group_starts[c + 1] - systems.group_starts[c]
        left += int(np.isnan(home[:size]).sum())
        total += int(size)
    b.destroy()
    comm = systems.comm
    return comm.allreduce(left, op=MPI.SUM), comm.allreduce(total, op=MPI.SUM)


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


def _full_matrix(W):
    """A over the whole mesh by dolfinx's own assembly (the reference of the partial one)."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_matrix

    import membranes.forms.equilibration as equilibration_forms
    (sigma, gamma), (tau, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
    A = assemble_matrix(fem.form(equilibration_forms.patch_system(sigma, gamma, tau, q,
                                                                  ufl.dx(domain=W.mesh))))
    A.assemble()
    return A


def _marked(mesh):
    """Owned cells of every third patch of the first group (bool per owned cell), and the
    owned W dofs all of whose cells are marked and those of some marked cell (bool per owned
    dof), for the space W."""
    from dolfinx import fem
    from dolfinx.la import ScatterMode

    from membranes.estimation.patches import mixed_space
    W = mixed_space(mesh)
    pid = vertex_groups(mesh)[0][0]
    marked = (pid >= 0) & (pid % 3 == 0)
    # dofs of unmarked and of marked owned cells, summed over the processes: 0 = none
    dofs = W.dofmap.list.array.reshape(-1, W.dofmap.dof_layout.num_dofs)[:marked.size]
    n = W.dofmap.index_map.size_local
    counts = []
    for cells in (~marked, marked):
        count = fem.Function(W)
        np.add.at(count.x.array, dofs[cells].ravel(), 1.0)
        count.x.scatter_reverse(ScatterMode.add)
        counts.append(count.x.array[:n])
    return W, marked, (counts[0] == 0) & (counts[1] > 0), counts[1] > 0


def _global_csr(comm, A, row_of, col_of, size):
    """The PETSc matrix A on all processes as one scipy matrix (size × size), its local rows'
    and columns' indices mapped by `row_of` and `col_of`."""
    import scipy.sparse as sp
    ia, ja, a = A.getValuesCSR()
    lo = A.getOwnershipRange()[0]
    rows = lo + np.repeat(np.arange(ia.size - 1), np.diff(ia))
    parts = comm.allgather((row_of[rows], col_of[ja], a))
    i, j, v = (np.concatenate(x) for x in zip(*parts))
    return sp.csr_matrix((v, (i, j)), shape=(size, size))


def partial_assembly_error(mesh):
    """(largest difference on the dofs inside the marked cells, largest difference anywhere,
    largest entry, number of inside dofs) between A assembled by `homes.assemble_rows` on the
    cells of every third patch of the first group, with rows and columns for the dofs of
    those cells only, and A over the whole mesh on the same rows and columns, over all
    processes. A dof is inside if all its cells are marked: there the principal submatrices
    must agree; on the other dofs of marked cells they differ."""
    from petsc4py import PETSc

    from membranes.estimation.homes import assemble_rows
    comm = mesh.comm
    W, marked, owned_inside, owned_touched = _marked(mesh)
    imap = W.dofmap.index_map
    n, start, N = imap.size_local, imap.local_range[0], imap.size_global
    glob = np.asarray(imap.local_to_global(np.arange(n + imap.num_ghosts, dtype=np.int32)),
                      dtype=np.int64)
    inside = np.concatenate(comm.allgather(np.flatnonzero(owned_inside) + start))
    touched = np.sort(np.concatenate(comm.allgather(np.flatnonzero(owned_touched) + start)))
    # the rows: the touched dofs in global order, all on process 0 (so that every row's
    # columns lie in its diagonal block)
    at = np.minimum(np.searchsorted(touched, glob), touched.size - 1)
    rows = np.where(touched[at] == glob, at, -1).astype(PETSc.IntType)
    width = W.dofmap.dof_layout.num_dofs
    room = np.full(touched.size if comm.rank == 0 else 0, 2 * width, dtype=PETSc.IntType)
    part = assemble_rows(W, np.flatnonzero(marked), rows, room)
    full = _full_matrix(W)
    whole = np.arange(N)
    M = [_global_csr(comm, full, whole, whole, N), _global_csr(comm, part, touched, touched, N)]
    full.destroy()
    part.destroy()
    d = (M[0] - M[1]).tocsr()
    ins, tou = np.zeros(N, dtype=bool), np.zeros(N, dtype=bool)
    ins[inside], tou[touched] = True, True
    d_inside = d[np.flatnonzero(ins)][:, ins]
    d_touched = d[np.flatnonzero(tou)][:, tou]
    return (abs(d_inside).max() if d_inside.nnz else 0.0,
            abs(d_touched).max() if d_touched.nnz else 0.0,
            abs(M[0]).max(), int(inside.size))


def class_keys(mesh):
    """The distinct keys of the classes of `mesh`'s vertex patches over all its processes
    (sorted; on rank 0, None elsewhere)."""
    from membranes.estimation.patches import PatchSystems, mixed_space
    patches, interior = vertex_groups(mesh)
    systems = PatchSystems(mesh, patches, interior, mixed_space(mesh))
    keys = mesh.comm.gather(systems.store.keys, root=0)
    systems.destroy()
    return np.unique(np.concatenate(keys)) if mesh.comm.rank == 0 else None


def keys_as_serial(comm):
    """Whether the classes' keys over all processes are those of the serial run, for the disk
    refined twice from h = 0.3 and the square's gmsh mesh refined twice from h = 0.2 (a key
    that rounded a position summed in dolfinx's local vertex order split a class of the
    square on 3 processes); on rank 0, None elsewhere."""
    from membranes.model import scenes
    same = []
    for make in (lambda c: refined_disk(c, 0.3, 2),
                 lambda c: scenes.square(h=0.2, levels=2, comm=c).hierarchy.finest):
        keys = class_keys(make(comm))
        if comm.rank == 0:
            same.append(np.array_equal(keys, class_keys(make(MPI.COMM_SELF))))
    return int(all(same)) if comm.rank == 0 else None


def main():
    comm = MPI.COMM_WORLD
    same_keys = keys_as_serial(comm)
    mesh = refined_disk(comm, 0.3, 2)
    shared, _, scale, diff = random_solutions(mesh)
    stats = shared.stats()
    groups = vertex_groups(mesh)[0]
    count = straddling(mesh.comm, groups)
    left, home = uncovered(shared, len(groups))
    inside, outside, entry, ninside = partial_assembly_error(mesh)
    if comm.rank == 0:
        print(f"OK P={comm.size} patches={stats['patches']} classes={stats['classes']} "
              f"straddling={count} scale={scale:.6e} diff={diff:.3e} "
              f"collisions={stats['collisions']} inside={inside:.3e} "
              f"outside={outside:.3e} entry={entry:.6e} ninside={ninside} "
              f"uncovered={left} home={home} same_keys={same_keys}", flush=True)


if __name__ == "__main__":
    main()
