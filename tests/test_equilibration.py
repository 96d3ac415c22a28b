"""Exactness of the equilibrated flux (DESIGN §4, §5), to round-off relative to the data.

On every cell ∇·σ_1,disc = Π_P1 f1 + λh - r1h and ∇·σ_2,disc = Π_P1 f2 - λh - r2h, and the
normal traces of σ_α,disc are continuous across interior facets. Both are checked at the
converged iterate (r = 0 to round-off), at a GMRES iterate inside a Newton step (r ≠ 0), and at
an arbitrary perturbation X with R = F - E X.
∇·σ is in DG1, so the first identity is tested against every DG1 function q:
(∇·σ - f ∓ λh + r, q)_K = 0 for all K (the (f, q) part is then (Π_P1 f, q)).
"""

import numpy as np
import pytest
import ufl

from membranes.discretisation import assemble_vector_array, over
from membranes.equilibration import _MINV_REF, FluxEquilibration, Geometry
from membranes.newton_system import linear_rows, split
from membranes.problem import as_builder

from .conftest import solved, solved_on

RNG = np.random.default_rng(1)


def lifting(geo):
    """The lifting R ↦ r_h of DESIGN §4 as a sparse matrix (DG1 coefficients, 3 per cell in
    vertex order): the reference for equilibration.Lifting, which applies it without one."""
    import scipy.sparse as sp
    rows = np.repeat(np.arange(3 * geo.ncells), 3)
    cols = np.repeat(geo.cells, 3, axis=0).ravel()
    scale = (3.0 / geo.area)[:, None, None] * _MINV_REF[None] \
        / geo.cells_per_vertex[geo.cells][:, None, :]
    return sp.csr_matrix((scale.ravel(), (rows, cols)), shape=(3 * geo.ncells, geo.n))


@pytest.fixture(scope="module", params=[("disk", 0.1, 0), ("square", 0.1, 0), ("disk", 0.3, 3)],
                ids=["disk", "square", "disk-refined"])
def setup(request):
    name, h, levels = request.param
    run = solved(name, h) if levels == 0 else solved_on(name, h, levels, estimators=False)
    return run, FluxEquilibration(run.disc)


def _iterate(run, which):
    """(X, R): the converged iterate, the first GMRES iterate X^{1,1} of the first Newton step
    (its true residual R = B - A X), or an arbitrary perturbation X with R = F - E X."""
    d = run.disc
    rows = linear_rows(d)
    if which == "converged":
        X = run.X
        return X, np.concatenate([rows.F - rows.E @ X, np.zeros(d.n)])
    if which == "krylov":
        from membranes.krylov import Krylov
        from membranes.newton import semismooth_newton
        seen = []
        semismooth_newton(rows, d.problem.g, variant="exact", krylov=Krylov(nu=1), max_it=1,
                          monitor=lambda rec, X, R: seen.append((rec["kind"], X, R)))
        return next((X, R) for kind, X, R in seen if kind == "krylov")
    inner = d.interior.astype(float)
    X = run.X + np.concatenate([
        1e-2 * d.problem.g * RNG.standard_normal(d.n) * inner,
        1e-2 * d.problem.g * RNG.standard_normal(d.n) * inner,
        1e-1 * np.abs(run.X[2 * d.n:]).max() * RNG.random(d.n) * inner])
    return X, np.concatenate([rows.F - rows.E @ X, np.zeros(d.n)])


