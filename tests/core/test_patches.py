"""The patch engine's sharing of inverses between congruent patches (§5, §6, §12).

* The canonical change of basis: `canonical_block` (in place on CSR rows) equals the dense
  Gᵀ A G, and `BasisChange` (by runs of one patch shape) the products with Gᵀ and G, G built
  independently from the codes and the blocks of `basis_changes` (which itself checks that
  dolfinx's RT and DG bases differ from the canonical ones by signed facet permutations,
  2 × 2 interior blocks and vertex relabelling).
* The classes: translated patches get equal keys, other shapes, codes or positions other keys;
  `Blocks` keeps each class's block; a patch whose key's class has another size gets a class
  of its own (keys that know nothing). That keys decide no more than they may is checked on
  the fluxes (tests/core/test_equilibration.py: keys that only know a patch's size make σ_disc
  fail its divergence check).
* Shared and unshared solves agree to round-off: the patch solutions of the vertex patches of
  a refined disk for random right-hand sides, with and without sharing, differ by at most
  ROUND_OFF relative (measured ~1e-15).
* The sharing happens: on the disk refined J times (boundary vertices moved onto the circle)
  the share of distinct inverses falls with J (measured 0.45, 0.23 at J = 2, 3 from h = 0.3),
  on a structured square all interior patches are translates (13 classes at any size), and on
  2 and 3 processes the same holds with patches straddling processes (mpi_patches.py).
* No matrix over the whole mesh: A assembled on some patches' cells, with rows and columns
  for their dofs only (`homes.assemble_rows`), equals the full A on the dofs inside those
  cells (measured: exactly) and differs on the other dofs of the cells; on 1, 2 and 3
  processes.
"""

import os

import numpy as np
import pytest
from mpi4py import MPI

from membranes.estimation import congruence as engine
from membranes.estimation.congruence import (
    FACET,
    INNER,
    NEGATIVE,
    Blocks,
    basis_changes,
    canonical_block,
)
from membranes.estimation.equilibration import FluxEquilibration, vertex_patches
from membranes.estimation.patches import PatchSystems, colour_vertices, mixed_space
from membranes.fem.discretisation import boundary_dofs
from tests.conftest import mpirun

from .mpi_patches import partial_assembly_error, random_solutions, refined_disk

HERE = os.path.dirname(os.path.abspath(__file__))
ROUND_OFF = 1e-12      # condition ~1e3 of the patch matrices times the blocks' ~1e-15


def _square(n):
    from dolfinx import mesh as dm
    return dm.create_unit_square(MPI.COMM_WORLD, n, n, dm.CellType.triangle, dm.GhostMode.none)


# ## The canonical change of basis against dense linear algebra

def _synthetic(rng, blocks):
    """Codes of 40 home dofs (facets with random signs, interior pairs with random blocks, DG)
    and the dense G (rows dolfinx, columns canonical) they stand for."""
    code, G = [], np.zeros((40, 40))
    i = 0
    while i < 40:
        kind = rng.integers(3) if i < 39 else FACET
        if kind == INNER:
            p = rng.integers(len(blocks))
            code += [(INNER << 2) | (p << engine.BLOCK), (INNER << 2) | 1 | (p << engine.BLOCK)]
            G[i:i + 2, i:i + 2] = blocks[p]
            i += 2
        else:
            negative = kind == FACET and rng.random() < 0.5
            code.append((kind << 2) | (NEGATIVE if negative else 0))
            G[i, i] = -1.0 if negative else 1.0
            i += 1
    return np.array(code, dtype=np.int64), G


def test_canonical_block_is_the_dense_product():
    _, blocks = basis_changes(mixed_space(_square(2)))
    rng = np.random.default_rng(1)
    code, G = _synthetic(rng, blocks)
    A = rng.standard_normal((40, 40))
    A = A + A.T
    sign = np.diag(G).copy()
    sign[(code >> 2) & 3 == INNER] = 1.0
    scaled = sign[:, None] * A * sign[None, :]            # as A.diagonalScale does
    ia = np.arange(0, 40 * 40 + 1, 40)
    ja = np.tile(np.arange(40), 40)
    got = canonical_block(ia, ja, scaled.ravel().copy(), code, blocks).reshape(40, 40)
    expected = G.T @ A @ G
    assert np.abs(got - expected).max() <= 1e-14 * np.abs(expected).max()


