"""Congruent patches: a canonical basis of RT_1 × DG1 and classes of equal patch blocks (§12).

`patches.PatchSystems` solves the patch problems of §5 and §6 with dense inverses; on a mesh
refined uniformly most patches are translates of a few shapes, and those share one inverse.
Their matrices A_p, principal submatrices of the matrix A that dolfinx assembles, differ only
through dolfinx's basis, which depends on the numbering (the local vertex order of a cell and
the orientation of a facet by global vertex indices). This module removes that dependence:

* `canonical_dofs`: on every cell the *canonical* basis is the Piola image of the reference
  basis through the vertices ordered along a fixed direction d, every facet oriented along d,
  and a patch's dofs are ordered RT facet dofs first, then the interior RT dofs (a cell's two
  adjacent), DG dofs last, each by the position of their entity along d — all translation
  invariant. The change of basis G (canonical → dolfinx) is
  ±1 on facet dofs, the identity on the DG dofs (Lagrange at the vertices: only their labels
  change) and a 2 × 2 integer block on the two interior RT dofs of a cell (`basis_changes`
  checks this form on basix's elements); `canonical_block` forms Ã_p = G_pᵀ A_p G_p on the rows
  of the patches, `BasisChange.apply` applies G and Gᵀ to home vectors by slices.
* `patch_keys` and `Blocks`: translated patches get equal keys (dof kinds and rounded relative
  positions); `Blocks` keeps one block per class.

The canonical basis only decides what is shared: with any invertible G the solves are exact.
A patch is solved with the inverse of its class's block; in the canonical basis its divergence
rows are its own whenever its key is (they do not depend on the geometry, see below), so the
divergence identity that the bound needs holds, and it is checked on every flux made
(`divergence`). The geometry enters the RT mass rows only, equal to those of the patch's own
to the key's resolution.
"""

import itertools

import numpy as np

from .exchange import counts_before

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
# the vertex order p = ORDERS.index(π) of a cell by 3 r_0 + r_1, r_v the rank of its vertex v
_BY_RANKS = np.zeros(9, dtype=np.int64)
for _p, _o in enumerate(ORDERS):
    _BY_RANKS[3 * _o.index(0) + _o.index(1)] = _p


def _kind(code):
    return (code >> 2) & 3


def basis_changes(W, rt=None, dg=None):
    """(signs, blocks): signs[p, info, i, t] = ±1, the canonical dof t of facet i against
    dolfinx's dof t of its facet π(i), for the vertex order p = ORDERS.index(π) and permutation
    info of a cell; blocks[p] the block of G on the interior RT dofs (rows dolfinx's, columns
    canonical). Raises if the elements' transformations are not of that form. `rt`, `dg`: W's
    RT and DG basix elements if at hand (each W.sub builds a dofmap)."""
    rt = rt if rt is not None else W.sub(0).element.basix_element
    dg = dg if dg is not None else W.sub(1).element.basix_element
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


def _canonical_sums(values):
    """For a coordinate of the cells' vertices in canonical order ((3, cells)): their sum
    per cell, and the midpoints of the facets opposite vertices 0, 1, 2 ((3, cells))."""
    a, b, c = values
    return (a + b) + c, 0.5 * np.stack([b + c, a + c, a + b])