@pytest.mark.parametrize("which", ["converged", "krylov", "perturbed"])
def test_divergence_and_normal_continuity(setup, which):
    from dolfinx import fem
    run, eq = setup
    d, problem = run.disc, run.disc.problem
    X, R = _iterate(run, which)
    assert np.all(R[d.boundary] == 0) and np.all(R[d.n + d.boundary] == 0)
    if which != "converged":
        assert np.abs(R[:2 * d.n]).max() > 1e-6 * np.abs(linear_rows(d).F).max()
    n = d.n
    u1, u2, lam = split(X, n)
    mesh = problem.mesh
    DG = fem.FunctionSpace(mesh, ("DG", 1))
    q = ufl.TestFunction(DG)
    x = ufl.SpatialCoordinate(mesh)
    lam_h = fem.Function(d.V)
    lam_h.x.array[:] = lam
    dg_cells = DG.dofmap.list.array.reshape(-1, 3)
    for alpha, u, Ra, f in ((1, u1, R[:n], problem.f1), (2, u2, R[n:2 * n], problem.f2)):
        sigma = fem.Function(eq.RT)
        sigma.x.array[:] = eq.sigma(alpha, u, lam, Ra)
        r = fem.Function(DG)
        r.x.array[dg_cells.ravel()] = eq.lift @ Ra
        sign = 1.0 if alpha == 1 else -1.0
        fx = as_builder(f)(x)
        defect = assemble_vector_array(over(d.dx_data, lambda dx: (
            ufl.div(sigma) - fx - sign * lam_h + r) * q * dx))
        scale = assemble_vector_array(over(d.dx_data, lambda dx: (
            abs(fx) + abs(lam_h) + abs(r)) * q * dx))   # DG1 basis functions are ≥ 0
        # round-off: each entry is a sum of O(10) products of O(scale) numbers
        assert np.abs(defect).max() <= 1e-11 * np.abs(scale).max()
        nrm = ufl.FacetNormal(mesh)
        jump = fem.assemble_scalar(fem.form(ufl.jump(sigma, nrm) ** 2 * ufl.dS))
        size = fem.assemble_scalar(fem.form(ufl.inner(sigma, sigma) * ufl.dx))
        assert jump <= 1e-24 * size


def test_lifting_reproduces_the_residual(setup):
    """(r_h, ψ_l)_Ω = R_l for every vertex l (DESIGN §4), with exact P1 × DG1 integrals."""
    run, eq = setup
    geo = Geometry(run.disc.V)
    R = RNG.standard_normal(geo.n)
    R[run.disc.boundary] = 0.0
    r = (lifting(geo) @ R).reshape(-1, 3)
    # (r, ψ_k)_K = |K|/12 (r_k + Σ r) for r ∈ P1(K) in the cell's vertex order
    local = geo.area[:, None] / 12.0 * (r + r.sum(axis=1, keepdims=True))
    back = np.bincount(geo.cells.ravel(), local.ravel(), minlength=geo.n)
    assert np.allclose(back, R, rtol=0, atol=1e-13 * np.abs(R).max())
    # the set-up applies the same formula without storing the matrix
    assert np.allclose(eq.lift @ R, lifting(geo) @ R, rtol=0, atol=1e-13 * np.abs(r).max())


def test_operators_are_linear_in_the_data(setup):
    """σ(u, λ, R) = μ G_u u ± G_λ λ + G_R R + σ_f: the set-up is linear, so σ of a sum of
    iterates minus σ_f twice equals the sum of the σ's minus σ_f, to round-off."""
    run, eq = setup
    n = run.disc.n
    a, b = (RNG.standard_normal(n) for _ in range(2))
    lam, R = RNG.standard_normal(n), RNG.standard_normal(n)
    s_ab = eq.sigma(1, a + b, 2 * lam, 2 * R)
    s_a, s_b = eq.sigma(1, a, lam, R), eq.sigma(1, b, lam, R)
    assert np.allclose(s_ab - eq.sigma_f[:, 0], s_a + s_b - 2 * eq.sigma_f[:, 0],
                       atol=1e-12 * np.abs(s_ab).max())


def test_translated_patches_share_operators():
    """On a uniform refinement most vertex patches are translates of a few: their σ_a come
    from one operator per class (change of basis with entries 0, ±1); the result is the σ of
    every patch solved on its own, to round-off."""
    run = solved_on("disk", 0.3, 3, estimators=False)
    d = run.disc
    shared = FluxEquilibration(d)
    assert shared.classes is not None
    per_class = sum(len(G) for _, G, _, _ in shared.classes[0])
    assert per_class > 0.8 * d.n
    FluxEquilibration.TRANSLATES = False
    try:
        alone = FluxEquilibration(d)
    finally:
        FluxEquilibration.TRANSLATES = True
    assert alone.classes is None
    u, lam, R = (RNG.standard_normal(d.n) for _ in range(3))
    R[d.boundary] = 0.0
    for alpha in (1, 2):
        for Ra in (R, None):
            a, b = shared.sigma(alpha, u, lam, Ra), alone.sigma(alpha, u, lam, Ra)
            assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()