@pytest.mark.parametrize("chunk", [None, 3])
def test_basis_change_by_runs_is_the_dense_product(monkeypatch, chunk):
    """BasisChange (G and Gᵀ by slices over runs of patches of one shape) equals the dense G
    built from the codes, for patches in canonical order (facets, interior pairs, DG) of three
    shapes, two runs of one of them; also with the 2 × 2 blocks applied 3 patches at a time
    (APPLY_CHUNK, 2¹⁵ in a run: runs of 4 patches then take two passes, as the runs of large
    meshes do)."""
    if chunk is not None:
        monkeypatch.setattr(engine, "APPLY_CHUNK", chunk)
    _, blocks = basis_changes(mixed_space(_square(2)))
    rng = np.random.default_rng(5)
    code, offsets = [], [0]
    for f, c, d in [(3, 2, 5)] * 4 + [(4, 1, 2)] * 3 + [(3, 2, 5)] * 2 + [(0, 0, 3)]:
        code += [(FACET << 2) | (i % 2) | (NEGATIVE if rng.random() < 0.5 else 0)
                 for i in range(f)]
        for _ in range(c):
            p = int(rng.integers(len(blocks)))
            code += [(INNER << 2) | (p << engine.BLOCK), (INNER << 2) | 1 | (p << engine.BLOCK)]
        code += [(engine.DG << 2) | (i % 3) for i in range(d)]
        offsets.append(len(code))
    code = np.array(code, dtype=np.int16)
    G = np.zeros((code.size, code.size))
    for i, k in enumerate(code.tolist()):
        if (k >> 2) & 3 == INNER:
            if k & 3 == 0:
                G[i:i + 2, i:i + 2] = blocks[(k >> engine.BLOCK) & 7]
        else:
            G[i, i] = -1.0 if k & NEGATIVE else 1.0
    change = engine.BasisChange(code, np.array(offsets), blocks)
    assert len(change.runs) == 4
    v = rng.standard_normal(code.size)
    assert np.allclose(change.apply(v.copy(), transpose=True), G.T @ v, rtol=0, atol=1e-14)
    assert np.allclose(change.apply(v.copy(), transpose=False), G @ v, rtol=0, atol=1e-14)
    # dofs out of the canonical order are refused
    with pytest.raises(RuntimeError):
        engine.BasisChange(code[::-1].copy(), np.array([0, code.size]), blocks)


def test_basis_changes_are_integer_and_invertible():
    signs, blocks = basis_changes(mixed_space(_square(2)))
    assert set(np.unique(signs)) == {-1.0, 1.0}
    assert np.all(np.abs(np.linalg.det(blocks)) == 1.0)
    assert np.array_equal(blocks[0], np.eye(2))        # vertices already in order: identity


def test_a_vertex_order_not_global_is_counted_as_disagreement(monkeypatch):
    """The count of facet dofs on whose canonical function the two cells of the facet
    disagree (`canonical_dofs`; the tests above assert it is 0) sees an order that is not a
    global one: with every cell's first two canonical vertices swapped (the table of orders
    by ranks permuted), two cells along a facet see its vertices in opposite orders wherever
    their third vertices fall on different sides, so the count is positive on a 4 × 4 square
    (measured 24)."""
    from dolfinx import fem
    V = fem.FunctionSpace(_square(4), ("Lagrange", 1))
    assert FluxEquilibration(V).summary()["sharing"]["disagree"] == 0
    table = engine._BY_RANKS.copy()
    for r, p in enumerate(engine._BY_RANKS.tolist()):
        order = engine.ORDERS[p]
        table[r] = engine.ORDERS.index((order[1], order[0], order[2]))
    monkeypatch.setattr(engine, "_BY_RANKS", table)
    assert FluxEquilibration(V).summary()["sharing"]["disagree"] > 0


