"""Coloured patch problems: mixed RT_1 × DG1 systems on a distributed mesh, solved by shared
dense inverses of congruent patches (§5, §6, §12).

A *patch* is a group of cells; the patch problems of §5 (and of the multilevel flux, §6) are
mixed Raviart–Thomas problems on each patch:

    (σ, τ) - (γ, ∇·τ) - (∇·σ, q) = ℓ(τ, q)     ∀ (τ, q) ∈ V^p × Q^p,

V^p = RT_1 on the patch's cells with zero normal flux on the patch boundary (except on ∂Ω for a
patch that is not *interior*), Q^p = DG1 on its cells (zero mean on an interior patch). The
divergence equation is negated against §5 so that the matrix is symmetric.

**Groups.** Patches straddle processes, and dolfinx 0.5.2 cannot ghost vertex patches. So the
patches are handed over in *groups* (colours) whose patches share no cell. Every dof kept for a
group is supported on the cells of one patch (a facet dof is kept only if both its cells are in
that patch, or its one cell if the facet lies on ∂Ω), so the entry of the matrix A of the form
above, assembled by dolfinx over the whole mesh (forms.equilibration.patch_system), between two
kept dofs is the sum of the cell blocks of that patch only: each patch's matrix is a principal
submatrix A_p of A. Each patch is solved on one process, its *home*; PETSc's
MatCreateSubMatrices brings the rows of the patches at home there (as for overlapping Schwarz
subdomains) and a VecScatter moves right-hand sides and solutions.

**Congruent patches share one inverse.** On a mesh refined uniformly most patches are
translates of a few shapes. Their matrices A_p differ only through dolfinx's basis, which
depends on the numbering (local vertex order of a cell, orientation of a facet by global vertex
indices). In the *canonical* basis of `canonical_dofs` — on every cell the Piola image of the
reference basis through the vertices ordered along a fixed direction d, each facet oriented
along d — the matrix Ã_p = G_pᵀ A_p G_p of a patch depends on its geometry only, and its dofs
are ordered by their entity's position along d (translation invariant). G_p, the change of
basis, is ±1 on facet dofs (a reflection), the identity on DG dofs (Lagrange at the vertices:
only their labels change) and a 2 × 2 integer block on the two interior RT dofs of a cell. The
blocks Ã_p are fingerprinted, grouped, and a patch joins a class only after its block is
checked entry by entry against the class's first block (`Blocks`, relative tolerance
`SAME`: the translates differ by the round-off of their coordinates). Each class keeps one
dense inverse, and a call solves all patches of a class by one matrix product. Where nothing is
congruent (an unstructured mesh) every patch has its own dense inverse. The canonical basis only
decides what is shared: with any invertible G the solve is exact, and each patch is solved with
the inverse of a matrix equal to its own up to `SAME`.

**Zero mean on interior patches.** Instead of a Lagrange multiplier, one DG dof k of the patch
(its first in the canonical order) is removed, both as unknown (γ_k = 0) and as equation (the
row of its basis function φ_k). The reduced system is nonsingular: with B the divergence block,
B maps the zero-flux RT space onto {b : Σ_i b_i = 0} (div is onto the zero-mean DG1 functions and
Σ_i φ_i = 1), so Bᵀγ = 0 only for γ constant, which γ_k = 0 excludes, and σ = 0 follows from the
first row as usual. The removed row is implied when the data are compatible, (ℓ_q, 1) = 0: then
(∇·σ, φ_k) = (∇·σ, 1) - Σ_{i≠k} (∇·σ, φ_i) = 0 - Σ_{i≠k} ℓ_i = ℓ_k. So σ is the solution of §5
and γ differs from the zero-mean one by a constant. With incompatible data the defect would
land on the pinned dof's cell; §4's lifting makes the vertex patches of §5 compatible, and the
multilevel data of §6 are compatible by construction.

Only facet-cell connectivity and index-map communication are used, so the engine works on
GhostMode.none meshes (the patch id of the cell across a process boundary travels with the
facet's index map) as well as on ghosted ones (only owned cells carry patch ids).
"""

import itertools

import numpy as np
import ufl
from mpi4py import MPI
from petsc4py import PETSc
from threadpoolctl import threadpool_limits

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
    if comm.size == 1:
        return rows
    out = np.empty((int(recv_counts.sum()),) + rows.shape[1:], dtype=rows.dtype)
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


