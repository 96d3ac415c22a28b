"""The algebraic fluxes of DESIGN §6.

* Multilevel: ∇·σ_α,alg = r_αh on every cell of T_J to round-off, and σ_alg ∈ H(div).
* ν extra iterations: σ_alg = σ_disc(X^{k,i+ν}) - σ_disc(X^{k,i}), whose divergence is
  r - r' ± (λ'_h - λ_h) (DESIGN §6 writes r - r'; the λ shift between the two iterates is
  there too and goes to the remainder, see Estimators.nu_flux).
* The RT_1 prolongation T_{j-1} → T_j (reference blocks per kind of child, signs of the edge
  reflections) is dolfinx's interpolation of the coarse basis functions, to round-off.
* Owner computes: σ_alg set up on two complementary ownerships of the patches sums to σ_alg.
* The classes' scatter (`_apply_buckets`) adds the same terms in the same order as the sparse
  matrix of the change of basis and scatter: equal to the bit.
* Sharpness of the multilevel η_alg = (Σ_α μ_α^{-1} ‖σ_α,alg‖²)^{1/2} against the true
  algebraic error |||u_h^{k,exact} - u_h^{k,i}||| (the same Newton system solved by MUMPS) at
  GMRES iterates of the disk scene: between 1 and 3 (measured figures are printed).
"""

import functools
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
import ufl

from membranes import newton_system as ns
from membranes.algebraic_flux import MultilevelFlux
from membranes.discretisation import assemble_vector_array, discretise
from membranes.estimators import Estimators
from membranes.krylov import Krylov
from membranes.linear_solve import solve_direct
from membranes.newton import semismooth_newton

from .conftest import scene


@functools.lru_cache(maxsize=None)
def setup(name, h, levels):
    problem = scene(name, h, levels=levels)
    disc = discretise(problem)
    return problem, disc, ns.linear_rows(disc), Estimators(disc), \
        MultilevelFlux(disc, problem.hierarchy)


def krylov_iterates(rows, g, steps=3, nu=5):
    """(k, X^{k,i}, R^{k,i}, ‖R‖/‖B‖, X^{k-1}) at every ν-th GMRES iterate of `steps` exact
    Newton steps."""
    seen, last = [], {}

    def monitor(rec, X, R):
        if rec["kind"] == "krylov":
            seen.append((rec["newton_it"], X.copy(), R.copy(), rec["alg_residual"],
                         last["X"]))
        else:
            last["X"] = X.copy()
    semismooth_newton(rows, g, variant="exact", krylov=Krylov(nu=nu), max_it=steps,
                      monitor=monitor)
    return seen


def _divergence_defect(disc, est, sigma, r_cells, scale_cells=None):
    """max |(∇·σ - r, q)_K| / max (s, q)_K over the DG1 basis q of every cell, s = |r| or the
    data scale given by `scale_cells` (≥ 0, DG1 coefficients per cell)."""
    from dolfinx import fem
    space = est.flux.space
    q = ufl.TestFunction(space.DG)
    s = fem.Function(space.RT)
    s.x.array[:] = sigma
    r = fem.Function(space.DG)
    r.x.array[space.dg_cells.ravel()] = r_cells.ravel()
    defect = assemble_vector_array((ufl.div(s) - r) * q * ufl.dx)
    if scale_cells is not None:
        r = fem.Function(space.DG)
        r.x.array[space.dg_cells.ravel()] = scale_cells.ravel()
    scale = assemble_vector_array(abs(r) * q * ufl.dx)   # DG1 basis functions are ≥ 0
    mesh = disc.problem.mesh
    n = ufl.FacetNormal(mesh)
    jump = fem.assemble_scalar(fem.form(ufl.jump(s, n) ** 2 * ufl.dS))
    size = fem.assemble_scalar(fem.form(ufl.inner(s, s) * ufl.dx))
    return np.abs(defect).max() / np.abs(scale).max(), jump / size