def test_malformed_blocks_are_refused():
    """The engine's guards on the CSR rows it transforms and keeps: a patch row with a column
    of the next patch (one past its last dof, `Blocks.add`), an interior dof of a cell not
    followed by the cell's other one, and a row that couples the first interior dof of a
    cell but not the second (`canonical_block`) raise instead of mixing patches or applying
    a 2 × 2 block to the wrong entries."""
    _, blocks = basis_changes(mixed_space(_square(2)))
    full = [[0, 1, 2]] * 3
    ia, ja, a, offsets = _csr([(full, np.ones(9)), (full, np.ones(9))])
    assert Blocks().add(ia, ja, a, offsets, np.array([2, 2])).tolist() == [0, 1]
    ja[2] = 3                                # patch 0's first row: the first dof of patch 1
    with pytest.raises(RuntimeError, match="couples two patches"):
        Blocks().add(ia, ja, a, offsets, np.array([2, 2]))
    pair = [(INNER << 2) | (1 << engine.BLOCK), (INNER << 2) | 1 | (1 << engine.BLOCK)]
    code = np.array(pair + [FACET << 2])
    ia, ja, a, _ = _csr([(full, np.arange(9.0))])
    canonical_block(ia, ja, a, code, blocks)                            # well formed
    with pytest.raises(RuntimeError, match="not adjacent"):
        canonical_block(ia, ja, a, code[[0, 2, 1]], blocks)
    ia, ja, a, _ = _csr([([[0, 1], [0, 1], [0, 2]], np.arange(6.0))])   # row 2: dof 0, not 1
    with pytest.raises(RuntimeError, match="couples one interior dof"):
        canonical_block(ia, ja, a, code, blocks)


# ## Classes

def _csr(blocks):
    """The CSR arrays of a block diagonal matrix from (rows: list of column lists, values)."""
    ia, ja, a, offsets = [0], [], [], [0]
    for rows, values in blocks:
        base = offsets[-1]
        for cols in rows:
            ja += [base + c for c in cols]
            ia.append(ia[-1] + len(cols))
        a += list(values)
        offsets.append(base + len(rows))
    return (np.array(ia, dtype=np.int64), np.array(ja, dtype=np.int32), np.array(a),
            np.array(offsets, dtype=np.int64))


def test_keys_of_translates_agree():
    """Keys are equal for a translated patch (positions shifted by far more than the grid,
    with round-off), and differ for another shape, another code or a moved entity: moved
    along DIRECTION, across it, or mirrored in a line along it (the positions are (along,
    across) pairs: the mirror image changes the second coordinate only), or mirrored in a
    line at 45° to it (the two coordinates swap: a key must not be symmetric in them).
    Positions count in units of the patch's h: the patch scaled with its h by 1e-6 keeps
    its key. 1e-3 h is ~7e7 grid units, far from any rounding boundary."""
    rng = np.random.default_rng(4)
    code = np.array([0, 1, 0, 1, (INNER << 2), (INNER << 2) | 1, 8, 9, 10])
    point = rng.random((9, 2))
    h = np.array([0.25])
    offsets = np.array([0, 9])
    key = engine.patch_keys(offsets, code, point, h)
    shifted = (point + [3.7, -1.3]) * (1.0 + 1e-15)
    assert engine.patch_keys(offsets, code, shifted, h) == key
    moved = point.copy()
    moved[2, 0] += 1e-3 * h[0]            # an entity's first dof (the others follow it)
    assert engine.patch_keys(offsets, code, moved, h) != key
    across = point.copy()
    across[2, 1] += 1e-3 * h[0]
    assert engine.patch_keys(offsets, code, across, h) != key
    assert engine.patch_keys(offsets, code, point * [1.0, -1.0], h) != key
    assert engine.patch_keys(offsets, code, point[:, ::-1].copy(), h) != key    # (along ↔ across)
    other = code.copy()
    other[6] ^= engine.INTERIOR
    assert engine.patch_keys(offsets, other, point, h) != key
    assert engine.patch_keys(offsets, code, point * 2.0, h) != key
    # positions in units of h: a mesh in other units (all lengths times 1e-6) gets the same
    # keys, and still tells a moved entity apart
    assert engine.patch_keys(offsets, code, point * 1e-6, h * 1e-6) == key
    assert engine.patch_keys(offsets, code, moved * 1e-6, h * 1e-6) != key
    two = engine.patch_keys(np.array([0, 9, 18]), np.tile(code, 2),
                            np.vstack([point, shifted]), np.array([0.25, 0.25]))
    assert two[0] == two[1] == key[0]