def mixed_space(mesh):
    """RT_1 × DG1 (basix "RT" degree 2, "DG" degree 1) as one dolfinx mixed space."""
    from dolfinx import fem
    cell = mesh.ufl_cell()
    element = ufl.MixedElement(ufl.FiniteElement("RT", cell, 2), ufl.FiniteElement("DG", cell, 1))
    return fem.FunctionSpace(mesh, element)


# ## Dof transformations and the Piola pull-back on the reference cell
#
# dolfinx's basis on a cell K is the Piola image of T_K φ̂ (T_K the dof transformation of the
# cell, from its permutation info). Interpolating a field into K's basis gives the coefficients
# T_K⁻ᵀ Π̂ (pulled-back values at the reference points), Π̂ basix's interpolation matrix. For an
# affine map A of the reference cell into itself (vertices `ref`), Π̂ V(A) expresses the
# reference functions pulled back along A in the reference basis:
# V(A)[(i, p), m] = (det(DA) DA⁻¹ φ̂_m(A X_p))_i.

def dof_transformation(element, info, inverse_transpose=False):
    """The matrix T (or T⁻ᵀ) of a basix element's dof transformation for permutation info."""
    n = element.dim
    apply = (element.apply_inverse_transpose_dof_transformation if inverse_transpose
             else element.apply_dof_transformation)
    return np.asarray(apply(np.eye(n).ravel(), n, int(info))).reshape(n, n)


def piola_reference_block(element, ref):
    """Π̂ V(A) for the affine map A sending the reference vertices to `ref` (3, 2)."""
    X, Pi = element.points, element.interpolation_matrix
    DA = np.column_stack([ref[1] - ref[0], ref[2] - ref[0]])
    table = element.tabulate(0, ref[0] + X @ DA.T)[0]                    # (points, dofs, 2)
    pulled = np.linalg.det(DA) * np.einsum("ij,pmj->pmi", np.linalg.inv(DA), table)
    values = np.concatenate([pulled[:, :, 0], pulled[:, :, 1]], axis=0)  # component-major
    return Pi @ values


# ## The canonical basis
#
# On a cell K, let π order its vertices by their position along DIRECTION (ties by global
# vertex index): canonical vertex k is dolfinx's local vertex π(k). The canonical basis of K is
# the Piola image of the reference basis through the reference map with the vertices in that
# order, with no dof transformation: along every facet both cells see the same vertex order, so
# this basis is H(div)-conforming like dolfinx's, and translated cells get the same functions.
# With A the symmetry of the reference cell sending vertex k to vertex π(k), the canonical
# coefficients of a field are M_K = Π̂ V(A) T_Kᵀ times dolfinx's, and G_K = M_K⁻¹ depends only
# on (π, permutation info): checked below to be ±1 between the dofs of canonical facet i and
# dolfinx's facet π(i) (same index t along the facet), a 2 × 2 block on the interior dofs, and,
# for DG1, the identity between canonical vertex k and dolfinx's vertex π(k).
#
# A W dof is labelled by a `code`: bits 0-1 its index t in its entity, bits 2-3 its kind
# (FACET, INNER: interior RT, DG), bit 4 NEGATIVE (the canonical function is minus dolfinx's),
# bits 5-7 the vertex order π of its cell (interior dofs: which 2 × 2 block), bit 8 INTERIOR
# (its patch is interior; set per group).

DIRECTION = np.array([np.cos(1.0), np.sin(1.0)])     # parallel to no edge of usual meshes
ORDERS = list(itertools.permutations(range(3)))
FACET, INNER, DG = 0, 1, 2
NEGATIVE, BLOCK, INTERIOR = 1 << 4, 5, 1 << 8


def _kind(code):
    return (code >> 2) & 3