def canonical_dofs(mesh, W, c2f, rt_dofs, dg_dofs, rt=None, dg=None, xy=None):
    """The code of every local W dof (owned and ghost); the interior blocks; the number of
    facet dofs on which the two cells of the facet disagree (0: both see the same vertex
    order); and the positions of the entities along DIRECTION and across it, which order the
    dofs of a patch: of every local facet (its midpoint, (facets, 2)) and of every local cell
    (its centroid, (cells, 2)), summed in the canonical vertex order: the same values on any
    number of processes. The dofs of an entity
    share its position; its global index breaks ties. `rt`, `dg`: W's RT and DG basix
    elements, `xy` the (cells, 3, 2) coordinates of the local cells' nodes, if at hand."""
    cmap = mesh.topology.index_map(2)
    nall = cmap.size_local + cmap.num_ghosts
    rt = rt if rt is not None else W.sub(0).element.basix_element
    signs, blocks = basis_changes(W, rt, dg)
    mesh.topology.create_entity_permutations()
    info = np.asarray(mesh.topology.get_cell_permutation_info())[:nall]
    if info.max(initial=0) >= 8:
        raise RuntimeError("unexpected cell permutation info (not a triangle mesh?)")
    if xy is None:
        xy = mesh.geometry.x[:, :2][mesh.geometry.dofmap.array.reshape(-1, 3)[:nall]]
    # (one product over all nodes: numpy's matmul of a stack of (3, 2) matrices makes one BLAS
    # call per cell; the same values)
    along, across = (np.reshape(xy.reshape(-1, 2) @ d, (nall, 3))
                     for d in (DIRECTION, np.array([-DIRECTION[1], DIRECTION[0]])))
    mesh.topology.create_connectivity(2, 0)
    c2v = mesh.topology.connectivity(2, 0).array.reshape(-1, 3)[:nall]
    vglobal = np.asarray(mesh.topology.index_map(0).local_to_global(c2v.ravel()),
                         dtype=np.int64).reshape(nall, 3)
    # π: the vertices of each cell by position, ties by global index; from the three
    # comparisons of the cell's vertices (distinct global indices: one of i, j is first)
    # the ranks of vertices 0 and 1 determine π (the table `_BY_RANKS`)
    ahead = [(along[:, i] < along[:, j]) | ((along[:, i] == along[:, j])
                                            & (vglobal[:, i] < vglobal[:, j]))
             for i, j in ((0, 1), (0, 2), (1, 2))]                   # vertex i before j
    ranks = 3 * (2 - ahead[0].astype(np.int8) - ahead[1]) + ahead[0] + 1 - ahead[2]
    p = _BY_RANKS[ranks]
    del ahead, ranks, vglobal
    # order[k]: dolfinx's local vertex π(k) of every cell (canonical vertex k, and canonical
    # facet k opposite it); flat[k]: its entry in a (cells, 3) table
    order = np.array(ORDERS, dtype=np.int64).T[:, p]
    flat = order + np.arange(0, 3 * nall, 3)
    # positions summed in the canonical vertex order, which does not depend on the partition
    # (dolfinx's local order does): a key rounds the same sums on any number of processes,
    # and a facet's two cells give its midpoint the same value (sums in dolfinx's order
    # split classes on some partitions: tests/core/mpi_patches.py)
    total, facet_along = _canonical_sums(along.take(flat))
    side, facet_across = _canonical_sums(across.take(flat))
    nlocal = W.dofmap.index_map.size_local + W.dofmap.index_map.num_ghosts
    fmap = mesh.topology.index_map(1)
    facet_point = np.zeros((fmap.size_local + fmap.num_ghosts, 2))
    code = np.zeros(nlocal, dtype=np.int16)
    facet_cols = np.array(rt.entity_dofs[1])
    inner_cols = np.array(rt.entity_dofs[2][0])
    # the codes of canonical facet i's dofs per (vertex order, permutation info)
    facet_code = ((FACET << 2) | np.arange(facet_cols.shape[1])
                  | np.where(signs < 0, NEGATIVE, 0)).astype(np.int16).reshape(-1, 3,
                                                                               facet_cols.shape[1])
    which = 8 * p + info
    # each write covers all local cells at once: the facets (one write, canonical facet 0 of
    # every cell, then 1, then 2: facet i is opposite vertex i), or the dofs (cells, dofs of
    # the entity); of a facet's two cells the later writes last
    facets = np.ascontiguousarray(c2f[:nall]).take(flat)
    facet_point[facets, 0] = facet_along
    facet_point[facets, 1] = facet_across
    del facets, facet_along, facet_across
    cell_first = np.arange(nall)[:, None] * rt_dofs.shape[1]     # (flat positions in rt_dofs)
    facet_dofs, facet_codes = [], []
    for i in range(3):
        f = order[i]                                      # dolfinx facet of canonical facet i
        dof = np.ascontiguousarray(rt_dofs).take(cell_first + facet_cols[f])
        code[dof] = facet_code[:, i][which]
        facet_dofs.append(dof)
        facet_codes.append(code[dof])
    disagree = sum(int(np.count_nonzero(code[d] != k)) for d, k in zip(facet_dofs, facet_codes))
    code[rt_dofs[:, inner_cols]] = (INNER << 2) | np.arange(inner_cols.size) | (p[:, None] << BLOCK)
    code[np.ascontiguousarray(dg_dofs).take(flat)] = ((DG << 2) | np.arange(3))[:, None]
    return code, blocks, disagree, facet_point, np.stack([total / 3.0, side / 3.0], axis=1)


