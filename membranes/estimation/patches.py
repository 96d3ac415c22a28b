"""Coloured patch problems: block-diagonal mixed RT_1 × DG1 systems on a distributed mesh (§5, §12).

A *patch* is a group of cells; the patch problems of §5 (and of the multilevel flux, §6) are
mixed Raviart–Thomas problems on each patch:

    (σ, τ) - (γ, ∇·τ) - (∇·σ, q) = ℓ(τ, q)     ∀ (τ, q) ∈ V^p × Q^p,

V^p = RT_1 on the patch's cells with zero normal flux on the patch boundary (except on ∂Ω for a
patch that is not *interior*), Q^p = DG1 on its cells (zero mean on an interior patch). The
divergence equation is negated against §5 so that the matrix is symmetric.

Patches straddle processes, and dolfinx 0.5.2 cannot ghost vertex patches. So the patches are
handed over in *groups* (colours) whose patches share no cell: the patches of one group form
ONE block-diagonal system, a principal submatrix of the matrix A of the form above assembled
by dolfinx over the whole mesh. This holds because every dof kept for a group is supported on
the cells of one patch (a facet dof is kept only if both its cells are in that patch, or its
one cell if the facet lies on ∂Ω), so A's entry between two kept dofs is the sum of the cell
blocks of that patch only, and is zero between dofs of two patches. PETSc extracts each group's
submatrix and MUMPS factorises it once (LDLᵀ: it is symmetric indefinite); a right-hand side
is then one back-solve per group. Only the factors are kept. This is dolfin-tape's design;
where each patch is solved is told in `PatchSystems`.

Only facet-cell connectivity and index-map communication are used, so the engine works on
GhostMode.none meshes (the patch id of the cell across a process boundary travels with the
facet's index map) as well as on ghosted ones (only owned cells carry patch ids).

Zero mean on interior patches: instead of a Lagrange multiplier, one DG dof k of the patch is
removed, both as unknown (γ_k = 0) and as equation (the row of its basis function φ_k). The
reduced system is nonsingular: with B the divergence block, B maps the zero-flux RT space onto
{b : Σ_i b_i = 0} (div is onto the zero-mean DG1 functions and Σ_i φ_i = 1), so Bᵀγ = 0 only
for γ constant, which γ_k = 0 excludes, and σ = 0 follows from the first row as usual. The
removed row is implied when the data are compatible, (ℓ_q, 1) = 0: then
(∇·σ, φ_k) = (∇·σ, 1) - Σ_{i≠k} (∇·σ, φ_i) = 0 - Σ_{i≠k} ℓ_i = ℓ_k. So σ is the solution of §5
and γ differs from the zero-mean one by a constant. With incompatible data the defect would
land on the pinned dof's cell; §4's lifting makes the vertex patches of §5 compatible, and the
multilevel data of §6 are compatible by construction.
"""

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc

import forms.equilibration as equilibration_forms


# ## Communication on an index map
#
# dolfinx's own scatterers add or insert; the colouring needs max and bitwise-or, and the
# facet exchange max. `Shared` does both directions for any numpy ufunc with MPI Alltoallv.

class Shared:
    """Owned/ghost communication on a dolfinx IndexMap (block size 1).

    `reverse(values, op)`: every ghost's value is combined into its owner's entry with the ufunc
    `op` (np.add, np.maximum, np.bitwise_or, ...). `forward(values)`: ghosts receive their
    owner's value. `values` has one row per local entry (owned then ghosts)."""

    def __init__(self, imap, comm):
        self.comm = comm
        n = imap.size_local
        owners = np.asarray(imap.owners, dtype=np.int64)
        ghosts = np.asarray(imap.ghosts, dtype=np.int64)
        order = np.argsort(owners, kind="stable")
        self.ghost_local = (n + order).astype(np.int64)
        self.send_counts = np.bincount(owners, minlength=comm.size).astype(np.int64)
        self.recv_counts = np.asarray(comm.alltoall(self.send_counts.tolist()), dtype=np.int64)
        received = alltoallv(comm, ghosts[order], self.send_counts, self.recv_counts)
        self.owned_local = received - imap.local_range[0]

    def reverse(self, values, op):
        sent = np.ascontiguousarray(values[self.ghost_local])
        got = alltoallv(self.comm, sent, self.send_counts, self.recv_counts)
        op.at(values, self.owned_local, got)
        return values

    def forward(self, values):
        sent = np.ascontiguousarray(values[self.owned_local])
        values[self.ghost_local] = alltoallv(self.comm, sent, self.recv_counts, self.send_counts)
        return values