def test_keys_of_patches_too_long_for_a_key_word_differ():
    """A patch whose entities lie more than 2⁶²⁻³⁶ h from its first (cells of aspect ratio
    beyond about 1e7, the graded square of structured_square(16, 16, 8)) has positions that
    no int64 word holds: their cast gave one value for all (and a RuntimeWarning), so two
    such patches of other shapes shared a key, and one was solved with the other's block
    (σ_disc's divergence defect there 0.41 of the right-hand sides). Now each keeps a key of
    its own, and patches of ordinary length keep theirs."""
    import warnings
    code = np.zeros(4, dtype=np.int64)
    offsets = np.array([0, 2, 4])
    h = np.array([1e-20, 1e-20])                  # 1 / h · 2³⁶ ≈ 6.9e30 > 2⁶³
    point = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [2.0, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")            # (the old cast warned)
        wide = engine.patch_keys(offsets, code, point, h)
    assert wide[0] != wide[1]
    ordinary = engine.patch_keys(offsets, code, point, np.array([1.0, 1.0]))
    shifted = engine.patch_keys(offsets, code, point + [0.5, 0.0], np.array([1.0, 1.0]))
    assert ordinary[0] != ordinary[1] and np.array_equal(ordinary, shifted)


def test_blocks_keep_their_classes():
    """Blocks.add: each new class keeps its block (dense), its shape (n, L, n_σ), and more
    classes are numbered on."""
    rng = np.random.default_rng(2)
    full = [[0, 1, 2]] * 3
    other = [[0, 1], [0, 1], [1, 2]]
    M = rng.standard_normal(9) + 2.0
    ia, ja, a, offsets = _csr([(full, M), (other, M[:6])])
    classes = Blocks()
    cls = classes.add(ia, ja, a, offsets, np.array([2, 2]))
    assert cls.tolist() == [0, 1]
    dense = [classes.dense([k])[0] for k in cls]
    assert np.array_equal(dense[0], M.reshape(3, 3))
    assert np.array_equal(dense[1], [[M[0], M[1], 0], [M[2], M[3], 0], [0, M[4], M[5]]])
    assert [classes.shape(k) for k in cls] == [(3, 9, 2), (3, 6, 2)]
    assert classes.add(ia, ja, a, offsets, np.array([2, 2])).tolist() == [2, 3]
    assert classes.count() == 4


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="serial reference")
def test_a_key_of_another_size_gets_a_class_of_its_own(monkeypatch):
    """With keys that know nothing (all equal), the patches of another size than their key's
    first are collisions with classes of their own, so that every patch is solved with a block
    of its own size (the solves of such patches equal the unshared ones; those of one size
    but other shapes do not: the fluxes' divergence check refuses them, see
    test_equilibration.py)."""
    from membranes.estimation import homes as module
    mesh = refined_disk(MPI.COMM_WORLD, 0.3, 1)
    monkeypatch.setattr(module, "patch_keys",
                        lambda offsets, *_: np.zeros(len(offsets) - 1, dtype=np.uint64))
    careless, _, _, _ = random_solutions(mesh)
    stats = careless.stats()
    assert stats["collisions"] > 0.3 * stats["patches"]
    assert stats["classes"] > stats["collisions"]