APPLY_CHUNK = 1 << 15     # patches per pass of `BasisChange.apply` over the 2 × 2 blocks


class BasisChange:
    """G and Gᵀ on home vectors (`apply`) by slices: the patches are
    cut into runs of consecutive patches with the same size n, number F of facet dofs and
    number c of cells; in canonical order a patch holds its F facet dofs, then its c pairs of
    interior RT dofs, then its DG dofs, so that in a run (M patches) the signs act on the
    columns [0, F) of an (M, n) view and the 2 × 2 blocks on the pairs of the columns [F, F +
    2c). Kept per run: the signs (M, F) and the blocks (M, c, 2, 2), as int8."""

    def __init__(self, code, offsets, blocks):
        n = np.diff(offsets)
        self.runs = []
        if n.size == 0:
            return
        kind = code & 12                                  # the kind bits, in place
        F = np.diff(counts_before(kind == FACET << 2, offsets))
        c = np.diff(counts_before(kind == INNER << 2, offsets)) // 2
        del kind
        shape = np.stack([n, F, c], axis=1)
        cut = np.flatnonzero(np.any(shape[1:] != shape[:-1], axis=1)) + 1
        bounds = np.concatenate([[0], cut, [n.size]])
        table = np.asarray(np.rint(blocks), dtype=np.int8)
        for first, last in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
            m, f, k = (int(x) for x in shape[first])
            h0, count = int(offsets[first]), last - first
            view = code[h0:h0 + count * m].reshape(count, m)
            expected = np.repeat([FACET, INNER, DG], [f, 2 * k, m - f - 2 * k])
            if (np.any(_kind(view) != expected)
                    or np.any((view[:, f:f + 2 * k] & 3) != np.arange(2 * k) % 2)):
                raise RuntimeError("a patch's dofs are not in the canonical order")
            sign = np.where(view[:, :f] & NEGATIVE, np.int8(-1), np.int8(1))
            block = table[(view[:, f:f + 2 * k:2] >> BLOCK) & 7]
            self.runs.append((h0, count, m, f, k, sign, block))

    def apply(self, values, transpose=True):
        """values ← Gᵀ values (transpose) or G values, in place; the 2 × 2 blocks APPLY_CHUNK
        patches at a time (their temporaries are then small beside the home vector)."""
        a, b = (1, 0) if transpose else (0, 1)
        for h0, count, m, f, k, sign, block in self.runs:
            rows = values[h0:h0 + count * m].reshape(count, m)
            if f:
                rows[:, :f] *= sign
            for p0 in range(0, count if k else 0, APPLY_CHUNK):
                p1 = min(count, p0 + APPLY_CHUNK)
                pairs = rows[p0:p1, f:f + 2 * k].reshape(p1 - p0, k, 2)
                v0, v1 = pairs[:, :, 0].copy(), pairs[:, :, 1].copy()
                B = block[p0:p1]
                pairs[:, :, 0] = v0 * B[:, :, 0, 0] + v1 * B[:, :, a, b]
                pairs[:, :, 1] = v0 * B[:, :, b, a] + v1 * B[:, :, 1, 1]
        return values

    def nbytes(self):
        return sum(r[5].nbytes + r[6].nbytes for r in self.runs)


def _pair_blocks(code):
    """Positions of the first interior dof of each cell (kind and index in the low four bits of
    the code), and the block of each."""
    first = np.flatnonzero((code & 15) == INNER << 2)
    if first.size and not np.all((code[first + 1] & 15) == (INNER << 2 | 1)):
        raise RuntimeError("the interior dofs of a cell are not adjacent in a patch")
    return first, (code[first] >> BLOCK) & 7