def alltoallv(comm, rows, send_counts, recv_counts):
    """Rows of `rows` (grouped by destination rank, send_counts[p] rows to rank p) sent with
    MPI Alltoallv; returns the received rows grouped by source rank."""
    rows = np.ascontiguousarray(rows)
    width = int(np.prod(rows.shape[1:], dtype=np.int64))
    out = np.empty((int(recv_counts.sum()),) + rows.shape[1:], dtype=rows.dtype)
    if comm.size == 1:
        out[...] = rows
        return out
    sc, rc = send_counts * width, recv_counts * width
    sd = np.concatenate([[0], np.cumsum(sc)[:-1]])
    rd = np.concatenate([[0], np.cumsum(rc)[:-1]])
    comm.Alltoallv([rows.reshape(-1), (sc, sd)], [out.reshape(-1), (rc, rd)])
    return out


def reduce_by_key(comm, keys, values, op):
    """For integer `keys` spread over the processes, the reduction with ufunc `op` of the
    `values` of all processes with the same key, returned for each local key (a distributed
    dictionary: key k lives on rank k mod P)."""
    keys = np.asarray(keys, dtype=np.int64)
    values = np.asarray(values)
    dest = keys % comm.size
    order = np.argsort(dest, kind="stable")
    send_counts = np.bincount(dest, minlength=comm.size).astype(np.int64)
    recv_counts = np.asarray(comm.alltoall(send_counts.tolist()), dtype=np.int64)
    k = alltoallv(comm, keys[order], send_counts, recv_counts)
    v = alltoallv(comm, values[order], send_counts, recv_counts)
    by_key = np.argsort(k, kind="stable")
    first = np.ones(k.size, dtype=bool)
    first[1:] = k[by_key][1:] != k[by_key][:-1]
    reduced = op.reduceat(v[by_key], np.flatnonzero(first)) if k.size else v[:0]
    inverse = np.empty(k.size, dtype=np.int64)
    inverse[by_key] = np.cumsum(first) - 1
    back = alltoallv(comm, reduced[inverse], recv_counts, send_counts)
    out = np.empty_like(values)
    out[order] = back
    return out


# ## Vertex colouring
#
# Vertices are adjacent when they share a cell (for triangles: an edge). Jones–Plassmann: each
# round colours the uncoloured vertices whose priority beats all their uncoloured neighbours
# (an independent set), each with the smallest colour none of its neighbours has. The result is
# the sequential greedy colouring in order of decreasing priority. Neighbours across process
# boundaries are seen through the reverse exchange of the vertex index map: each process
# reduces over its own cells, the owner combines.

def _priority(global_index):
    """Distinct pseudo-random priorities: 32 hashed bits (splitmix64) above the index + 1."""
    z = global_index.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return ((z >> np.uint64(32)) << np.uint64(32)) | (global_index.astype(np.uint64) + np.uint64(1))


def vertex_graph(cells, nlocal):
    """CSR adjacency (offsets, neighbours) of the local vertices through the given cells."""
    k = cells.shape[1]
    i = np.repeat(cells, k - 1, axis=1).ravel()
    j = np.concatenate([np.roll(cells, -s, axis=1)[:, :, None] for s in range(1, k)],
                       axis=2).reshape(-1)
    pairs = np.unique(i.astype(np.int64) * nlocal + j)
    i, j = pairs // nlocal, pairs % nlocal
    offsets = np.zeros(nlocal + 1, dtype=np.int64)
    np.cumsum(np.bincount(i, minlength=nlocal), out=offsets[1:])
    return offsets, j


def _segment_reduce(op, values, offsets, identity):
    """op over each CSR segment of `values`, `identity` for empty segments."""
    out = np.full(offsets.size - 1, identity, dtype=values.dtype)
    nonempty = offsets[1:] > offsets[:-1]
    if values.size:
        out[nonempty] = op.reduceat(values, offsets[:-1][nonempty])
    return out