def basis_changes(W):
    """(signs, blocks): signs[p, info, i, t] = ±1, the canonical dof t of facet i against
    dolfinx's dof t of its facet π(i), for the vertex order p = ORDERS.index(π) and permutation
    info of a cell; blocks[p] the block of G on the interior RT dofs (rows dolfinx's, columns
    canonical). Raises if the elements' transformations are not of that form."""
    rt, dg = (W.sub(i).element.basix_element for i in (0, 1))
    facet = [list(d) for d in rt.entity_dofs[1]]
    inner = list(rt.entity_dofs[2][0])
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    signs = np.zeros((len(ORDERS), 8, 3, len(facet[0])))
    blocks = np.zeros((len(ORDERS), len(inner), len(inner)))
    for p, order in enumerate(ORDERS):
        ref = corners[list(order)]
        pulled = piola_reference_block(rt, ref)
        blocks[p] = np.round(np.linalg.inv(pulled)[np.ix_(inner, inner)])
        for info in range(8):
            G = np.linalg.inv(pulled @ dof_transformation(rt, info).T)
            expected = np.zeros_like(G)
            for i in range(3):
                for t, (row, col) in enumerate(zip(facet[order[i]], facet[i])):
                    signs[p, info, i, t] = expected[row, col] = np.sign(G[row, col])
            expected[np.ix_(inner, inner)] = blocks[p]
            if np.abs(G - expected).max() > 1e-12:
                raise RuntimeError("the RT element's dof transformations are not signed "
                                   "facet permutations: no canonical basis")
        DA = np.column_stack([ref[1] - ref[0], ref[2] - ref[0]])
        values = dg.tabulate(0, ref[0] + dg.points @ DA.T)[0][:, :, 0]
        if np.abs(dg.interpolation_matrix @ values - np.eye(3)[list(order)]).max() > 1e-12:
            raise RuntimeError("the DG element is not Lagrange at the vertices")
    return signs, blocks


def canonical_dofs(mesh, W, c2f, rt_dofs, dg_dofs):
    """Per local W dof (owned and ghost): its entity's position along DIRECTION (facet
    midpoint or cell centroid), a global integer that orders the dofs of equal position (the
    entity's global index, the dof's kind and index in it), its code; the interior blocks; and
    the number of facet dofs on which the two cells of the facet disagree (0: both see the same
    vertex order)."""
    cmap = mesh.topology.index_map(2)
    nall = cmap.size_local + cmap.num_ghosts
    signs, blocks = basis_changes(W)
    mesh.topology.create_entity_permutations()
    info = np.asarray(mesh.topology.get_cell_permutation_info())[:nall].astype(np.int64)
    if info.max(initial=0) >= 8:
        raise RuntimeError("unexpected cell permutation info (not a triangle mesh?)")
    nodes = mesh.geometry.dofmap.array.reshape(-1, 3)[:nall]
    along = mesh.geometry.x[:, :2][nodes] @ DIRECTION                      # (cells, 3)
    mesh.topology.create_connectivity(2, 0)
    c2v = mesh.topology.connectivity(2, 0).array.reshape(-1, 3)[:nall]
    vglobal = np.asarray(mesh.topology.index_map(0).local_to_global(c2v.ravel()),
                         dtype=np.int64)
    # π: the vertices of each cell by position, ties by global index
    rank = np.lexsort((vglobal, along.ravel(), np.repeat(np.arange(nall), 3)))
    order = (rank - np.repeat(3 * np.arange(nall), 3)).reshape(nall, 3)
    lookup = np.zeros(27, dtype=np.int64)
    for p, o in enumerate(ORDERS):
        lookup[9 * o[0] + 3 * o[1] + o[2]] = p
    p = lookup[9 * order[:, 0] + 3 * order[:, 1] + order[:, 2]]
    total = along.sum(axis=1)
    midpoint = 0.5 * (total[:, None] - along)                 # facet i is opposite vertex i
    fglobal = np.asarray(mesh.topology.index_map(1).local_to_global(c2f.ravel()),
                         dtype=np.int64).reshape(nall, 3)
    cglobal = np.asarray(cmap.local_to_global(np.arange(nall, dtype=np.int32)), dtype=np.int64)

    nlocal = W.dofmap.index_map.size_local + W.dofmap.index_map.num_ghosts
    position = np.zeros(nlocal)
    entity = np.zeros(nlocal, dtype=np.int64)
    code = np.zeros(nlocal, dtype=np.int64)
    cells = np.arange(nall)
    facet_cols = np.array(W.sub(0).element.basix_element.entity_dofs[1])
    inner_cols = W.sub(0).element.basix_element.entity_dofs[2][0]
    facet_dofs, facet_codes = [], []
    for i in range(3):
        f = order[:, i]                                   # dolfinx facet of canonical facet i
        for t in range(facet_cols.shape[1]):
            dof = rt_dofs[cells, facet_cols[f, t]]
            position[dof] = midpoint[cells, f]
            entity[dof] = fglobal[cells, f]
            code[dof] = (FACET << 2) | t | np.where(signs[p, info, i, t] < 0, NEGATIVE, 0)
            facet_dofs.append(dof)
            facet_codes.append(code[dof])
    disagree = sum(int(np.count_nonzero(code[d] != k)) for d, k in zip(facet_dofs, facet_codes))
    for t, col in enumerate(inner_cols):
        dof = rt_dofs[:, col]
        position[dof], entity[dof] = total / 3.0, cglobal
        code[dof] = (INNER << 2) | t | (p << BLOCK)
    for k in range(3):
        dof = dg_dofs[cells, order[:, k]]
        position[dof], entity[dof] = total / 3.0, cglobal
        code[dof] = (DG << 2) | k
    # one integer per dof for ties of position: entity, kind, index in the entity
    entity = (entity * 4 + _kind(code)) * 4 + (code & 3)
    return position, entity, code, blocks, disagree


