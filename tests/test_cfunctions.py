"""C-functions (DESIGN §3), min against Fischer–Burmeister, and complementarity at round-off."""

import numpy as np
import pytest

from membranes import cfunctions
from membranes.newton_system import split

from membranes import solve

from .conftest import scene, solved, solved_with

RNG = np.random.default_rng(0)


@pytest.mark.parametrize("name", ["min", "fb"])
def test_zero_set_is_complementarity(name):
    C, _ = cfunctions.get(name)
    a = np.concatenate([RNG.uniform(0.1, 1, 50), np.zeros(50), RNG.uniform(-1, -0.1, 50),
                        RNG.uniform(0.1, 1, 50)])
    b = np.concatenate([np.zeros(50), RNG.uniform(0.1, 1, 50), RNG.uniform(0.1, 1, 50),
                        RNG.uniform(0.1, 1, 50)])
    value = C(a, b)
    complementary = (a >= 0) & (b >= 0) & (a * b == 0)
    assert np.all(value[complementary] == 0)
    assert np.all(np.abs(value[~complementary]) > 1e-3)


@pytest.mark.parametrize("name", ["min", "fb"])
def test_jacobian_is_derivative_where_smooth(name):
    C, J = cfunctions.get(name)
    a, b = RNG.uniform(-1, 1, 200), RNG.uniform(-1, 1, 200)
    keep = np.abs(a - b) > 1e-3          # away from the kink of min
    a, b = a[keep], b[keep]
    alpha, beta = J(a, b)
    eps = 1e-7   # central differences: error O(eps²) plus round-off O(1e-16/eps) ≈ 1e-9
    assert np.allclose(alpha, (C(a + eps, b) - C(a - eps, b)) / (2 * eps), atol=1e-6)
    assert np.allclose(beta, (C(a, b + eps) - C(a, b - eps)) / (2 * eps), atol=1e-6)


def test_fb_kink_choice_is_in_clarke_jacobian():
    alpha, beta = cfunctions.jacobian_fb(np.zeros(1), np.zeros(1))
    xi, zeta = alpha[0] + 1, beta[0] + 1
    assert xi ** 2 + zeta ** 2 <= 1 + 1e-15
    alpha_, beta_, B3 = cfunctions.linearise("fb", np.zeros(1), np.zeros(1))
    assert B3[0] == 0.0


def test_min_linearisation_has_no_constant_term():
    a, b = RNG.uniform(-1, 1, 100), RNG.uniform(-1, 1, 100)
    _, _, B3 = cfunctions.linearise("min", a, b)
    assert np.all(B3 == 0)   # min is piecewise linear: the primal–dual active set method


@pytest.mark.parametrize("name", ["disk", "square"])
def test_min_and_fb_give_the_same_discrete_solution(name):
    a, b = solved(name, 0.05, "min"), solved(name, 0.05, "fb")
    assert a.converged and b.converged
    n = a.disc.n
    for xa, xb in zip(split(a.X, n), split(b.X, n)):
        assert np.abs(xa - xb).max() <= 1e-8 * np.abs(xa).max()


def _complementarity(run, bound):
    d = run.disc
    u1, u2, lam = split(run.X, d.n)
    w = (u1 - u2)[d.interior]
    lam = lam[d.interior]
    u_scale, lam_scale = d.problem.g, np.abs(lam).max()
    assert w.min() >= -bound * u_scale
    assert lam.min() >= -bound * lam_scale
    assert np.abs(w * lam).max() <= bound * u_scale * lam_scale
    assert run.complementarity_violation() <= bound


@pytest.mark.parametrize("name", ["disk", "square"])
def test_min_complementarity_at_round_off(name):
    """min is piecewise linear: at convergence the active set is exact, the rest round-off
    (of exact linear solves: MUMPS; GMRES leaves its own tolerance, 2e-12, in R3)."""
    _complementarity(solved_with(name, 0.05, cfun="min", linear_solver="direct"), 1e-12)


@pytest.mark.parametrize("name", ["disk", "square"])
def test_fb_complementarity(name):
    """Fischer–Burmeister is smooth off the kink: at the stop its complementarity error is
    bounded by the Newton tolerance (|C| ≤ tol ‖F‖, and |C(w, λ)| ≈ |λ| where w ≫ |λ|), so
    ≤ 1e-10 at tol = 1e-10; one more (superlinear) step, tol = 1e-13, reaches round-off."""
    _complementarity(solved(name, 0.05, "fb"), 1e-10)
    _complementarity(solve(scene(name, 0.05), cfun="fb", tol=1e-13), 1e-12)


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_full_and_eliminated_systems_agree(cfun):
    """The same Newton iterates, to round-off of exact (MUMPS) solves."""
    full, elim = (solved_with("square", 0.1, cfun=cfun, system=system, linear_solver="direct")
                  for system in ("full", "eliminated"))
    assert full.newton_iterations == elim.newton_iterations
    assert np.abs(full.X - elim.X).max() <= 1e-10 * np.abs(full.X).max()
    for rf, re in zip(full.history, elim.history):
        assert abs(rf["residual"] - re["residual"]) <= 1e-8 * max(rf["residual"], 1e-6)