def _pairs(code):
    """Positions of the first interior dof of each cell, by block (`canonical_block`)."""
    first, p = _pair_blocks(code)
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
# The canonical basis is translation invariant, so translated patches have the same *key*: the
# kinds and indices of their kept dofs in canonical order with the positions of their entities
# relative to the patch's first, in units of the patch's shortest edge h, rounded to 2⁻³⁶
# (`patch_keys`, hashed to 64 bits), and their number of dofs. Patches with equal keys form one
# class: only the block of the class's first patch (its representative) is taken from A. Two
# patches of one key have the same entities in the same relative places to 2⁻³⁶ h, so:
#
# * their divergence rows are equal exactly: in the canonical basis the entry (∇·φ_j, q_i)_K
#   is ±∫_K̂ ∇̂·φ̂_j q̂_i (the contravariant Piola map, the sign that of the canonical
#   vertex order's orientation), which depends on which entities of the patch carry the dofs
#   and not on the cells' shapes;
# * their RT mass rows, functions of the edge vectors of their cells, agree to the key's
#   resolution (true translates to the round-off of the coordinates, ~ε R/h). Meshers make
#   many cells congruent to 1e-7 h but not to round-off (gmsh's disk at h = 0.132); the fine
#   grid gives those keys of their own.
#
# So a patch solved with its class's inverse gets a flux with the divergence the bound needs
# (the mass rows decide only which such flux, i.e. its optimality); a key collision between
# patches of other shapes would break that, and the check of every flux (`divergence`) would
# raise. A collision between patches of other sizes is caught at once (`patches`: such a patch
# gets a class of its own).

KEY_GRID = 2.0 ** 36     # relative positions in a key: multiples of 2⁻³⁶ h
KEY_LIMIT = 2.0 ** 62    # the largest |position| / 2⁻³⁶ h a key's int64 word holds
KEY_CODE = 15 | INTERIOR                # the code bits in a key: index, kind, interior patch


def _mix(z):
    """splitmix64's finaliser on uint64 (wrapping arithmetic), in place."""
    with np.errstate(over="ignore"):
        z ^= z >> np.uint64(30)
        z *= np.uint64(0xBF58476D1CE4E5B9)
        z ^= z >> np.uint64(27)
        z *= np.uint64(0x94D049BB133111EB)
        z ^= z >> np.uint64(31)
    return z


def patch_keys(offsets, code, point, h, sizes=None):
    """The key of each patch (uint64): entries offsets[k]:offsets[k+1] of `code` and `point`
    (entity positions, (entries, 2)) are patch k's dofs in canonical order (or only the first
    dof of each entity), h[k] its shortest edge, sizes[k] its number of dofs (None: the
    entries). Translated patches get equal keys (but for positions within round-off of a
    rounding boundary)."""
    n = np.diff(offsets) if sizes is None else np.asarray(sizes)
    keys = np.zeros(n.size, dtype=np.uint64)
    if n.size == 0:
        return keys
    # the first dof of each entity stands for its entity (the others differ only by index)
    first = (code & 3) == 0
    start = offsets
    if not first.all():
        start = counts_before(first, offsets)
        first = np.flatnonzero(first)
        code, point = code[first], point.take(first, axis=0)
    step = 1 << 14                                   # patches at a time (bounds the memory)
    for lo in range(0, n.size, step):
        hi = min(lo + step, n.size)
        a, b = start[lo], start[hi]
        keys[lo:hi] = _keys(start[lo:hi + 1] - a, code[a:b], point[a:b], h[lo:hi])
    with np.errstate(over="ignore"):
        return keys + _mix(n.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15))