@pytest.mark.parametrize("name,h,levels", [("disk", 0.3, 2), ("square", 0.25, 3)])
def test_multilevel_divergence_is_the_lifted_residual(name, h, levels):
    problem, disc, rows, est, ml = setup(name, h, levels)
    assert np.array_equal(ml.RT.dofmap.list.array, est.flux.RT.dofmap.list.array)
    _, X, R, alg, _ = krylov_iterates(rows, problem.g, steps=1, nu=2)[0]
    assert alg > 1e-6
    n = disc.n
    for sigma, Ra in zip(ml.sigma(R), (R[:n], R[n:2 * n])):
        r = (ml.lift @ Ra).reshape(-1, 3)
        defect, jump = _divergence_defect(disc, est, sigma, r)
        assert defect <= 1e-11 and jump <= 1e-24


@pytest.mark.parametrize("pair", ["early", "late"])
def test_nu_flux_divergence(pair):
    """σ_alg is a difference of two O(1) fluxes: round-off is relative to their data (λ_h,
    r_h of both iterates), not to the small difference."""
    problem, disc, rows, est, _ = setup("disk", 0.3, 2)
    its = krylov_iterates(rows, problem.g, steps=2, nu=3)
    (k1, X, R, _, _), (k2, X2, R2, _, _) = its[:2] if pair == "early" else its[-2:]
    assert k1 == k2
    sigma_alg, eta_rem = est.nu_flux(X, R, X2, R2)
    n = disc.n
    lam, lam2 = X[2 * n:][est.geo.cells], X2[2 * n:][est.geo.cells]
    for alpha, (sigma, Ra, Rb) in enumerate(zip(sigma_alg, (R[:n], R[n:2 * n]),
                                                 (R2[:n], R2[n:2 * n]))):
        sign = 1.0 if alpha == 0 else -1.0
        r, r2 = ((est.flux.lift @ v).reshape(-1, 3) for v in (Ra, Rb))
        target = r - r2 + sign * (lam2 - lam)
        scale = np.abs(lam) + np.abs(lam2) + np.abs(r) + np.abs(r2)
        defect, jump = _divergence_defect(disc, est, sigma, target, scale)
        assert defect <= 1e-11 and jump <= 1e-24
    assert eta_rem > 0