def colour_vertices(cells, imap, comm):
    """A colouring of the vertices of an index map such that no two vertices of one colour
    share a cell of `cells` ((owned cells, vertices) local vertex indices). Returns
    (colour of every local vertex, owned and ghost, int32; number of colours; rounds)."""
    n, nloc = imap.size_local, imap.size_local + imap.num_ghosts
    shared = Shared(imap, comm)
    offsets, nbrs = vertex_graph(cells, nloc)
    prio = _priority(np.asarray(imap.local_to_global(np.arange(nloc, dtype=np.int32))))
    colour = np.full(nloc, -1, dtype=np.int64)
    rounds = 0
    while comm.allreduce(int(np.count_nonzero(colour[:n] < 0)), op=MPI.SUM) > 0:
        rounds += 1
        uncoloured = colour < 0
        # the largest priority among the uncoloured neighbours, over all processes' cells
        best = _segment_reduce(np.maximum, np.where(uncoloured, prio, 0)[nbrs], offsets,
                               np.uint64(0))
        shared.reverse(best, np.maximum)
        chosen = np.flatnonzero(uncoloured[:n] & (prio[:n] > best[:n]))
        # the colours of the coloured neighbours as bits
        bits = np.where(colour >= 0, np.left_shift(np.uint64(1), np.maximum(colour, 0)
                                                   .astype(np.uint64)), np.uint64(0))
        taken = _segment_reduce(np.bitwise_or, bits[nbrs], offsets, np.uint64(0))
        shared.reverse(taken, np.bitwise_or)
        free = ~taken[chosen]
        if np.any(free == 0):
            raise RuntimeError("vertex colouring needs more than 64 colours")
        lowest = free & (~free + np.uint64(1))
        colour[chosen] = np.round(np.log2(lowest.astype(np.float64))).astype(np.int64)
        shared.forward(colour)
    ncolours = comm.allreduce(int(colour.max(initial=-1)) + 1, op=MPI.MAX)
    return colour.astype(np.int32), ncolours, rounds


# ## The coloured patch systems

def mixed_space(mesh):
    """RT_1 × DG1 (basix "RT" degree 2, "DG" degree 1) as one dolfinx mixed space."""
    from dolfinx import fem
    cell = mesh.ufl_cell()
    element = ufl.MixedElement(ufl.FiniteElement("RT", cell, 2), ufl.FiniteElement("DG", cell, 1))
    return fem.FunctionSpace(mesh, element)


def _mumps_factor(A, prefix, comm):
    """The MUMPS LDLᵀ factor (a PETSc factored Mat, `F.solve(b, x)`) of the symmetric
    sequential matrix A, or None if A is empty. A itself is not needed afterwards: MUMPS keeps
    its own copy. Collective on `comm`: a failure on one process raises on all."""
    factor, info = None, 0
    if A.getSize()[0] > 0:
        ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(A)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("cholesky")
        pc.setFactorSolverType("mumps")
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        ksp.setFromOptions()
        ksp.setUp()
        factor = pc.getFactorMatrix()          # a new reference: it outlives the KSP
        ksp.destroy()
        info = factor.getMumpsInfog(1)
    info = comm.allreduce(min(info, 0), op=MPI.MIN)
    if info < 0:
        raise RuntimeError(f"MUMPS could not factorise the patch system {prefix[:-1]} "
                           f"(INFOG(1) = {info}; -10: a patch is singular)")
    return factor