def _keys(offsets, code, point, h):
    n = np.diff(offsets)
    first = np.repeat(offsets[:-1], n)
    rel = point - point.take(first, axis=0)
    rel *= np.repeat(KEY_GRID / h, n)[:, None]
    wide = None
    if not (rel.max(initial=0.0) < KEY_LIMIT and rel.min(initial=0.0) > -KEY_LIMIT):
        # a patch longer than 2⁶²⁻³⁶ h (cells of aspect ratio ≳ 1e7; or NaN): its position
        # does not fit a key word, so the word is the entity's absolute position (its bits),
        # which no other patch shares: the patch gets a class of its own
        wide = ~(np.abs(rel) < KEY_LIMIT)
        rel[wide] = 0.0
    word = np.rint(rel, out=rel).astype(np.int64).view(np.uint64)
    if wide is not None:
        word[wide] = np.ascontiguousarray(point)[wide].view(np.uint64)
    first -= np.arange(offsets[-1])                                # minus the index in the patch
    with np.errstate(over="ignore"):
        word[:, 0] *= np.uint64(0x9E3779B97F4A7C15)
        word[:, 1] *= np.uint64(0xC2B2AE3D27D4EB4F)
        mixed = word[:, 0] + word[:, 1]
        mixed += (code & KEY_CODE).astype(np.uint64) * np.uint64(0x165667B19E3779F9)
        mixed -= first.view(np.uint64) * np.uint64(0x27D4EB2F165667C5)
        return np.add.reduceat(_mix(mixed), offsets[:-1])


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
    """The canonical blocks of the classes of one process (`add` blocks as new classes;
    `operators` of the classes). A block is kept as CSR rows, grouped by shape (n, L, n_σ):
    size, number of entries, number of RT dofs."""

    def __init__(self):
        self.shapes = {}             # (n, L, n_σ) → [values, columns, row lengths]
        self.where = []              # class → ((n, L, n_σ), row in the shape's arrays)

    def add(self, ia, ja, a, offsets, nsigma):
        """New classes for the blocks of CSR rows (ia, ja, a): rows offsets[k]:offsets[k+1]
        are patch k's, its RT dofs first (nsigma[k] of them), its columns in the same range.
        Returns their class numbers."""
        n = np.diff(offsets)
        base = len(self.where)
        if n.size == 0:
            return np.zeros(0, dtype=np.int64)
        starts = ia[offsets]
        L = np.diff(starts)
        rowlen = np.diff(ia)
        if np.any(L == 0):
            raise RuntimeError("an empty patch block")
        where = [None] * n.size
        shapes, shape_of = np.unique(np.stack([n, L, nsigma], axis=1), axis=0,
                                     return_inverse=True)
        for g, shape in enumerate(map(tuple, shapes.tolist())):
            size, length, _ = shape
            members = np.flatnonzero(shape_of.ravel() == g)
            entries = starts[members, None] + np.arange(length)
            columns = ja[entries] - offsets[members, None].astype(ja.dtype)
            if columns.min() < 0 or columns.max() >= size:
                raise RuntimeError("a patch block couples two patches: the patches share a cell")
            if shape not in self.shapes:
                self.shapes[shape] = [_Rows(length, np.float64), _Rows(length, np.int32),
                                      _Rows(size, np.int32)]
            store = self.shapes[shape]
            first = store[0].size
            for rows, data in zip(store, (a[entries], columns,
                                          rowlen[offsets[members, None] + np.arange(size)])):
                rows.append(data)
            for k, m in enumerate(members.tolist()):
                where[m] = (shape, first + k)
        self.where.extend(where)
        return np.arange(base, base + n.size)

    def count(self):
        return len(self.where)

    def shape(self, k):
        """(n, L, n_σ) of class k."""
        return self.where[k][0]

    def dense(self, order):
        """The blocks of the classes `order` (all of one size n) as an array (k, n, n)."""
        n = self.where[order[0]][0][0]
        dense = np.zeros((len(order), n, n))
        shape_of = [self.where[k][0] for k in order]
        row_of = np.array([self.where[k][1] for k in order], dtype=np.int64)
        for shape in set(shape_of):
            pick = np.array([s == shape for s in shape_of])
            values, columns, lengths = self.shapes[shape]
            rows = row_of[pick]
            k = np.repeat(np.flatnonzero(pick), shape[1])
            r = np.repeat(np.tile(np.arange(n), rows.size), lengths.data[rows].ravel())
            dense[k, r, columns.data[rows].ravel()] = values.data[rows].ravel()
        return dense

    def operators(self, order, inputs, outputs):
        """The blocks of the inverses of the classes `order` (all of one shape (n, L, n_σ))
        that map the right-hand side entries `inputs` to the solution entries `outputs` (slices
        of the patch's dofs), as an array (k, outputs, inputs). Raises np.linalg.LinAlgError
        for a singular block."""
        rt = self.where[order[0]][0][2]
        n = self.where[order[0]][0][0]
        rows, cols = range(n)[outputs], range(n)[inputs]
        flux_of_divergence = rows.stop <= rt <= cols.start
        out = np.empty((len(order), len(rows), len(cols)))
        part = _InversePart(n, outputs, inputs)
        for first in range(0, len(order), 1024):        # dense blocks a few at a time
            chunk = order[first:first + 1024]
            for k, block in enumerate(self.dense(chunk)):
                corner = _saddle_corner(block, rt) if flux_of_divergence else None
                if corner is not None:
                    out[first + k] = corner[outputs, cols.start - rt:cols.stop - rt]
                else:
                    out[first + k] = part(block)
        return out

    def drop(self):
        """Frees the blocks kept so far; their classes keep their numbers and shapes, and
        new classes are numbered on."""
        self.shapes = {}