def _discretisation(kind):
    """Small discretisations: the gmsh disk refined twice (translated classes, curved ∂Ω), the
    structured square (translates up to its corners) and the gmsh square."""
    from membranes import scenes
    from membranes.discretisation import discretise
    from membranes.meshes import structured_square
    if kind == "disk-refined":
        return discretise(scenes.disk(h=0.3, levels=2))
    if kind == "structured":
        return discretise(scenes.square(mesh=structured_square(6, 6)))
    return discretise(scenes.square(h=0.25))


def _assembled_blocks(space, form, rows, cols, colours=True):
    """An independent computation of per-cell blocks: dolfinx assembles `form(dx)` colour by
    colour of cells that share no edge (each assembled entry then belongs to one cell; with
    colours=False, once, for forms whose entries belong to one cell anyway) and the blocks
    A[rows[K]][:, cols[K]] are read off the matrices."""
    from dolfinx import mesh as dmesh
    from membranes.discretisation import assemble_matrix_csr
    from membranes.equilibration import graph_colouring
    mesh = space.V.mesh
    nc = space.geo.ncells
    colour = np.zeros(nc, dtype=np.int64)
    if colours:
        mesh.topology.create_connectivity(1, 2)
        e2c = mesh.topology.connectivity(1, 2)
        counts = np.diff(e2c.offsets)
        pairs = e2c.array[np.repeat(counts == 2, counts)].reshape(-1, 2).astype(np.int64)
        colour = graph_colouring(pairs, nc)
    out = np.empty((nc, rows.shape[1], cols.shape[1]))
    for c in np.unique(colour):
        cells = np.flatnonzero(colour == c).astype(np.int32)
        dx = ufl.dx
        if colours:
            tags = dmesh.meshtags(mesh, 2, cells, np.ones_like(cells))
            dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)(1)
        A = assemble_matrix_csr(form(dx)).toarray()
        out[cells] = A[rows[cells][:, :, None], cols[cells][:, None, :]]
    return out


@pytest.mark.parametrize("kind", ["disk-refined", "structured"])
def test_element_blocks_match_dolfinx_assembly(kind):
    """The per-cell RT_1 × DG1 blocks computed from reference integrals and the Piola map (with
    dolfinx's edge reflections) and the load moments equal the entries of matrices that dolfinx
    assembles from the UFL forms. Both integrate the same polynomials exactly (the loads with
    the same quadrature) and differ in the order of the floating-point sums only: round-off,
    relative to the largest entry of each block type."""
    from dolfinx import fem
    from forms.equilibration import divergence, rt_mass, vector_moment, weighted_mass
    from membranes.discretisation import load, over
    from membranes.equilibration import _SYM, PatchSpace, load_moments
    d = _discretisation(kind)
    space = PatchSpace(d.V)
    nc = space.geo.ncells
    assert len(np.unique(space.reflections)) > 1         # some edges are reflected
    sig, tau = ufl.TrialFunction(space.RT), ufl.TestFunction(space.RT)
    p, q = ufl.TrialFunction(space.DG), ufl.TestFunction(space.DG)
    rt, dg = space.rt_cells, space.dg_cells.astype(np.int64)
    W = fem.VectorFunctionSpace(d.V.mesh, ("DG", 1))
    wc = W.dofmap.list.array.reshape(nc, -1).astype(np.int64)
    wcols = (2 * wc[:, :, None] + np.arange(2)).reshape(nc, 6)          # (k, d) -> 2k + d
    mesh = d.V.mesh
    cases = [(space.Me, lambda dx: rt_mass(sig, tau, dx), rt, rt, True),
             (space.Be, lambda dx: divergence(sig, q, dx), dg, rt, True),
             (space.vector_moments(np.arange(nc)),
              lambda dx: vector_moment(ufl.TrialFunction(W), tau, dx), rt, wcols, True)]
    Wf = load_moments(d, space.geo)[0]                           # (ncells, 6, 2), symmetric
    for alpha, f in enumerate((d.problem.f1, d.problem.f2)):
        wf = Wf[:, _SYM, alpha]                                     # (ncells, 3, 3)
        # DG1 × DG1: every entry belongs to one cell (the data measures as the scene has them)
        cases.append((wf, lambda dx, f=f: over(d.dx_data, lambda dxd: weighted_mass(
            load(f, mesh), p, q, dxd)), dg, dg, False))
    for mine, form, rows, cols, colours in cases:
        ref = _assembled_blocks(space, form, rows, cols, colours)
        assert np.abs(mine - ref).max() <= 1e-13 * np.abs(ref).max()