class PatchSystems:
    """The coloured patch systems of one mesh, assembled and factorised once.

    `patches[c]`: int array over the owned cells, the global id of the patch of group (colour)
    c containing the cell, or -1; no two patches of one group share a cell. `interior[c]`: bool
    array over the owned cells, True where the cell's patch is interior (zero normal flux on all
    its boundary and zero mean; otherwise its facets on ∂Ω are free). Patch ids must be unique
    within a group across processes; a patch's cells may live on several processes.

    Each patch is solved on one process, its *home*: the owner of its cell of least global
    index. The kept dofs of all the patches at home on a process, wherever they are owned, form
    a sequential principal submatrix of A (PETSc's MatCreateSubMatrices, as for overlapping
    Schwarz subdomains), factorised by sequential MUMPS; a VecScatter moves a right-hand side's
    kept entries to the home processes and the solution back. Only the dofs of patches that
    straddle processes travel; the factorisations and back-solves need no communication.

    `solve(c, b, out, extra)` solves group c for the right-hand side b (a PETSc Vec on W,
    assembled from a linear form on `W`, owned entries final) plus `extra` (entries at the
    group's home dofs, see `gather`) and returns the solution on W (zero at the dofs the group
    does not keep; ghosts not updated); `add_flux(x, sigma)` adds its RT part to an RT_1
    Function.
    """

    def __init__(self, mesh, patches, interior, W=None):
        from dolfinx import fem
        from dolfinx.fem.petsc import assemble_matrix
        self.mesh, self.comm = mesh, mesh.comm
        self.W = W = W if W is not None else mixed_space(mesh)
        self.rt_space, rt_map = W.sub(0).collapse()
        self.rt_map = np.asarray(rt_map, dtype=np.int64)
        self.ngroups = len(patches)
        self._topology(mesh, W)

        # A over the whole mesh, once; group c keeps a principal submatrix of it. All the
        # groups' blocks are taken before A is freed and MUMPS allocates (a lower peak).
        (sigma, gamma), (tau, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
        A = assemble_matrix(fem.form(equilibration_forms.patch_system(sigma, gamma, tau, q)))
        A.assemble()
        template = A.createVecLeft()
        self.groups, blocks = [], []
        for pid, inner in zip(patches, interior):
            home = self._home_dofs(np.asarray(pid, dtype=np.int64), np.asarray(inner, dtype=bool))
            iset = PETSc.IS().createGeneral(home.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
            blocks.append(A.createSubMatrices(iset)[0])
            self.groups.append(dict(iset=iset, home=home.size,
                                    size=self.comm.allreduce(home.size, op=MPI.SUM)))
        A.destroy()
        for c, (group, block) in enumerate(zip(self.groups, blocks)):
            group["x"], group["b"] = block.createVecs()
            group["factor"] = _mumps_factor(block, f"patches_{c}_", self.comm)
            block.destroy()
            group["scatter"] = PETSc.Scatter().create(template, group["iset"], group["b"], None)
        template.destroy()

    def _topology(self, mesh, W):
        """Cell → facet and cell → dof tables (all local cells), facet cell counts (global)."""
        tdim = mesh.topology.dim
        mesh.topology.create_connectivity(tdim, tdim - 1)
        mesh.topology.create_connectivity(tdim - 1, tdim)
        cmap = mesh.topology.index_map(tdim)
        self.ncells = cmap.size_local
        nall = cmap.size_local + cmap.num_ghosts
        self.cell_global = np.asarray(cmap.local_to_global(np.arange(self.ncells, dtype=np.int32)),
                                      dtype=np.int64)
        self.c2f = mesh.topology.connectivity(tdim, tdim - 1).array.reshape(nall, 3)
        fmap = mesh.topology.index_map(tdim - 1)
        self.nfacets = fmap.size_local + fmap.num_ghosts
        self.facet_shared = Shared(fmap, self.comm)
        # the (at most two) owned cells of each local facet (-1: none), and the number of cells
        # of each facet over the whole mesh (owned cells only, each counted by its owner)
        facets = self.c2f[:self.ncells].ravel()
        order = np.argsort(facets, kind="stable")
        count = np.bincount(facets, minlength=self.nfacets)
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        self.facet_owned_cells = np.full((self.nfacets, 2), -1, dtype=np.int64)
        has = count > 0
        self.facet_owned_cells[has, 0] = order[start[has]] // 3
        two = count > 1
        self.facet_owned_cells[two, 1] = order[start[two] + 1] // 3
        self.facet_cells = self.facet_shared.forward(self.facet_shared.reverse(count, np.add))

        rt = W.sub(0).element.basix_element.entity_dofs
        self.rt_facet_cols = np.array(rt[tdim - 1])              # (3, 2): dofs of local facet i
        self.rt_cell_cols = np.array(rt[tdim][0])                 # interior dofs
        self.rt_dofs = W.sub(0).dofmap.list.array.reshape(nall, -1)
        self.dg_dofs = W.sub(1).dofmap.list.array.reshape(nall, -1)
        imap = W.dofmap.index_map
        self.nowned = imap.size_local
        self.nlocal = imap.size_local + imap.num_ghosts
        self.rstart = imap.local_range[0]

    def _home_dofs(self, pid, inner):
        """The global indices of the kept W dofs of the patches at home on this process, patch
        by patch (a collective call: every process hands over its owned kept dofs)."""
        comm = self.comm
        # per facet, over its (at most two) cells: the largest and smallest patch id + 1
        # (0 = no patch), and whether a cell's patch is not interior; reduced across processes
        least = np.iinfo(np.int64).min
        cell_info = np.stack([pid + 1, -(pid + 1), ((pid >= 0) & ~inner)], axis=1)
        cell_info = np.vstack([cell_info, np.full((1, 3), least)])     # row -1: no cell
        info = np.maximum(cell_info[self.facet_owned_cells[:, 0]],
                          cell_info[self.facet_owned_cells[:, 1]])
        self.facet_shared.forward(self.facet_shared.reverse(info, np.maximum))
        hi, lo, free = info[:, 0], -info[:, 1], info[:, 2]
        inside = (self.facet_cells == 2) & (hi == lo) & (hi > 0)
        on_boundary = (self.facet_cells == 1) & (free == 1)
        facet_patch = np.where(inside | on_boundary, hi - 1, -1)

        # the patch of every local dof the group keeps (-1: not kept)
        patch = np.full(self.nlocal, -1, dtype=np.int64)
        cols = self.rt_facet_cols
        patch[self.rt_dofs[:, cols.ravel()]] = np.repeat(facet_patch[self.c2f], cols.shape[1],
                                                         axis=1)
        cells = np.flatnonzero(pid >= 0)
        patch[self.rt_dofs[cells][:, self.rt_cell_cols]] = pid[cells, None]
        patch[self.dg_dofs[cells]] = pid[cells, None]

        # home and pinned cell of each patch: its cell of least global index (and that cell's
        # owner), found with the kept dofs' patches in one distributed reduction
        kept = np.flatnonzero(patch[:self.nowned] >= 0)
        big = np.iinfo(np.int64).max
        keys = np.concatenate([pid[cells], patch[kept]])
        values = np.concatenate([self.cell_global[cells] * comm.size + comm.rank,
                                 np.full(kept.size, big, dtype=np.int64)])
        first = reduce_by_key(comm, keys, values, np.minimum)
        first_cell, home = first[:cells.size] // comm.size, first[cells.size:] % comm.size
        # interior patches: drop the first DG dof of the first cell (see the module docstring)
        pinned = cells[inner[cells] & (self.cell_global[cells] == first_cell)]
        keep = np.ones(kept.size, dtype=bool)
        keep[np.searchsorted(kept, self.dg_dofs[pinned, 0])] = False
        kept, home = kept[keep], home[keep]

        # send every kept dof (global index, patch) to its patch's home
        order = np.argsort(home, kind="stable")
        send = np.bincount(home, minlength=comm.size).astype(np.int64)
        recv = np.asarray(comm.alltoall(send.tolist()), dtype=np.int64)
        rows = np.stack([kept + self.rstart, patch[kept]], axis=1)[order]
        got = alltoallv(comm, rows, send, recv)
        return got[np.lexsort((got[:, 0], got[:, 1])), 0]

    def gather(self, c, b):
        """The entries of the W vector b at the home dofs of group c (a sequential Vec)."""
        g = self.groups[c]
        g["scatter"].scatter(b, g["b"], PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        return g["b"]

    def solve(self, c, b, out=None, extra=None):
        """Solve group c for the W vector `b` (+ `extra` at its home dofs); the W vector `out`
        holds the solution at the kept dofs and zero elsewhere (owned entries)."""
        g = self.groups[c]
        if out is None:
            out = b.duplicate()
        rhs = self.gather(c, b)
        if extra is not None:
            rhs.array[:] += extra
        if g["factor"] is not None:
            g["factor"].solve(rhs, g["x"])
        with out.localForm() as local:
            local.set(0.0)
        g["scatter"].scatter(g["x"], out, PETSc.InsertMode.INSERT, PETSc.ScatterMode.REVERSE)
        return out

    def add_flux(self, x, sigma):
        """sigma.x (owned part) += the RT part of the W vector x (owned part)."""
        n = self.rt_space.dofmap.index_map.size_local
        sigma.x.array[:n] += x.array_r[self.rt_map[:n]]

    def sizes(self):
        """Global number of unknowns of each group's system."""
        return [g["size"] for g in self.groups]

    def destroy(self):
        for g in self.groups:
            for key in ("factor", "scatter", "x", "b", "iset"):
                if g[key] is not None:
                    g[key].destroy()
        self.groups = []