def _same_csr(A, B):
    """Whether A and B hold the same row pointers, columns and entries, bit for bit (a plain
    function: pytest's rewritten asserts would keep references to A's arrays)."""
    return bool(A.has_sorted_indices and np.array_equal(A.indptr, B.indptr) and
                np.array_equal(A.indices, B.indices) and np.array_equal(A.data, B.data))


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_eliminated_system_is_the_product_to_the_bit(cfun):
    """newton_system.eliminated_system writes Ã = (W E) T row by row into arrays it keeps
    from one call to the next (membranes.kept): the entries, columns and row pointers of
    scipy's product with T formed, at every call of a sequence; the same system made again
    once the first is let go is written into the same arrays, and a system its caller still
    holds is not written over."""
    import scipy.sparse as sp
    from membranes import discretisation, newton_system as ns
    rows = ns.linear_rows(discretisation.discretise(scene("disk", 0.1)))
    n = rows.n
    for k in range(5):
        X = RNG.normal(size=3 * n)
        X[2 * n:] *= RNG.uniform(size=n) < 0.5          # about half the vertices without λ
        alpha, beta, B3 = ns.complementarity_rows(rows, cfun, X)
        U, H, G, Q = ns.eliminate(n, alpha, beta, B3, rows.kappa).coefficients
        T = sp.bmat([[sp.identity(n), None], [sp.diags(U), sp.diags(H)],
                     [sp.diags(G), sp.diags(Q)]], format="csr")
        P = (rows.weighted_E @ T).tocsr()
        P.eliminate_zeros()
        P.sort_indices()
        A = ns.eliminated_system(rows, alpha, beta, B3, weighted=True)[0]
        same, address = _same_csr(A, P), A.data.ctypes.data
        if k == 1:
            held = (A, A.copy())                        # a system kept by its caller
        del A
        again = ns.eliminated_system(rows, alpha, beta, B3, weighted=True)[0]
        reused = again.data.ctypes.data == address
        same_again = _same_csr(again, P)
        del again
        assert same and same_again
        assert reused == (k != 1)
    assert _same_csr(*held)                             # not written over


# ## Fischer–Burmeister at the projection (newton: active-set steps)

def test_projection_is_the_nearest_point_of_the_complementarity_set():
    """The set is the two half-axes {a ≥ 0, b = 0} ∪ {a = 0, b ≥ 0}: compare with the nearest
    point on each (exact arithmetic: maxima and zeros only)."""
    a, b = RNG.uniform(-1, 1, 400), RNG.uniform(-1, 1, 400)
    a[:20], b[:20] = 0.0, 0.0                        # the kink
    a[20:40] = b[20:40]                              # ties: min's rule picks contact
    p, q = cfunctions.project(a, b)
    assert np.all((p >= 0) & (q >= 0) & (p * q == 0))
    assert np.all(cfunctions.c_fb(p, q) == 0)
    to_a_axis = (a - np.maximum(a, 0)) ** 2 + b ** 2
    to_b_axis = a ** 2 + (b - np.maximum(b, 0)) ** 2
    assert np.allclose((a - p) ** 2 + (b - q) ** 2, np.minimum(to_a_axis, to_b_axis),
                       rtol=0, atol=1e-15)
    contact = a <= b
    assert np.all(p[contact] == 0) and np.all(q[~contact] == 0)


def test_jacobian_at_projection_is_the_gradient_there():
    """Off the origin FB is differentiable at the projection (p, q) and the row is its gradient
    there; at the origin the row is (ξ - 1, ζ - 1) with ξ² + ζ² = 1, in the Clarke Jacobian
    (DESIGN §3). The linearisation at the projection has B3 = 0 and is min's row up to sign
    (the primal–dual active set step)."""
    a, b = RNG.uniform(-1, 1, 400), RNG.uniform(-1, 1, 400)
    alpha, beta = cfunctions.jacobian_fb_at_projection(a, b)
    p, q = cfunctions.project(a, b)
    off = np.hypot(p, q) > 1e-3
    ga, gb = cfunctions.jacobian_fb(p[off], q[off])
    assert np.array_equal(alpha[off], ga) and np.array_equal(beta[off], gb)
    assert np.all((alpha + 1) ** 2 + (beta + 1) ** 2 == 1)
    kappa = 0.3
    al, be, B3 = cfunctions.linearise("fb", a, b, kappa, at_projection=True)
    assert np.all(B3 == 0)
    am, bm, _ = cfunctions.linearise("min", a, b, kappa)
    assert np.array_equal(al, -am) and np.array_equal(be, -bm)
    with pytest.raises(ValueError, match="Fischer"):
        cfunctions.linearise("min", a, b, at_projection=True)