def _patchwise_sigma(d, alpha, u, lam, R):
    """σ_α,disc summed from every vertex patch's problem assembled by dolfinx from the UFL forms
    of DESIGN §5 (global RT_1 × DG1 matrices; right-hand sides as columns a of matrices with
    ψ_a the P1 trial function), restricted to the patch's dofs (the generic rule of
    `retained_dofs`) and solved densely: independent of the set-up's element blocks, classes,
    translates and operators."""
    from dolfinx import fem
    from forms.equilibration import divergence, rt_mass
    from membranes.discretisation import assemble_matrix_csr, assemble_vector_array, load, over
    from membranes.equilibration import PatchSpace, vertex_patches
    space = PatchSpace(d.V, blocks=False)
    geo, mesh = space.geo, d.V.mesh
    sig, tau = ufl.TrialFunction(space.RT), ufl.TestFunction(space.RT)
    q, psi = ufl.TestFunction(space.DG), ufl.TrialFunction(d.V)
    mu = d.problem.mu1 if alpha == 1 else d.problem.mu2
    sign = 1.0 if alpha == 1 else -1.0
    f = load(d.problem.f1 if alpha == 1 else d.problem.f2, mesh)
    uh, r = fem.Function(d.V), fem.Function(space.DG)
    uh.x.array[:] = u
    r.x.array[space.dg_cells.ravel()] = lifting(geo) @ R
    M = assemble_matrix_csr(rt_mass(sig, tau)).toarray()
    B = assemble_matrix_csr(divergence(sig, q)).toarray()
    mass_q = assemble_vector_array(q * ufl.dx)                               # (1, q_i)
    G = assemble_matrix_csr(-psi * mu * ufl.inner(ufl.grad(uh), tau) * ufl.dx).toarray()
    g = assemble_matrix_csr(over(d.dx_data, lambda dx: (psi * (f - r) - mu * ufl.inner(
        ufl.grad(uh), ufl.grad(psi))) * q * dx)).toarray()
    g_lam = assemble_matrix_csr(psi * q * ufl.dx).toarray()                 # (ψ_a, q)
    on_boundary = np.zeros(geo.n, dtype=bool)
    on_boundary[d.boundary] = True
    total = np.zeros(space.nrt)
    for verts, CS, KA in vertex_patches(geo):
        glob = space.retained_dofs(CS, on_boundary[verts])
        for a, cells, dofs in zip(verts, CS, glob):
            rt = np.unique(dofs[dofs >= 0])
            dg = np.unique(space.dg_cells[cells])
            nr, nq = len(rt), len(dg)
            extra = 0 if on_boundary[a] else 1
            A = np.zeros((nr + nq + extra,) * 2)
            A[:nr, :nr] = M[np.ix_(rt, rt)]
            A[:nr, nr:nr + nq] = -B[np.ix_(dg, rt)].T
            A[nr:nr + nq, :nr] = B[np.ix_(dg, rt)]
            if extra:
                A[nr:nr + nq, -1] = A[-1, nr:nr + nq] = mass_q[dg]
            b = np.concatenate([G[rt, a], g[dg, a] + sign * lam[a] * g_lam[dg, a],
                                np.zeros(extra)])
            total[rt] += np.linalg.solve(A, b)[:nr]
    return total


@pytest.mark.parametrize("kind", ["disk-refined", "structured", "square"])
def test_sigma_matches_patch_problems_assembled_by_dolfinx(kind):
    """The set-up's σ_disc (classes of translates, their changes of basis, operators, σ_f)
    equals the sum of the patch problems assembled by dolfinx and solved one by one, at
    random data, to round-off: the same patch systems (a few dozen unknowns, condition numbers
    ≤ 2.2e3 on these meshes) solved by two factorisations from entries that agree to round-off
    differ by ≲ 2.2e3 · 10 ε ≈ 5e-12 relative to |σ| (measured: ≤ 6e-15)."""
    d = _discretisation(kind)
    eq = FluxEquilibration(d)
    if kind != "square":
        assert eq.classes is not None
    rng = np.random.default_rng(7)
    u, lam, R = (rng.standard_normal(d.n) for _ in range(3))
    R[d.boundary] = 0.0
    for alpha in (1, 2):
        ref = _patchwise_sigma(d, alpha, u, lam, R)
        assert np.abs(eq.sigma(alpha, u, lam, R) - ref).max() <= 5e-12 * np.abs(ref).max()