# ## Inverses of the patch blocks
#
# LAPACK one block at a time: numpy's batched solves call threaded BLAS, far slower for these
# sizes. A full inverse by LU; a part of it by one LU and solves for the rows (or columns)
# wanted, the fewer: only the RT rows when only the flux is wanted (§5), fewer operations than
# the whole inverse. When only the flux of divergence data is wanted (§6), the block
# of the inverse from the DG rows to the RT unknowns: with the RT dofs first, a block is
# [[M, Bᵀ], [B, 0]], M the RT mass matrix (SPD), B the divergence (full row rank: the pinned
# dof removes the constants); with Y = M⁻¹Bᵀ and the Schur complement S = B Y (SPD), that block
# of the inverse is Y S⁻¹: two Cholesky factorisations, a sixth of the work of the LU inverse
# for the coarse patches.

def _saddle_corner(block, rt):
    """Y S⁻¹ for a saddle-point block [[M, Bᵀ], [B, 0]] (M: its first rt rows and columns),
    or None if the block is not of that form with M and S SPD. With M = L Lᵀ and
    W = L⁻¹ Bᵀ: S = Wᵀ W = R Rᵀ and Y S⁻¹ = L⁻ᵀ W R⁻ᵀ R⁻¹, by triangular solves (BLAS trsm,
    syrk: fewer operations than solving with M and S for their whole right-hand sides)."""
    from scipy.linalg import blas, lapack
    M, B = block[:rt, :rt], block[rt:, :rt]
    scale = np.abs(block).max(initial=0.0)
    if (np.any(block[rt:, rt:] != 0.0)
            or np.abs(block[:rt, rt:] - B.T).max(initial=0.0) > 1e-12 * scale):
        return None
    L, info = lapack.dpotrf(M, lower=1)
    if info != 0:
        return None
    W = blas.dtrsm(1.0, L, B.T, lower=1)                                # L⁻¹ Bᵀ
    R, info = lapack.dpotrf(blas.dsyrk(1.0, W, trans=1, lower=1), lower=1)
    if info != 0:
        return None
    Z = blas.dtrsm(1.0, R, W, side=1, lower=1, trans_a=1)               # W R⁻ᵀ
    Z = blas.dtrsm(1.0, R, Z, side=1, lower=1)                          # W S⁻¹
    return blas.dtrsm(1.0, L, Z, lower=1, trans_a=1)                    # L⁻ᵀ W S⁻¹


class _InversePart:
    """The block (outputs, inputs) (slices) of the inverses of n × n blocks, by LAPACK's LU:
    the whole inverse, or solves for the rows (Aᵀ X = E_rows) or the columns (A Y = E_cols)
    wanted, the fewer. A call raises np.linalg.LinAlgError for a singular block."""

    def __init__(self, n, outputs, inputs):
        from scipy.linalg import lapack
        rows, cols = range(n)[outputs], range(n)[inputs]
        self.outputs, self.inputs, self.gesv = outputs, inputs, lapack.dgesv
        self.full = len(rows) == n and len(cols) == n
        self.by_rows = len(rows) <= len(cols)
        self.unit = np.asfortranarray(np.eye(n)[:, rows if self.by_rows else cols])

    def __call__(self, block):
        if self.full:
            return _lu_inverse(block)
        _, _, x, info = self.gesv(block.T if self.by_rows else block, self.unit,
                                  overwrite_a=True)
        if info != 0:
            raise np.linalg.LinAlgError("singular patch block")
        return x.T[:, self.inputs] if self.by_rows else x[self.outputs, :]


def _lu_inverse(block):
    """The inverse of a block by LAPACK's LU (raises np.linalg.LinAlgError if singular)."""
    from scipy.linalg import lapack
    lu, pivots, info = lapack.dgetrf(block)
    if info == 0:
        inverse, info = lapack.dgetri(lu, pivots, overwrite_lu=True)
    if info != 0:
        raise np.linalg.LinAlgError("singular patch block")
    return inverse