def to_canonical(values, sign, pairs, blocks, transpose=True):
    """values ← Gᵀ values (transpose) or G values, in place, for home vectors: `sign` ±1 per
    entry, `pairs[p]` the positions of the first interior dof of the cells with block p (the
    second follows it)."""
    values *= sign
    for p, first in enumerate(pairs):
        if first.size:
            B = blocks[p].T if transpose else blocks[p]
            v0, v1 = values[first], values[first + 1]
            values[first] = B[0, 0] * v0 + B[0, 1] * v1
            values[first + 1] = B[1, 0] * v0 + B[1, 1] * v1
    return values


def _pairs(code):
    """Positions of the first interior dof of each cell, by block (see `to_canonical`)."""
    first = np.flatnonzero((_kind(code) == INNER) & ((code & 3) == 0))
    p = (code[first] >> BLOCK) & 7
    if first.size and not np.all((_kind(code[first + 1]) == INNER) & ((code[first + 1] & 3) == 1)):
        raise RuntimeError("the interior dofs of a cell are not adjacent in a patch")
    return [first[p == k] for k in range(len(ORDERS))]


def canonical_block(ia, ja, a, code, blocks):
    """Ã = Gᵀ A G in place on the CSR arrays of the home rows (rows and columns in home order,
    `code` per row), A's rows and columns already multiplied by the signs of G. The rows of the
    two interior dofs of a cell have the same columns, and in each row the two are adjacent
    columns."""
    pairs = _pairs(code)
    block_of = np.full(ia.size - 1, -1, dtype=np.int8)
    for p, first in enumerate(pairs):
        block_of[first] = p
        if not first.size:
            continue
        B = blocks[p]
        length = ia[first + 1] - ia[first]
        if np.any(ia[first + 2] - ia[first + 1] != length):
            raise RuntimeError("the interior dofs of a cell have different couplings")
        e0 = np.repeat(ia[first] - np.cumsum(length) + length, length) + np.arange(length.sum())
        e1 = e0 + np.repeat(length, length)
        v0, v1 = a[e0], a[e1]                                   # rows: Gᵀ A
        a[e0] = B[0, 0] * v0 + B[1, 0] * v1
        a[e1] = B[0, 1] * v0 + B[1, 1] * v1
    column = block_of[ja]
    k = np.flatnonzero(column >= 0)
    if k.size and (k[-1] + 1 >= ja.size or np.any(ja[k + 1] != ja[k] + 1)):
        raise RuntimeError("a row couples one interior dof of a cell but not the other")
    column = column[k]
    for p in range(len(pairs)):
        kp = k[column == p]
        B = blocks[p]
        v0, v1 = a[kp], a[kp + 1]                               # columns: (Gᵀ A) G
        a[kp] = B[0, 0] * v0 + B[1, 0] * v1
        a[kp + 1] = B[0, 1] * v0 + B[1, 1] * v1
    return a


# ## Classes of equal blocks
#
# The patches of a group with the same size n and number of entries L are compared as rows of a
# (patches, L) array of their CSR values (rows in order, columns sorted). A block's fingerprint
# is its values against fixed weights over the L positions divided by its largest entry,
# rounded to 2⁻³² (congruent blocks differ by ~1e-15: they share a fingerprint but for a ~1e-4
# chance of straddling a rounding boundary, which only loses the sharing). Blocks with the same
# n, L and fingerprint are candidates; a patch joins the class of its candidate only if its
# pattern (row lengths and columns) is the class's and every entry agrees to SAME times the
# class's largest entry. Classes persist across groups; each keeps its first block.

SAME = 1e-13