# ## Shared and unshared solves, and the sharing rate

@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="serial reference; see mpi_patches.py")
def test_shared_and_unshared_solves_agree():
    mesh = refined_disk(MPI.COMM_WORLD, 0.3, 2)
    shared, unshared, scale, diff = random_solutions(mesh)
    stats = shared.stats()
    assert stats["classes"] < 0.6 * stats["patches"]
    assert unshared.stats()["classes"] == stats["patches"]
    assert stats["collisions"] == 0 and stats["disagree"] == 0
    assert scale > 0.1
    assert diff <= ROUND_OFF * scale


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="serial rates")
def test_sharing_grows_with_refinement():
    from dolfinx import fem
    rates = []
    for J in (1, 2, 3):
        V = fem.FunctionSpace(refined_disk(MPI.COMM_WORLD, 0.3, J), ("Lagrange", 1))
        stats = FluxEquilibration(V).summary()["sharing"]
        assert stats["collisions"] == 0 and stats["disagree"] == 0
        rates.append(stats["classes"] / stats["patches"])
    assert rates[0] > rates[1] > rates[2]
    assert rates[2] < 0.3, rates


def test_structured_square_has_few_classes():
    """All patches of interior vertices of create_unit_square are translates: the classes are
    those of the interior, the four sides and the four corners' kinds (13 in all, whatever n;
    on several processes each process has its own)."""
    from dolfinx import fem
    for n in (8, 16):
        V = fem.FunctionSpace(_square(n), ("Lagrange", 1))
        stats = FluxEquilibration(V).summary()["sharing"]
        assert stats["patches"] == (n + 1) ** 2
        assert stats["collisions"] == 0 and stats["disagree"] == 0
        if MPI.COMM_WORLD.size == 1:      # neither more (no sharing) nor fewer (blocks shared
            assert stats["classes"] == 13    # between patches of other kinds)
        else:
            assert stats["classes"] <= 13 * MPI.COMM_WORLD.size


def test_unshared_engine_gives_the_same_flux():
    """σ_disc with sharing equals σ_disc of the engine without sharing (PatchSystems(share=
    False) in FluxEquilibration's place), on a refined disk."""
    from dolfinx import fem

    from .mpi_equilibration import MU, Compatible, equilibrate
    data = Compatible(refined_disk(MPI.COMM_WORLD, 0.4, 2))
    eq, sigmas = equilibrate(data)
    patches, interior = vertex_patches(data.V, eq.colour, eq.ncolours, eq.on_boundary)
    eq.systems = PatchSystems(data.mesh, patches, interior, eq.systems.W, share=False)
    eq._loads = {}
    for alpha in (1, 2):
        other = eq.sigma(alpha, data.u, data.lam, data.r[alpha], data.f, MU)
        a, b = data.functionals(sigmas[alpha]), data.functionals(other)
        assert np.abs(a - b).max() <= ROUND_OFF * np.abs(a).max()
        diff = fem.Function(other.function_space)
        diff.x.array[:] = other.x.array - sigmas[alpha].x.array
        assert data.functionals(diff)[0] <= (ROUND_OFF ** 2) * a[0]