def interpolated_prolongation(coarse, fine, parent):
    """Reference: the matrix of RT_1(T_{j-1}) → RT_1(T_j) by dolfinx's interpolation of sums of
    coarse basis functions, one sum per colour of coarse dofs that share no cell (a fine dof
    then sees at most one basis function of the colour: a coarse dof of its parent cell)."""
    import scipy.sparse as sp
    from dolfinx import fem
    from membranes.equilibration import graph_colouring
    iu = np.triu_indices(8, 1)
    pairs = np.unique(np.stack([coarse.rt_cells[:, iu[0]].ravel(),
                                coarse.rt_cells[:, iu[1]].ravel()], axis=1), axis=0)
    colour = graph_colouring(pairs, coarse.nrt)
    fc, ff = fem.Function(coarse.RT), fem.Function(fine.RT)

    def values(x):   # the interpolation points come cell by cell, for all cells of T_j
        cells = np.repeat(parent, x.shape[1] // len(parent)).astype(np.int32)
        return fc.eval(np.ascontiguousarray(x.T), cells).T

    rows, cols, vals = [], [], []
    for c in range(colour.max() + 1):
        fc.x.array[:] = (colour == c)
        ff.interpolate(values)
        source = np.where(colour[coarse.rt_cells[parent]] == c,
                          coarse.rt_cells[parent], -1).max(axis=1)            # (nc_j,)
        f_dofs = fine.rt_cells.ravel()
        src = np.repeat(source, fine.rt_cells.shape[1])
        ok = src >= 0
        rows.append(f_dofs[ok])
        cols.append(src[ok])
        vals.append(ff.x.array[f_dofs][ok])
    rows, cols, vals = (np.concatenate(z) for z in (rows, cols, vals))
    key = np.unique(rows.astype(np.int64) * coarse.nrt + cols, return_index=True)[1]
    return sp.csr_matrix((vals[key], (rows[key], cols[key])), shape=(fine.nrt, coarse.nrt))


@pytest.mark.parametrize("name,h,levels", [("disk", 0.3, 2), ("square", 0.25, 3)])
def test_prolongation_is_the_interpolation(name, h, levels):
    """On random coarse coefficients (a difference of the two operators would show): the
    entries are O(1) (moments of basis functions of comparable cells) and each fine dof sums
    at most 8 of them, so 1e-12 of max |X| · max row sum |P| is round-off."""
    from membranes.algebraic_flux import Prolongation
    from membranes.equilibration import PatchSpace
    from dolfinx import fem
    problem, disc, rows, est, ml = setup(name, h, levels)
    H = problem.hierarchy
    spaces = [PatchSpace(fem.FunctionSpace(m, ("Lagrange", 1)), blocks=False)
              for m in H.meshes]
    rng = np.random.default_rng(0)
    for j in range(2, levels + 1):
        ref = interpolated_prolongation(spaces[j - 1], spaces[j], H.parent_cells[j - 1])
        scale = abs(ref).sum(axis=1).max()
        assert 0.5 < abs(ref).max() and scale < 10
        X = rng.standard_normal((spaces[j - 1].nrt, 8))
        P = Prolongation(spaces[j - 1], spaces[j], H.parent_cells[j - 1], ml.Bp2[j])
        for op in (P, ml.prolong[j]):
            assert np.abs(op @ X - ref @ X).max() <= 1e-12 * np.abs(X).max() * scale
        assert np.abs(ml.prolong[j] @ X[:, 0] - ref @ X[:, 0]).max() \
            <= 1e-12 * np.abs(X).max() * scale


@pytest.mark.parametrize("name,h,levels", [("disk", 0.3, 2), ("square", 0.25, 3)])
def test_complementary_ownerships_sum_to_the_flux(name, h, levels):
    """Each patch is set up and evaluated by its owner only; the classes' representatives
    then differ between the runs, so the sum agrees to round-off (relative 1e-12: the
    operators are solutions of the same O(1)-conditioned patch problems)."""
    problem, disc, rows, est, ml = setup(name, h, levels)
    rng = np.random.default_rng(3)
    owned = [rng.random(len(m.geometry.x)) < 0.5 for m in problem.hierarchy.meshes[:-1]]
    parts = [MultilevelFlux(disc, problem.hierarchy, owned=own)
             for own in (owned, [~o for o in owned])]
    R = rng.standard_normal(3 * disc.n)
    for k in range(2):
        R[k * disc.n + disc.boundary] = 0.0
    full, half, other = ml.sigma(R), parts[0].sigma(R), parts[1].sigma(R)
    for f, a, b in zip(full, half, other):
        assert min(np.abs(a).max(), np.abs(b).max()) > 0.1 * np.abs(f).max()
        print("owner computes: relative difference", np.abs(a + b - f).max() / np.abs(f).max())
        assert np.abs(a + b - f).max() <= 1e-12 * np.abs(f).max()


def test_sharpness_of_the_multilevel_estimate():
    """At GMRES iterates whose residual is well above the reference's round-off."""
    problem, disc, rows, est, ml = setup("disk", 0.2, 3)
    n = disc.n
    energy = [lambda e: np.sqrt(e @ (disc.S1 @ e)), lambda e: np.sqrt(e @ (disc.S2 @ e))]
    ratios, nu_ratios = [], []
    its = krylov_iterates(rows, problem.g, steps=3, nu=10)
    for (k, X, R, alg, X_prev), later in zip(its, its[1:] + [None]):
        if alg < 1e-9:
            continue
        alpha, beta, B3 = ns.complementarity_rows(rows, "min", X_prev)
        A, B = ns.full_system(rows, alpha, beta, B3)
        exact, _ = solve_direct(A, B)
        e = exact - X
        true = np.sqrt(energy[0](e[:n]) ** 2 + energy[1](e[n:2 * n]) ** 2)
        eta_alg = est.evaluate(X, R, alg, sigma_alg=ml.sigma(R))["eta_alg"]
        ratios.append(eta_alg / true)
        if later is not None and later[0] == k:
            sigma_nu, rem = est.nu_flux(X, R, later[1], later[2])
            nu_ratios.append(est.evaluate(X, R, alg, sigma_alg=sigma_nu,
                                          eta_rem=rem)["eta_alg"] / true)
    print("multilevel eta_alg / algebraic error:", np.round(ratios, 2))
    print("nu-extra-iterations eta_alg / algebraic error:", np.round(nu_ratios, 2))
    assert len(ratios) >= 10
    assert 1.0 <= min(ratios) and max(ratios) <= 3.0


def test_bucket_scatter_sums_in_column_order():
    """`_apply_buckets` (gather, products, then the compiled change of basis and scatter) on
    random buckets with shared RT dofs, second terms (another representative dof, as the two
    dofs of an entity) on either side of the first and a class
    split across the blocks of `_ROWS` patches, against the sparse matrix of the change of
    basis and scatter (one entry C[p, i, t] at (RET, position of the term), summed by scipy in
    column order) times the concatenated products: equal to the bit, since both add the same
    terms (the products times 0, ±1, exact) to each RT dof in the same order; so is the
    pipeline of a pool's thread (products) and this one (scatters)."""
    import scipy.sparse as sp

    from membranes import algebraic_flux

    rng = np.random.default_rng(3)
    size, nflat = 50, 40
    buckets, ret, rows, cols, data, first = [], [], [], [], [], 0
    for g, per, nr, nq in ((3, 5, 4, 3), (2, 40, 6, 5), (1, 7, 2, 2)):
        P = g * per
        S = rng.standard_normal((g, nr, nq))
        G = rng.integers(0, nflat, (P, nq)).astype(np.int32)
        L = rng.integers(0, nr, (P, nr, 2))
        L[:, :, 1] = (L[:, :, 0] + rng.integers(1, nr, (P, nr))) % nr   # another dof
        L = L.astype(np.uint8)
        C = rng.integers(-1, 2, (P, nr, 2)).astype(np.int8)
        R = np.stack([rng.permutation(size)[:nr] for _ in range(P)]).astype(np.int32)
        buckets.append((S, G, L, C))
        ret.append(R.ravel())
        at = first + np.arange(P)[:, None] * nr                              # (P, 1)
        for t in range(2):
            keep = (C[:, :, t] != 0) if t else np.ones((P, nr), dtype=bool)
            rows.append(R[keep])
            cols.append(np.broadcast_to(at, (P, nr))[keep] + L[:, :, t][keep])
            data.append(C[:, :, t][keep].astype(float))
        first += P * nr
    flat = rng.standard_normal(nflat)
    level = (buckets, ret)
    M = sp.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(size, first))
    products = np.concatenate([np.matmul(flat[G].reshape(S.shape[0], -1, S.shape[2]),
                                         S.transpose(0, 2, 1)).ravel()
                               for S, G, _, _ in buckets])
    old = algebraic_flux._ROWS
    pool = ThreadPoolExecutor(1)
    try:
        for rows_per_block in (old, 16):
            algebraic_flux._ROWS = rows_per_block
            got = algebraic_flux._apply_buckets(level, flat, size)
            assert np.array_equal(got, M @ products)
            # with a thread to spare: products one chunk ahead of the scatters, same bits
            got = algebraic_flux._apply_buckets(level, flat, size, pool=pool)
            assert np.array_equal(got, M @ products)
    finally:
        algebraic_flux._ROWS = old
        pool.shutdown()