@pytest.mark.parametrize("kind", ["disk-refined", "structured"])
def test_owned_vertices_partition_sigma(kind):
    """Set up for the patches of a subset of the vertices (one process's share): the parts of a
    partition of the vertices add up to σ_disc, to round-off (the parts class and solve their
    patches apart, so each σ_a is computed by another, equally accurate, path)."""
    from membranes.estimators import Estimators
    d = _discretisation(kind)
    full = FluxEquilibration(d)
    rng = np.random.default_rng(3)
    owned = rng.random(d.n) < 0.5
    parts = [Estimators(d, owned=owned).flux, FluxEquilibration(d, owned=~owned)]
    u, lam, R = (rng.standard_normal(d.n) for _ in range(3))
    R[d.boundary] = 0.0
    for alpha in (1, 2):
        for Ra in (R, None):
            whole = full.sigma(alpha, u, lam, Ra)
            split = sum(p.sigma(alpha, u, lam, Ra) for p in parts)
            assert np.abs(split - whole).max() <= 1e-12 * np.abs(whole).max()
            assert np.abs(parts[0].sigma(alpha, u, lam, Ra) - whole).max() \
                > 0.1 * np.abs(whole).max()                        # a part is not the whole


def test_translated_patches_on_a_structured_square():
    """On a structured square almost every patch is a translate (corners and ∂Ω edges told
    apart by the classes): shared operators give each patch's own σ_a, to round-off."""
    d = _discretisation("structured")
    shared = FluxEquilibration(d)
    assert sum(len(G) for _, G, _, _ in shared.classes[0]) > 0.5 * d.n
    FluxEquilibration.TRANSLATES = False
    try:
        alone = FluxEquilibration(d)
    finally:
        FluxEquilibration.TRANSLATES = True
    u, lam, R = (RNG.standard_normal(d.n) for _ in range(3))
    R[d.boundary] = 0.0
    for alpha in (1, 2):
        a, b = shared.sigma(alpha, u, lam, R), alone.sigma(alpha, u, lam, R)
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max()


def test_estimators_from_parts_summed_over_processes():
    """Estimators set up for one part of the vertices, whose σ_disc parts are added by
    `sum_parts` (here the other part's σ, as a sum over two processes would give), evaluate as
    the estimators of the whole, to round-off."""
    from membranes.estimators import Estimators
    from membranes.newton_system import split
    d = _discretisation("structured")
    owned = np.random.default_rng(4).random(d.n) < 0.5
    other = FluxEquilibration(d, owned=~owned)
    rng = np.random.default_rng(5)
    X = rng.standard_normal(3 * d.n) * np.tile(d.interior, 3)

    def add_other(parts):
        u1, u2, lam = split(X, d.n)
        return [parts[0] + other.sigma(1, u1, lam, None),
                parts[1] + other.sigma(2, u2, lam, None)]
    whole = Estimators(d).evaluate(X)
    parts = Estimators(d, owned=owned, sum_parts=add_other).evaluate(X)
    for key in ("eta", "eta_disc", "eta_F"):
        assert parts[key] == pytest.approx(whole[key], rel=1e-12, abs=0)
    assert np.abs(parts["eta_K"] - whole["eta_K"]).max() <= 1e-12 * whole["eta_K"].max()