@pytest.mark.parametrize("declined", [False, True])
def test_reduced_operators(monkeypatch, declined):
    """rhs="divergence" (data only on DG rows) and solution="flux" (only σ): the RT part of the
    solutions equals the full solve's to round-off (the Schur complement path of §6's blocks
    against LU), and γ is returned as zero. `declined`: every block declined by the Schur
    complement path (as an ill-conditioned one is) takes the LU path instead, with the same
    result (its operator was once left unset)."""
    from petsc4py import PETSc

    from membranes.estimation import congruence

    from .mpi_patches import vertex_groups
    if declined:
        monkeypatch.setattr(congruence, "_saddle_corner", lambda block, rt: None)
    mesh = refined_disk(MPI.COMM_WORLD, 0.4, 1)
    patches, interior = vertex_groups(mesh)
    W = mixed_space(mesh)
    rt = np.zeros(W.dofmap.index_map.size_local, dtype=bool)
    rt[W.sub(0).dofmap.list.array[W.sub(0).dofmap.list.array < rt.size]] = True
    b = PETSc.Vec().createMPI((rt.size, PETSc.DECIDE), comm=mesh.comm)
    b.array[:] = np.random.default_rng(3 + mesh.comm.rank).standard_normal(rt.size)
    full = PatchSystems(mesh, patches, interior, W)
    for rhs, solution in (("full", "flux"), ("divergence", "flux"), ("divergence", "full")):
        if rhs == "divergence":
            b.array[rt] = 0.0
        reduced = PatchSystems(mesh, patches, interior, W, rhs=rhs, solution=solution)
        for c in range(len(patches)):
            x, y = full.solve(c, b), reduced.solve(c, b)
            scale = mesh.comm.allreduce(np.abs(x.array).max(initial=0.0), op=MPI.MAX)
            part = rt if solution == "flux" else slice(None)
            diff = np.abs(x.array[part] - y.array[part]).max(initial=0.0)
            assert mesh.comm.allreduce(diff, op=MPI.MAX) <= ROUND_OFF * scale
            if solution == "flux":
                assert np.all(y.array[~rt] == 0.0)
    with pytest.raises(ValueError):
        PatchSystems(mesh, patches, interior, W, rhs="data")


def test_routes_by_slices_and_by_positions_agree(monkeypatch):
    """The home's own entries move as slices (runs of at least RUN home positions) or one by
    one (`PatchSystems._own_route`): both give the same gathers and solutions, bit for bit."""
    from petsc4py import PETSc

    import membranes.estimation.patches as engine

    from .mpi_patches import vertex_groups
    mesh = refined_disk(MPI.COMM_WORLD, 0.4, 2)
    patches, interior = vertex_groups(mesh)
    W = mixed_space(mesh)
    n = W.dofmap.index_map.size_local
    b = PETSc.Vec().createMPI((n, PETSc.DECIDE), comm=mesh.comm)
    b.array[:] = np.random.default_rng(5 + mesh.comm.rank).standard_normal(n)
    results = []
    for run in (1, 1 << 40):                       # every run a slice; none
        monkeypatch.setattr(engine, "RUN", run)
        systems = PatchSystems(mesh, patches, interior, W)
        sliced = sum(sum(r[2] for r in route[1]) for route in systems.local)
        single = sum(route[2].size for route in systems.local)
        home = systems.home_vector()
        homes = [systems.gather(c, b, home).copy() for c in range(len(patches))]
        results.append((sliced, single, homes, [systems.solve(c, b).array.copy()
                                                 for c in range(len(patches))]))
    (sliced, single, home, x), (sliced_0, single_0, home_0, x_0) = results
    assert single == 0 and sliced_0 == 0 and sliced == single_0 > 0
    assert all(np.array_equal(a, a_0) for a, a_0 in zip(home, home_0))
    assert all(np.array_equal(a, a_0) for a, a_0 in zip(x, x_0))


def test_a_groups_gather_writes_its_whole_part_of_the_home_vector():
    """σ_disc reuses one home vector for every colour without zeroing it (equilibration):
    right because a group's patches make up its part of the home vector, so its gather writes
    every entry there (here a NaN-filled home keeps no NaN). The groups' parts add up to all
    the patches' kept dofs, and the buffer is the largest part."""
    from .mpi_patches import uncovered, vertex_groups
    mesh = refined_disk(MPI.COMM_WORLD, 0.4, 2)
    patches, interior = vertex_groups(mesh)
    systems = PatchSystems(mesh, patches, interior, mixed_space(mesh))
    left, home = uncovered(systems, len(patches))
    assert left == 0 and home == systems.home_size > 0
    assert systems.home_vector().size == np.diff(systems.group_starts).max()
    assert systems.home_vector().size < systems.home_size
    # another group's gather leaves entries unwritten: the count sees them
    assert uncovered(systems, len(patches), every=False)[0] > 0