class _Rows:
    """A growing 2-d array (rows appended in blocks)."""

    def __init__(self, width, dtype):
        self.data, self.size = np.zeros((16, width), dtype=dtype), 0

    def append(self, rows):
        end = self.size + len(rows)
        if end > len(self.data):
            data = np.zeros((max(end, len(self.data) * 3 // 2),) + self.data.shape[1:],
                            self.data.dtype)
            data[:self.size] = self.data[:self.size]
            self.data = data
        self.data[self.size:end] = rows
        self.size = end


class Blocks:
    """The distinct canonical patch blocks of one process (`classify`, then `inverses`)."""

    def __init__(self):
        self.index = {}              # (n, L, fingerprint) → class
        self.shapes = {}             # (n, L) → [values, columns, row lengths, scales] (_Rows)
        self.where = []              # class → ((n, L), row in the shape's arrays)
        self.rejected = 0

    def _add(self, shape, values, columns, lengths, scales):
        """New classes, one per row of `values`; their numbers."""
        if shape not in self.shapes:
            n, L = shape
            self.shapes[shape] = [_Rows(L, np.float64), _Rows(L, np.int32), _Rows(n, np.int32),
                                  _Rows(1, np.float64)]
        store = self.shapes[shape]
        first = store[0].size
        for rows, data in zip(store, (values, columns, lengths, scales[:, None])):
            rows.append(data)
        numbers = np.arange(len(self.where), len(self.where) + len(values))
        self.where.extend((shape, first + k) for k in range(len(values)))
        return numbers

    def classify(self, ia, ja, a, offsets):
        """The class of each patch of a group: rows offsets[k]:offsets[k+1] of the canonical
        CSR block (ia, ja, a) are patch k's; its columns must lie in the same range."""
        n = np.diff(offsets)
        starts = ia[offsets]
        L = np.diff(starts)
        cls = np.zeros(n.size, dtype=np.int64)
        if n.size == 0:
            return cls
        rowlen = np.diff(ia).astype(np.int32)
        shapes, shape_of = np.unique(np.stack([n, L], axis=1), axis=0, return_inverse=True)
        for g, (size, length) in enumerate(shapes.tolist()):
            shape = (size, length)
            members = np.flatnonzero(shape_of.ravel() == g)
            entries = starts[members, None] + np.arange(length)
            values = a[entries]
            columns = ja[entries]
            del entries
            columns -= offsets[members, None].astype(ja.dtype)
            if length == 0 or columns.min() < 0 or columns.max() >= size:
                raise RuntimeError("a patch block couples two patches: the patches share a cell")
            lengths = rowlen[offsets[members, None] + np.arange(size)]
            scales = np.abs(values).max(axis=1)
            weights = 1.0 + np.mod(np.arange(length) * 0.6180339887498949, 1.0)
            fingerprint = np.round(np.ldexp(values @ weights / scales, 32)).astype(np.int64)
            unique, first, inverse = np.unique(fingerprint, return_index=True,
                                               return_inverse=True)
            found = np.array([self.index.get((size, length, k), -1) for k in unique.tolist()],
                             dtype=np.int64)
            new = np.flatnonzero(found < 0)
            found[new] = self._add(shape, values[first[new]], columns[first[new]],
                                   lengths[first[new]], scales[first[new]])
            for k in new:
                self.index[(size, length, int(unique[k]))] = found[k]
            found = found[inverse.ravel()]

            # every entry and row length against the class's first block
            store = self.shapes[shape]
            row = np.array([self.where[k][1] for k in found.tolist()], dtype=np.int64)
            error = np.abs(store[0].data[row] - values).max(axis=1)
            same = ((store[1].data[row] == columns).all(axis=1)
                    & (store[2].data[row] == lengths).all(axis=1)
                    & (error <= SAME * store[3].data[row, 0]))
            bad = np.flatnonzero(~same)
            if bad.size:
                self.rejected += bad.size
                found[bad] = self._add(shape, values[bad], columns[bad], lengths[bad],
                                       scales[bad])
            cls[members] = found
        return cls

    def count(self):
        return len(self.where)

    def size(self, classes):
        """The sizes n of the given classes."""
        return np.array([self.where[k][0][0] for k in classes], dtype=np.int64)

    def inverses(self, order):
        """The inverses of the classes `order` (all of one size n) as an array (k, n, n)."""
        n = self.where[order[0]][0][0]
        dense = np.zeros((len(order), n, n))
        shape_of = [self.where[k][0] for k in order]
        row_of = np.array([self.where[k][1] for k in order], dtype=np.int64)
        for shape in set(shape_of):
            pick = np.array([s == shape for s in shape_of])
            values, columns, lengths, _ = self.shapes[shape]
            rows = row_of[pick]
            k = np.repeat(np.flatnonzero(pick), shape[1])
            r = np.repeat(np.tile(np.arange(n), rows.size), lengths.data[rows].ravel())
            dense[k, r, columns.data[rows].ravel()] = values.data[rows].ravel()
        # Many small inverses: LAPACK per matrix, on one BLAS thread (threads only add their
        # start-up cost to a 50 × 50 inverse, and several MPI processes would share cores)
        with threadpool_limits(limits=1, user_api="blas"):
            for i in range(0, len(order), 4096):
                dense[i:i + 4096] = np.linalg.inv(dense[i:i + 4096])
        return dense

    def release(self):
        self.__init__()


# ## The coloured patch systems

class PatchSystems:
    """The patch problems of one mesh in groups, set up once (see the module docstring).

    `patches[c]`: int array over the owned cells, the global id of the patch of group (colour)
    c containing the cell, or -1; no two patches of one group share a cell. `interior[c]`: bool
    array over the owned cells, True where the cell's patch is interior (zero normal flux on all
    its boundary and zero mean; otherwise its facets on ∂Ω are free). Patch ids must be unique
    within a group across processes; a patch's cells may live on several processes.

    Each patch is solved on one process, its *home*: the owner of its cell of least global
    index. The kept dofs of all patches at home on a process form its *home vector* (numpy),
    class by class. A call goes: `home = home_vector()`; `gather(c, b, home)` for each group c
    (b a PETSc Vec on W with final owned entries, the right-hand side of group c's patches);
    `x = solve_home(home, extra)` (extra: canonical home values to add, see `canonical`); then
    `scatter(c, x, out, add)` puts group c's solutions into a W Vec (zero elsewhere unless
    `add`), and `add_flux(out, sigma)` adds its RT part to an RT_1 Function. `solve(c, b, out,
    extra)` does all this for one group.
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
        self.position, self.entity, self.code, self.blocks, self.disagree = canonical_dofs(
            mesh, W, self.c2f, self.rt_dofs, self.dg_dofs)
        n = self.nowned
        self.by_rank = np.lexsort((self.entity[:n], self.position[:n]))   # canonical order

        # A over the whole mesh, once; each group's rows at home are taken from it, made
        # canonical and classified, one group at a time
        (sigma, gamma), (tau, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
        A = assemble_matrix(fem.form(equilibration_forms.patch_system(sigma, gamma, tau, q)))
        A.assemble()
        signs = A.createVecLeft()
        signs.array[:] = np.where(self.code[:n] & NEGATIVE, -1.0, 1.0)
        A.diagonalScale(signs, signs)                 # the ±1 of G on facet dofs
        signs.destroy()
        classes = Blocks()
        groups = []
        for pid, inner in zip(patches, interior):
            dofs, offsets, code = self._home_dofs(np.asarray(pid, dtype=np.int64),
                                                  np.asarray(inner, dtype=bool))
            iset = PETSc.IS().createGeneral(dofs.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
            block = A.createSubMatrices(iset)[0]
            iset.destroy()
            ia, ja, a = block.getValuesCSR()
            block.destroy()
            ia = ia.astype(np.int64)
            a = canonical_block(ia, ja.astype(np.int64), a, code, self.blocks)
            groups.append((dofs.astype(PETSc.IntType), offsets, code.astype(np.int16),
                           classes.classify(ia, ja, a, offsets)))
            del ia, ja, a
        A.destroy()
        self._layout(groups, classes)
        del self.position, self.entity, self.code, self.by_rank

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
        """The kept W dofs of the group's patches at home on this process (global indices), in
        canonical order patch by patch, the patches' offsets and the dofs' codes (a collective
        call: every process hands over its owned kept dofs)."""
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
        # the owned kept dofs in canonical order, patch by patch
        kept = self.by_rank[patch[self.by_rank] >= 0]
        kp = patch[kept]
        by_patch = np.argsort(kp, kind="stable")
        kept, kp = kept[by_patch], kp[by_patch]

        # home of each patch: the owner of its cell of least global index, found with the
        # patch's interior flag in one distributed reduction over the patches seen here
        keys, at = np.unique(pid[cells], return_inverse=True)
        values = np.full(keys.size, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(values, at, ((self.cell_global[cells] * comm.size + comm.rank) << 1)
                      | ~inner[cells])
        seen = kp[np.flatnonzero(np.diff(kp, prepend=-1))]          # unique, sorted
        extra = seen[keys[np.minimum(np.searchsorted(keys, seen), keys.size - 1)] != seen] \
            if keys.size else seen                      # patches with no owned cell here
        if extra.size:
            keys = np.concatenate([keys, extra])
            values = np.concatenate([values, np.full(extra.size, np.iinfo(np.int64).max)])
            order = np.argsort(keys)
            keys, values = keys[order], values[order]
        first = reduce_by_key(comm, keys, values, np.minimum)[np.searchsorted(keys, kp)]
        home = (first >> 1) % comm.size
        code = self.code[kept] | np.where(first & 1, 0, INTERIOR)

        # send every kept dof to its patch's home (in order), which keeps the patches whole
        order = np.argsort(home, kind="stable")
        send = np.bincount(home, minlength=comm.size).astype(np.int64)
        recv = np.asarray(comm.alltoall(send.tolist()), dtype=np.int64)
        rows = np.empty((kept.size, 5), dtype=np.int64)
        kept = kept[order]
        rows[:, 0], rows[:, 1], rows[:, 4] = kept + self.rstart, kp[order], code[order]
        rows[:, 2], rows[:, 3] = self.position[kept].view(np.int64), self.entity[kept]
        got = alltoallv(comm, rows, send, recv)
        by_patch = np.argsort(got[:, 1], kind="stable")
        got = got[by_patch]
        if comm.size > 1:
            # a patch with dofs from several processes: merge them in canonical order
            source = np.repeat(np.arange(comm.size), recv)[by_patch]
            new = np.flatnonzero(np.diff(got[:, 1], prepend=-1) != 0)
            mixed = (np.minimum.reduceat(source, new) != np.maximum.reduceat(source, new)
                     if new.size else np.zeros(0, dtype=bool))
            redo = np.flatnonzero(np.repeat(mixed, np.diff(np.append(new, len(got)))))
            if redo.size:
                part = got[redo]
                got[redo] = part[np.lexsort((part[:, 3], part[:, 2].view(np.float64),
                                             part[:, 1]))]
        # patch offsets; interior patches lose their first DG dof
        new = np.flatnonzero(np.diff(got[:, 1], prepend=-1) != 0)
        is_dg = _kind(got[:, 4]) == DG
        dg_patch, dg_first = np.unique(got[is_dg, 1], return_index=True)
        pinned = np.flatnonzero(is_dg)[dg_first]
        pinned = pinned[(got[pinned, 4] & INTERIOR) != 0]
        keep = np.ones(len(got), dtype=bool)
        keep[pinned] = False
        start = np.searchsorted(np.flatnonzero(keep), np.append(new, len(got)))
        got = got[keep]
        return got[:, 0], start, got[:, 4]

    def _layout(self, groups, classes):
        """Home order (size, class multiplicity, class, group, patch), the scatters, the
        canonical change of basis in home order, and the inverses of the classes."""
        comm = self.comm
        n = np.concatenate([np.diff(g[1]) for g in groups])
        cls = np.concatenate([g[3] for g in groups])
        group = np.concatenate([np.full(len(g[1]) - 1, c) for c, g in enumerate(groups)])
        nclasses = classes.count()
        count = np.bincount(cls, minlength=nclasses)
        order = np.lexsort((np.arange(cls.size), group, cls, count[cls], n))
        start = np.zeros(cls.size, dtype=np.int64)
        start[order] = np.cumsum(n[order]) - n[order]
        self.home_size = int(n.sum())
        code = np.zeros(self.home_size, dtype=np.int64)
        template = PETSc.Vec().createMPI((self.nowned, PETSc.DECIDE), comm=comm)
        home = self.home_vector()
        hv = PETSc.Vec().createWithArray(home, comm=PETSc.COMM_SELF)
        self.scatters, self.group_sizes = [], []
        first = 0
        for c, (dofs, offsets, gcode, _) in enumerate(groups):
            k = np.diff(offsets)
            at = (np.repeat(start[first:first + k.size] - offsets[:-1], k)
                  + np.arange(offsets[-1]))
            first += k.size
            code[at] = gcode
            src = PETSc.IS().createGeneral(dofs, comm=PETSc.COMM_SELF)
            dst = PETSc.IS().createGeneral(at.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
            self.scatters.append(PETSc.Scatter().create(template, src, hv, dst))
            src.destroy()
            dst.destroy()
            self.group_sizes.append(comm.allreduce(int(offsets[-1]), op=MPI.SUM))
        template.destroy()
        hv.destroy()
        self.sign = np.where(code & NEGATIVE, -1, 1).astype(np.int8)
        self.pairs = _pairs(code)

        # the classes' inverses, size by size in home order; one product per (size, count)
        self.solves = []
        ok = True
        try:
            ranked = np.unique(np.stack([n[order], count[cls[order]], cls[order]], axis=1),
                               axis=0)
            for size in np.unique(ranked[:, 0]):
                these = ranked[ranked[:, 0] == size]
                inverses = classes.inverses(these[:, 2])
                at = 0
                for m in np.unique(these[:, 1]):
                    K = int(np.count_nonzero(these[:, 1] == m))
                    h0 = int(start[cls == these[at, 2]].min())
                    self.solves.append((h0, K, int(m), int(size),
                                        inverses[at:at + K].transpose(0, 2, 1)))
                    at += K
        except np.linalg.LinAlgError:
            ok = False
        if not comm.allreduce(ok, op=MPI.LAND):
            raise RuntimeError("a patch problem is singular")
        self.nclasses, self.npatches = nclasses, cls.size
        self.rejected = classes.rejected
        classes.release()

    def home_vector(self):
        """A zero home vector (numpy): the kept dofs of the patches at home, all groups."""
        return np.zeros(self.home_size)

    def _vec(self, array):
        return PETSc.Vec().createWithArray(array, comm=PETSc.COMM_SELF)

    def gather(self, c, b, home):
        """home ← the entries of the W vector b at group c's kept dofs (dolfinx's basis)."""
        hv = self._vec(home)
        self.scatters[c].scatter(b, hv, PETSc.InsertMode.INSERT, PETSc.ScatterMode.FORWARD)
        hv.destroy()
        return home

    def canonical(self, home):
        """Gᵀ home in place: gathered right-hand sides in the canonical basis."""
        return to_canonical(home, self.sign, self.pairs, self.blocks, transpose=True)

    def solve_home(self, home, extra=None):
        """The solutions of all patches for the gathered right-hand sides `home` (overwritten)
        plus `extra` (canonical, e.g. `canonical(gathered)` of a fixed part), as a home vector
        in dolfinx's basis."""
        rhs = self.canonical(home)
        if extra is not None:
            rhs += extra
        x = np.empty_like(rhs)
        for h0, K, m, n, inverse_t in self.solves:
            h1 = h0 + K * m * n
            np.matmul(rhs[h0:h1].reshape(K, m, n), inverse_t, out=x[h0:h1].reshape(K, m, n))
        return to_canonical(x, self.sign, self.pairs, self.blocks, transpose=False)

    def scatter(self, c, x, out, add=False):
        """The solutions of group c (home vector x) into the W vector `out` (owned entries):
        added, or written with zeros at the dofs the group does not keep."""
        if not add:
            with out.localForm() as local:
                local.set(0.0)
        xv = self._vec(x)
        self.scatters[c].scatter(xv, out, PETSc.InsertMode.ADD if add else
                                 PETSc.InsertMode.INSERT, PETSc.ScatterMode.REVERSE)
        xv.destroy()
        return out

    def solve(self, c, b, out=None, extra=None):
        """Solve group c for the W vector `b` (+ `extra`, canonical home values); the W vector
        `out` holds the solution at the kept dofs and zero elsewhere (owned entries)."""
        if out is None:
            out = b.duplicate()
        home = self.gather(c, b, self.home_vector())
        return self.scatter(c, self.solve_home(home, extra), out)

    def add_flux(self, x, sigma):
        """sigma.x (owned part) += the RT part of the W vector x (owned part)."""
        n = self.rt_space.dofmap.index_map.size_local
        sigma.x.array[:n] += x.array_r[self.rt_map[:n]]

    def sizes(self):
        """Global number of unknowns of each group's patches."""
        return list(self.group_sizes)

    def stats(self):
        """Global facts of the sharing: patches, classes (distinct inverses, summed over the
        processes), blocks rejected by the entry check, inverse memory in bytes, facet dofs
        whose two cells disagree on the canonical basis (0)."""
        memory = sum(s[4].nbytes for s in self.solves)
        local = np.array([self.npatches, self.nclasses, self.rejected, memory, self.disagree])
        total = self.comm.allreduce(local, op=MPI.SUM)
        return dict(zip(("patches", "classes", "rejected", "inverse_bytes", "disagree"),
                        total.tolist()))

    def destroy(self):
        for s in self.scatters:
            s.destroy()
        self.scatters, self.solves = [], []
