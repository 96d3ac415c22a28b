"""Communication helpers of the patch engine on a distributed mesh (§12): owned/ghost exchange
with any numpy ufunc on a dolfinx IndexMap (`Shared`), MPI Alltoallv of numpy rows, a
distributed reduction by key, and the vertex colouring that makes the groups of §5 and §6; and
the array helpers they and the set-up share (a linear-time stable sort of integer keys, runs;
the segments' `ranges` lives in `fem.segments`, which the mesh checks share).

Split off `patches`, which re-exports these names.
"""

import numpy as np
from mpi4py import MPI

from ..fem.segments import ranges  # noqa: F401  (patches and homes take it from here)

# ## Sorting and segments

def stable_order(keys):
    """np.argsort(keys, kind="stable") for non-negative integers, by passes over 16 bits
    (numpy's stable sort of uint16 is a radix sort: linear time). Each pass gathers its
    16-bit digits in the order so far, not the keys (a quarter of the memory traffic)."""
    top = int(keys.max(initial=0))
    order = np.argsort(keys.astype(np.uint16), kind="stable")
    shift = 16
    while top >> shift:
        digit = (keys >> shift).astype(np.uint16)
        order = order[np.argsort(digit[order], kind="stable")]
        shift += 16
    return order


def run_starts(values):
    """The index of the first entry of each run of equal consecutive values."""
    if values.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.concatenate([[True], values[1:] != values[:-1]]))


def counts_before(flags, offsets):
    """The number of true `flags` before each offset (the counts of the segments
    offsets[k]:offsets[k + 1] are its differences)."""
    return np.searchsorted(np.flatnonzero(flags), offsets)


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
    """CSR adjacency (offsets, neighbours) of the local vertices through the given cells.

    The graph is symmetric, so each pair of vertices of a cell is listed once, as an edge
    {lo ≤ hi} (half the pairs to sort and deduplicate). A vertex's neighbours are then the
    lo of its edges by hi (all ≤ it) followed by the hi of its edges by lo (all > it): its
    neighbours in increasing order."""
    a, b = np.triu_indices(cells.shape[1], 1)
    u, v = cells[:, a], cells[:, b]
    edges = np.minimum(u, v).astype(np.int64)
    edges *= nlocal
    edges += np.maximum(u, v)
    # sorted and without repeats; numpy's stable sort of int64 (timsort) is fast on these
    # keys, which come in runs along the cells
    edges = np.sort(edges.ravel(), kind="stable")
    if edges.size:
        edges = edges[np.concatenate([[True], edges[1:] != edges[:-1]])]
    lo = edges // nlocal
    hi = edges - lo * nlocal
    del edges
    below = np.bincount(hi, minlength=nlocal)                  # neighbours ≤ each vertex
    strict = lo < hi
    above = np.bincount(lo[strict], minlength=nlocal)          # neighbours > each vertex
    offsets = np.zeros(nlocal + 1, dtype=np.int64)
    np.cumsum(below + above, out=offsets[1:])
    nbrs = np.empty(int(offsets[-1]), dtype=np.int64)
    by_hi = stable_order(hi)                                   # the edges by (hi, lo)
    h = hi[by_hi]
    first = np.cumsum(below) - below
    nbrs[offsets[h] - first[h] + np.arange(h.size)] = lo[by_hi]
    lo, hi = lo[strict], hi[strict]                            # by (lo, hi)
    first = np.cumsum(above) - above
    nbrs[offsets[lo] + below[lo] - first[lo] + np.arange(lo.size)] = hi
    return offsets, nbrs


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
    (colour of every local vertex, owned and ghost, int32; number of colours; rounds).

    A round reads, for the priorities, only the uncoloured neighbours of the uncoloured
    vertices: those lists are kept from round to round and shrunk (a coloured neighbour
    adds 0 to the maximum, and the priorities are positive). The colours taken around a
    vertex are gathered from its whole neighbour list, for the chosen vertices only (the
    owners' choice is sent to the ghosts first), which are the only ones read."""
    n, nloc = imap.size_local, imap.size_local + imap.num_ghosts
    shared = Shared(imap, comm)
    offsets, nbrs = vertex_graph(cells, nloc)
    prio = _priority(np.asarray(imap.local_to_global(np.arange(nloc, dtype=np.int32))))
    colour = np.full(nloc, -1, dtype=np.int8)               # at most 64 colours
    full = np.diff(offsets)
    todo, degree, seen = np.arange(nloc), full, nbrs       # uncoloured, uncoloured neighbours
    rounds = 0
    while comm.allreduce(int(np.count_nonzero(colour[:n] < 0)), op=MPI.SUM) > 0:
        rounds += 1
        segments = np.zeros(todo.size + 1, dtype=np.int64)
        np.cumsum(degree, out=segments[1:])
        # the largest priority among the uncoloured neighbours, over all processes' cells
        best = np.zeros(nloc, dtype=np.uint64)
        best[todo] = _segment_reduce(np.maximum, prio[seen], segments, np.uint64(0))
        shared.reverse(best, np.maximum)
        chosen = np.flatnonzero((colour[:n] < 0) & (prio[:n] > best[:n]))
        # the colours of the chosen vertices' coloured neighbours as bits
        pick = np.zeros(nloc, dtype=bool)
        pick[chosen] = True
        picked = np.flatnonzero(shared.forward(pick))
        near = colour[nbrs[ranges(offsets[picked], full[picked])]]
        part = np.zeros(picked.size + 1, dtype=np.int64)
        np.cumsum(full[picked], out=part[1:])
        bits = np.where(near >= 0, np.left_shift(np.uint64(1), np.maximum(near, 0)
                                                 .astype(np.uint64)), np.uint64(0))
        taken = np.zeros(nloc, dtype=np.uint64)
        taken[picked] = _segment_reduce(np.bitwise_or, bits, part, np.uint64(0))
        shared.reverse(taken, np.bitwise_or)
        free = ~taken[chosen]
        if np.any(free == 0):
            raise RuntimeError("vertex colouring needs more than 64 colours")
        lowest = free & (~free + np.uint64(1))
        colour[chosen] = np.round(np.log2(lowest.astype(np.float64))).astype(np.int64)
        shared.forward(colour)
        # drop the coloured vertices and neighbours
        left = colour[seen] < 0
        before = np.zeros(seen.size + 1, dtype=np.int64)
        np.cumsum(left, out=before[1:])
        keep = colour[todo] < 0
        left &= np.repeat(keep, degree)
        seen = seen[left]
        todo, degree = todo[keep], (before[segments[1:]] - before[segments[:-1]])[keep]
    ncolours = comm.allreduce(int(colour.max(initial=-1)) + 1, op=MPI.MAX)
    return colour.astype(np.int32), ncolours, rounds
