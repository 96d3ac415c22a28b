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
from membranes.equilibration import FluxEquilibration, Geometry, lifting
from membranes.newton_system import linear_rows, split
from membranes.problem import as_builder

from .conftest import solved, solved_on

RNG = np.random.default_rng(1)


@pytest.fixture(scope="module", params=[("disk", 0.1, 0), ("square", 0.1, 0), ("disk", 0.3, 3)],
                ids=["disk", "square", "disk-refined"])
def setup(request):
    name, h, levels = request.param
    run = solved(name, h) if levels == 0 else solved_on(name, h, levels, estimators=False)
    return run, FluxEquilibration(run.disc)


def _iterate(run, which):
    """(X, R): the converged iterate, the first GMRES iterate X^{1,1} of the first Newton step (its true
    residual R = B - A X), or an arbitrary perturbation X with R = F - E X."""
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


def test_operators_are_linear_in_the_data(setup):
    """σ(u, λ, R) = μ G_u u ± G_λ λ + G_R R + σ_f: the set-up is linear, so σ of a sum of
    iterates minus σ_f twice equals the sum of the σ's minus σ_f, to round-off."""
    run, eq = setup
    n = run.disc.n
    a, b = (RNG.standard_normal(n) for _ in range(2))
    lam, R = RNG.standard_normal(n), RNG.standard_normal(n)
    s_ab = eq.sigma(1, a + b, 2 * lam, 2 * R)
    s_a, s_b = eq.sigma(1, a, lam, R), eq.sigma(1, b, lam, R)
    assert np.allclose(s_ab - eq.sigma_f[0], s_a + s_b - 2 * eq.sigma_f[0],
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