def test_translation_classes_regroup_near_translates():
    """Patches whose rounded offsets coincide but which are not translates to round-off (a
    gmsh mesh has such near-translates, equal to 1e-8 of their size) must not share an
    operator, and must still be classed with their own exact translates: copies of a fan of
    six triangles A (exact translates by multiples of 2^k: no round-off) and of its
    near-translate B (one vertex moved by 1e-8) give the classes {A...} and {B...}, in
    whatever order they come. Before the regrouping, every B was made its own class."""
    from types import SimpleNamespace
    from membranes.equilibration import translation_classes
    rng = np.random.default_rng(1)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 6))
    ring = np.stack([np.cos(angles), np.sin(angles)], axis=1) * rng.uniform(0.8, 1.2, (6, 1))
    fan = np.vstack([[0.0, 0.0], ring])                      # centre, then the ring
    near = fan.copy()
    near[3] += 1e-8
    cells = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])
    shifts = [(0.0, 0.0), (8.0, 0.0), (0.0, 16.0), (8.0, 8.0), (16.0, 0.0), (16.0, 16.0)]
    kinds = ["A", "B", "A", "B", "B", "A"]
    xs, cs, xa = [], [], []
    for k, (kind, shift) in enumerate(zip(kinds, shifts)):
        pts = (fan if kind == "A" else near) + np.array(shift)
        xs.append(pts)
        cs.append(cells + 7 * k)
        xa.append(pts[0])
    geo = SimpleNamespace(x=np.vstack(xs), cells=np.vstack(cs))
    cent = geo.x[geo.cells].mean(axis=1)
    P = len(kinds)
    CF = np.arange(6 * P).reshape(P, 6)
    CF, KF, rep, pi = translation_classes(np.array(xa), CF, np.zeros_like(CF),
                                          np.zeros(P, dtype=bool), geo, cent, 1.0)
    classes = {}
    for p in range(P):
        classes.setdefault(rep[p], set()).add(kinds[p])
    assert sorted(map(sorted, classes.values())) == [["A"], ["B"]]
    assert len(classes) == 2
    # the vertex matches put every patch vertex on its representative's
    for p in range(P):
        mine = geo.x[geo.cells[CF[p]]] - np.array(xa[p])
        theirs = geo.x[geo.cells[CF[rep[p]]]] - np.array(xa[rep[p]])
        matched = np.take_along_axis(theirs, pi[p][..., None].astype(int), axis=1)
        assert np.abs(mine - matched).max() <= 1e-13


def test_vertex_patches_are_the_cells_at_each_vertex():
    """`vertex_patches` (a compiled counting sort of the cells' vertex slots, then a gather per
    patch size) lists, for every vertex, exactly the cells that contain it in ascending order
    and the vertex's local index in each: compared with numpy's stable argsort of the slots."""
    from membranes.equilibration import vertex_patches
    geo = Geometry(_discretisation("disk-refined").V)
    order = np.argsort(geo.cells.ravel(), kind="stable")
    ptr = np.concatenate([[0], np.cumsum(geo.cells_per_vertex)])
    seen = 0
    for verts, CS, KA in vertex_patches(geo):
        idx = order[ptr[verts][:, None] + np.arange(CS.shape[1])]
        assert np.array_equal(CS, idx // 3) and np.array_equal(KA, idx % 3)
        assert np.array_equal(geo.cells[CS, KA], np.repeat(verts[:, None], CS.shape[1], 1))
        seen += len(verts)
    assert seen == geo.n


def test_translation_classes_without_classes_when_keys_overflow():
    """Keys in units of 1e-6 scale must fit in 31 bits: with a scale so small that a patch
    spans more than 2^30 units, the compiled signature loop reports the overflow and every
    patch is its own class (identity vertex matches), rather than wrapped keys joining
    patches that are not translates."""
    from types import SimpleNamespace
    from membranes.equilibration import translation_classes
    fan = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [-0.5, 1.0], [-1.0, 0.0],
                    [-0.5, -1.0], [0.5, -1.0]])
    cells = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])
    geo = SimpleNamespace(x=np.vstack([fan, fan + 4.0]), cells=np.vstack([cells, cells + 7]))
    cent = geo.x[geo.cells].mean(axis=1)
    CF = np.arange(12).reshape(2, 6)
    xa = geo.x[[0, 7]]
    for scale, classes in ((1.0, 1), (1e-4, 2)):
        _, _, rep, pi = translation_classes(xa, CF, np.zeros_like(CF), np.zeros(2, dtype=bool),
                                            geo, cent, scale)
        assert len(np.unique(rep)) == classes
    assert np.array_equal(pi, np.broadcast_to(np.arange(3), pi.shape))