def test_stable_order_is_a_stable_argsort():
    from membranes.estimation.patches import stable_order
    rng = np.random.default_rng(6)
    for top in (5, 70000, 1 << 40):
        keys = rng.integers(0, top, 5000)
        assert np.array_equal(stable_order(keys), np.argsort(keys, kind="stable"))
    assert stable_order(np.zeros(0, dtype=np.int64)).size == 0
    keys = rng.integers(0, 1 << 20, 5000).astype(np.int32)
    assert np.array_equal(stable_order(keys), np.argsort(keys, kind="stable"))


def test_vertex_graph_lists_the_sorted_neighbours():
    """vertex_graph against sets of pairs: every vertex's neighbours through the cells, once,
    in increasing order (a vertex repeated in a cell is its own neighbour)."""
    from membranes.estimation.exchange import vertex_graph
    rng = np.random.default_rng(7)
    for width, nv in ((2, 30), (3, 40), (4, 25), (3, 5)):
        cells = rng.integers(0, nv, (60, width)).astype(np.int32)
        offsets, nbrs = vertex_graph(cells, nv + 2)
        assert offsets.size == nv + 3 and nbrs.dtype == np.int64
        for v in range(nv + 2):
            want = sorted({int(c[q]) for c in cells for p in range(width)
                           for q in range(width) if p != q and c[p] == v})
            assert nbrs[offsets[v]:offsets[v + 1]].tolist() == want
    offsets, nbrs = vertex_graph(np.zeros((0, 3), dtype=np.int32), 4)
    assert offsets.tolist() == [0] * 5 and nbrs.size == 0


def test_colouring_and_boundary_helpers_used_by_the_groups():
    """vertex_patches: every owned cell is in exactly three groups (one per vertex)."""
    from dolfinx import fem
    V = fem.FunctionSpace(_square(5), ("Lagrange", 1))
    nc = V.mesh.topology.index_map(2).size_local
    cells = V.dofmap.list.array.reshape(-1, 3)[:nc]
    colour, ncolours, _ = colour_vertices(cells, V.dofmap.index_map, V.mesh.comm)
    patches, interior = vertex_patches(V, colour, ncolours, boundary_dofs(V))
    assert np.all(sum((p >= 0).astype(int) for p in patches) == 3)
    assert all(np.all(~i[p < 0]) for p, i in zip(patches, interior))


# ## No matrix over the whole mesh

def test_partial_assembly_keeps_the_inside_blocks():
    """A assembled on some patches' cells into rows for their dofs only
    (`homes.assemble_rows`) equals A over the whole mesh on the dofs all of whose cells are
    marked (those are the kept dofs of the marked patches), and differs on the others (the
    assembly is partial)."""
    inside, outside, entry, ninside = partial_assembly_error(refined_disk(MPI.COMM_WORLD, 0.3, 1))
    assert ninside > 100
    assert inside <= 1e-14 * entry
    assert outside > 0.01 * entry


# ## On several processes

@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
@pytest.mark.parametrize("nproc", [2, 3])
def test_parallel_sharing(nproc):
    out = mpirun([os.path.join(HERE, "mpi_patches.py")], processes=nproc, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    fields = dict(item.split("=") for item in out.stdout.split("OK")[-1].split())
    assert int(fields["P"]) == nproc
    assert int(fields["straddling"]) > 0
    assert int(fields["classes"]) < int(fields["patches"])
    assert float(fields["diff"]) <= ROUND_OFF * float(fields["scale"])
    assert int(fields["collisions"]) == 0
    assert int(fields["ninside"]) > 100
    assert float(fields["inside"]) <= 1e-14 * float(fields["entry"])
    assert float(fields["outside"]) > 0.01 * float(fields["entry"])
    assert int(fields["uncovered"]) == 0 and int(fields["home"]) > 0
    assert int(fields["same_keys"]) == 1
