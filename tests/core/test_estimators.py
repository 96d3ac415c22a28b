"""The estimators of §7 (and the remainder of §6, the energy error) against an independent
computation: numpy quadrature cell by cell (a collapsed Gauss–Legendre rule exact to degree
14, the P1 basis by barycentric coordinates, the RT_1 fields and the data by their formulas),
on the scene of `tests/core/mpi_estimators.py`, whose integrands are all polynomials (cubic
loads, RT_1 fields, P1 and DG1 functions, a quadratic exact solution) so that both sides are
exact up to round-off: tolerance 1e-11 relative to the largest value of each quantity.
"""

import json
import os

import numpy as np
import pytest
import ufl
from mpi4py import MPI

from membranes.estimation import estimators as est_module
from membranes.estimation.energy_error import EnergyError
from membranes.estimation.estimators import Estimators
from tests.conftest import mpirun
from tests.core.mpi_estimators import MU1, MU2, NP, iterate, residual, scene

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
TOL = 1e-11


def collapsed_rule(n=8):
    """Points and weights on the reference triangle (0,0), (1,0), (0,1) from an n × n
    Gauss–Legendre rule on the square through the Duffy map (ξ, η) = (a, b (1 - a)): exact for
    polynomials of degree ≤ 2n - 2."""
    g, w = np.polynomial.legendre.leggauss(n)
    g, w = (g + 1) / 2, w / 2
    a, b = np.meshgrid(g, g, indexing="ij")
    wa, wb = np.meshgrid(w, w, indexing="ij")
    return np.stack([a.ravel(), (b * (1 - a)).ravel()], axis=1), (wa * wb * (1 - a)).ravel()


PTS, WTS = collapsed_rule()
PHI = np.stack([1 - PTS[:, 0] - PTS[:, 1], PTS[:, 0], PTS[:, 1]], axis=1)   # (q, 3)
DPHI = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])


def reference(disc, X, sigma_f, alg_f, f_np, r_f=None, dlam=None, exact=None, nodal=NP):
    """Every per-cell quantity by numpy quadrature on the owned cells (mesh order); X's u1,
    u2, λ are the formulas nodal["u1"], nodal["u2"], nodal["lam"] (default: the scene's)."""
    V, n = disc.V, disc.n
    coords = V.tabulate_dof_coordinates()[:, :2]
    ghosts = V.dofmap.index_map.num_ghosts
    # nodal values on owned and ghost dofs from the formulas (not from a scatter)
    vals = {k: nodal[k](coords.T) for k in ("u1", "u2", "lam")}
    assert np.array_equal(np.concatenate([vals[k][:n] for k in ("u1", "u2", "lam")]), X)
    u1, u2, lam = vals["u1"], vals["u2"], vals["lam"]
    lp, ln = np.maximum(lam, 0), np.minimum(lam, 0)
    half = np.where(u1 < u2, 0.5 * (u2 - u1), 0.0)
    assert len(u1) == n + ghosts
    ncells = disc.mesh.topology.index_map(2).size_local
    mu = (MU1, MU2)
    out = {k: np.zeros(ncells) for k in ("disc1", "disc2", "F1", "F2", "alg1", "alg2", "osc1",
                                         "osc2", "C", "lin1", "lp", "ln", "rem", "energy")}
    M_ref = np.einsum("q,qi,qj->ij", WTS, PHI, PHI)
    for c in range(ncells):
        d = V.dofmap.cell_dofs(c)
        v = coords[d]
        J = np.column_stack([v[1] - v[0], v[2] - v[0]])
        det = abs(np.linalg.det(J))
        grads = DPHI @ np.linalg.inv(J)                      # (3, 2): ∇φ_i
        x = (v[0][:, None] + J @ PTS.T)                      # (2, q)
        w = WTS * det
        h = max(np.linalg.norm(v[i] - v[j]) for i, j in ((0, 1), (1, 2), (2, 0)))

        def p1(values):
            return PHI @ values[d]

        def grad(values):
            return values[d] @ grads
        for a, (u, sig, alg, f) in enumerate(zip((u1, u2), sigma_f, alg_f, f_np)):
            s = np.array(sig(x))
            al = np.array(alg(x))
            gu = grad(u)[:, None]
            out[f"disc{a + 1}"][c] = w @ ((np.sqrt(mu[a]) * gu + s / np.sqrt(mu[a])) ** 2).sum(0)
            out[f"F{a + 1}"][c] = w @ ((np.sqrt(mu[a]) * gu + (s + al) / np.sqrt(mu[a])) ** 2
                                       ).sum(0)
            out[f"alg{a + 1}"][c] = w @ (al ** 2).sum(0) / mu[a]
            fx = f(x)
            coef = np.linalg.solve(M_ref * det, (w * fx) @ PHI)
            out[f"osc{a + 1}"][c] = (h / np.pi) ** 2 / mu[a] * (w @ (fx - PHI @ coef) ** 2)
        out["C"][c] = 2 * w @ ((p1(u1) - p1(u2)) * p1(lp))
        e1, e2 = grad(half), grad(-half)
        out["lin1"][c] = det / 2 * (MU1 * e1 @ e1 + MU2 * e2 @ e2)
        out["lp"][c] = w @ p1(lp) ** 2
        out["ln"][c] = w @ p1(ln) ** 2
        if r_f is not None:
            dl = np.zeros(n + ghosts)
            dl[:] = NP["dlam"](coords.T)
            # r_α: the DG1 interpolant of its formula (the vertex values of the cell)
            r1, r2 = (PHI @ rf(v.T) for rf in r_f)
            out["rem"][c] = w @ (r1 - p1(dl)) ** 2 / MU1 + w @ (r2 + p1(dl)) ** 2 / MU2
        if exact is not None:
            g1, g2 = (np.array(gx(x)) for gx in exact)
            out["energy"][c] = (MU1 * w @ ((g1 - grad(u1)[:, None]) ** 2).sum(0)
                                + MU2 * w @ ((g2 - grad(u2)[:, None]) ** 2).sum(0))
    return out


EXACT_GRADS = (lambda x: (2 * x[0] + x[1], x[0]), lambda x: (-np.ones_like(x[0]), 2 * x[1]))


@pytest.fixture(scope="module")
def setup():
    disc, X, sigma, alg, r, dlam = scene(MPI.COMM_WORLD, 5)
    ref = reference(disc, X, (NP["sigma1"], NP["sigma2"]), (NP["alg1"], NP["alg2"]),
                    (NP["f1"], NP["f2"]), (NP["r1"], NP["r2"]), dlam, EXACT_GRADS)
    return disc, X, sigma, alg, r, dlam, ref


def close(a, b, tol=TOL):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    scale = max(np.abs(b).max(initial=0.0), 1e-300)
    return np.abs(a - b).max(initial=0.0) <= tol * scale


CPF = 1 / (np.pi * np.sqrt(2))                  # C_PF h_Ω of the unit square (§7)
C_LAMBDA = CPF * np.sqrt(1 / MU1 + 1 / MU2)


def linearisation_reference(ref):
    """η_lin1, η_lin2, η_lin3 of §7 from the independent per-cell values."""
    lin1 = np.sqrt(ref["lin1"].sum())
    return (lin1, 2 * C_LAMBDA * np.sqrt(ref["lp"].sum()) * lin1,
            C_LAMBDA * np.sqrt(ref["ln"].sum()))


def per_cell(est, X, sigma, alg):
    """The per-cell integrals the estimators assemble, by name."""
    est.assemble(X, sigma, alg)
    q = est.cells_alg.cells()
    E = est_module
    return {"disc1": q[:, E.DISC1], "disc2": q[:, E.DISC2], "F1": q[:, E.FLUX1],
            "F2": q[:, E.FLUX2], "alg1": q[:, E.ALG1], "alg2": q[:, E.ALG2],
            "osc1": est.osc[:, 0] ** 2, "osc2": est.osc[:, 1] ** 2, "C": q[:, E.CONTACT],
            "lin1": q[:, E.LIN1], "lp": q[:, E.LAM_POS], "ln": q[:, E.LAM_NEG]}


def test_per_cell_against_numpy_quadrature(setup):
    """Each per-cell quantity of §7 equals the numpy quadrature on every cell."""
    disc, X, sigma, alg, r, dlam, ref = setup
    got = per_cell(Estimators(disc), X, sigma, alg)
    for key, value in got.items():
        assert close(value, ref[key]), key
    # the scene is not degenerate: every quantity is present on some cell
    for key in got:
        assert np.abs(ref[key]).max() > 1e-12, key


def test_oscillation_from_the_equilibration_loads(setup):
    """With the flux equilibration, η_osc takes the loads (f_α, q)_K of Π_P1 f_α from the
    equilibration's data assembly (the slots' blocks summed) instead of its own: the same
    numpy quadrature values on every cell."""
    from membranes.estimation.equilibration import FluxEquilibration
    disc, *_, ref = setup
    eq = FluxEquilibration(disc.V, disc.dx_data)
    _, moments = eq.loads((disc.f1, disc.f2), moments=True)
    assert moments.shape == (disc.mesh.topology.index_map(2).size_local, 3, 2)
    est = Estimators(disc, eq)
    assert close(est.osc[:, 0] ** 2, ref["osc1"]) and close(est.osc[:, 1] ** 2, ref["osc2"])


def test_global_values_and_bound(setup):
    """The global values and η_K from the independent per-cell values by §7's formulas, with
    the remainder of §6 against its own quadrature."""
    disc, X, sigma, alg, r, dlam, ref = setup
    est = Estimators(disc)
    eta_rem = est.remainder(r, dlam)
    assert np.isclose(eta_rem, CPF * np.sqrt(ref["rem"].sum()), rtol=TOL, atol=0)
    got = est.assemble(X, sigma, alg, eta_rem)
    osc = np.sqrt(np.stack([ref["osc1"], ref["osc2"]], 1))
    F = np.sqrt(np.stack([ref["F1"], ref["F2"]], 1))
    D = np.sqrt(np.stack([ref["disc1"], ref["disc2"]], 1))
    eta_1 = np.sqrt(((F + osc) ** 2).sum())
    lin1, lin2, lin3 = linearisation_reference(ref)
    sum_C = ref["C"].sum()
    expect = {
        "eta": np.sqrt((eta_1 + eta_rem + lin1 + lin3) ** 2 + lin2 + max(0, sum_C)),
        "eta_disc": np.sqrt(((D + osc) ** 2).sum()) + np.sqrt(abs(sum_C)),
        "eta_lin": lin1 + lin3 + np.sqrt(lin2),
        "eta_alg": np.sqrt((ref["alg1"] + ref["alg2"]).sum()) + eta_rem,
        "eta_F": np.sqrt((F ** 2).sum()), "eta_osc": np.sqrt((osc ** 2).sum()),
        "eta_C": sum_C, "eta_lin1": lin1, "eta_lin2": lin2, "eta_lin3": lin3,
        "eta_rem": eta_rem, "eta_1": eta_1}
    for key, value in expect.items():
        assert np.isclose(got[key], value, rtol=TOL, atol=0), key
    eta_K = np.sqrt(((F + osc) ** 2).sum(1) + ref["lin1"] + C_LAMBDA ** 2 * ref["ln"]
                    + np.abs(ref["C"]))
    assert close(got["eta_K"], eta_K)
    # the components bound η (Corollary 5.6 of the paper, §7)
    assert got["eta"] <= got["eta_disc"] + got["eta_lin"] + got["eta_alg"]
    # without σ_alg: η_F is η_disc's flux part, no algebraic part
    plain = est.assemble(X, sigma)
    assert np.isclose(plain["eta_F"], np.sqrt((D ** 2).sum()), rtol=TOL, atol=0)
    assert plain["eta_alg"] == 0.0 and plain["eta_rem"] == 0.0


def test_a_negative_contact_sum_enters_eta_and_eta_disc_as_section_7_says(setup):
    """An iterate with λh > 0 where u1h < u2h (the scene's iterate with the membranes
    swapped): Σ_C = 2 Σ_K (u1h - u2h, λ^pos)_K < 0. §7 adds max(0, Σ_C) = 0 to η² and
    |Σ_C|^{1/2} to η_disc; the scene's own iterate has Σ_C > 0, where max(0, Σ_C), |Σ_C| and
    Σ_C agree, so only an iterate like this one tells them apart. Against the numpy
    quadrature of that iterate, to round-off as above; |Σ_C| ≥ 1e-6 η² (here 1e-3), so
    adding |Σ_C| to η² would move η by ≥ 5e-7 relative, far beyond that tolerance."""
    disc, X, sigma, alg, r, dlam, _ = setup
    n = disc.n
    swapped = {"u1": NP["u2"], "u2": NP["u1"], "lam": NP["lam"]}
    Xs = np.concatenate([X[n:2 * n], X[:n], X[2 * n:]])
    ref = reference(disc, Xs, (NP["sigma1"], NP["sigma2"]), (NP["alg1"], NP["alg2"]),
                    (NP["f1"], NP["f2"]), nodal=swapped)
    sum_C = disc.comm.allreduce(float(ref["C"].sum()), op=MPI.SUM)
    assert sum_C < 0
    got = Estimators(disc).assemble(Xs, sigma)
    osc = np.sqrt(np.stack([ref["osc1"], ref["osc2"]], 1))
    D = np.sqrt(np.stack([ref["disc1"], ref["disc2"]], 1))
    eta_1 = np.sqrt(((D + osc) ** 2).sum())
    lin1, lin2, lin3 = linearisation_reference(ref)
    assert lin1 > 0 and abs(sum_C) > 1e-6 * ((eta_1 + lin1 + lin3) ** 2 + lin2)
    assert np.isclose(got["eta_C"], sum_C, rtol=TOL, atol=0)
    assert np.isclose(got["eta"], np.sqrt((eta_1 + lin1 + lin3) ** 2 + lin2), rtol=TOL, atol=0)
    assert np.isclose(got["eta_disc"], eta_1 + np.sqrt(-sum_C), rtol=TOL, atol=0)


def test_the_shortcuts_against_numpy_quadrature(setup):
    """The two ways to a part of η without a full evaluation give the independent values:
    `linearisation` (η_lin and its parts, the gates' signal) and `remainder_of` (η_rem from
    the global ‖ρ_α‖², as the multilevel flux hands them over). The scene has μ1 ≠ μ2 and
    λ^pos, λ^neg ≠ 0, so a wrong weight or a swapped sum shows."""
    from dolfinx import fem
    disc, X, sigma, alg, r, dlam, ref = setup
    assert MU1 != MU2
    est = Estimators(disc)
    lin1, lin2, lin3 = linearisation_reference(ref)
    got = est.linearisation(X)
    expect = {"eta_lin1": lin1, "eta_lin2": lin2, "eta_lin3": lin3,
              "eta_lin": lin1 + lin3 + np.sqrt(lin2)}
    for key, value in expect.items():
        assert value > 0 and np.isclose(got[key], value, rtol=TOL, atol=0), key
    # ‖r_α‖² by dolfinx's exact quadrature of the DG1 squares (degree 2)
    dx = ufl.dx(metadata={"quadrature_degree": 2})
    squares = [disc.comm.allreduce(float(fem.assemble_scalar(fem.form(ra ** 2 * dx))),
                                   op=MPI.SUM) for ra in r]
    by_hand = CPF * np.sqrt(squares[0] / MU1 + squares[1] / MU2)
    assert np.isclose(est.remainder_of(squares), by_hand, rtol=TOL, atol=0)
    assert np.isclose(est.remainder_of(squares), est.remainder(r), rtol=TOL, atol=0)


def test_energy_error_against_numpy_quadrature(setup):
    disc, X, sigma, alg, r, dlam, ref = setup
    error = EnergyError(disc)
    assert close(error.per_cell(X) ** 2, ref["energy"])
    assert np.isclose(error(X), np.sqrt(ref["energy"].sum()), rtol=TOL, atol=0)


def test_energy_error_needs_exact_solution(setup):
    disc = setup[0]

    class NoExact:
        exact = None
    saved = disc.problem
    try:
        disc.problem = NoExact()
        with pytest.raises(ValueError, match="exact solution"):
            EnergyError(disc)
    finally:
        disc.problem = saved


def test_constraint_estimators_vanish_on_a_feasible_iterate(setup):
    """u1h ≥ u2h, λh ≥ 0 and λh (u1h - u2h) = 0 at every vertex (an iterate satisfying the
    discrete complementarity exactly, as a discrete solution does): s_h = u_h, λ^neg = 0 and
    (u1h - u2h) λ^pos = 0 nodally, but not on cells where contact and gap meet: η_lin1 =
    η_lin2 = η_lin3 = 0 exactly, and Σ_C ≥ 0 (the lumped complementarity leaves a positive
    product (u1h - u2h, λ^pos)_K on the cells that have both a vertex in contact and one off
    it). Without contact (λh = 0) Σ_C = 0 too, and η_lin = 0."""
    disc, X, sigma, alg, r, dlam, ref = setup
    n = disc.n
    est = Estimators(disc)
    coords = disc.V.tabulate_dof_coordinates()[:n, :2].T
    u2 = NP["u2"](coords)
    contact = coords[0] < 0.5
    gap = np.where(contact, 0.0, 0.1 + coords[1] ** 2)
    lam = np.where(contact, 1.0 + coords[1], 0.0)
    Xf = np.concatenate([u2 + gap, u2, lam])
    got = est.assemble(Xf, sigma)
    assert got["eta_lin1"] == got["eta_lin2"] == got["eta_lin3"] == got["eta_lin"] == 0.0
    assert got["eta_C"] > 0.0
    Xn = np.concatenate([u2 + gap, u2, np.zeros(n)])
    got = est.assemble(Xn, sigma)
    assert got["eta_C"] == got["eta_lin"] == 0.0
    # and a negative λ is measured by η_lin3 = C_λ ‖λ^neg‖ alone
    Xm = np.concatenate([u2 + gap, u2, -np.ones(n)])
    got = est.assemble(Xm, sigma)
    c_lambda = est.c_lambda
    area = disc.comm.allreduce(float(cell_areas(disc).sum()), op=MPI.SUM)
    assert got["eta_lin1"] == 0.0 and got["eta_C"] == 0.0
    assert np.isclose(got["eta_lin3"], c_lambda * np.sqrt(area), rtol=TOL, atol=0)


def cell_areas(disc):
    x = disc.V.tabulate_dof_coordinates()[:, :2]
    ncells = disc.mesh.topology.index_map(2).size_local
    d = np.array([disc.V.dofmap.cell_dofs(c) for c in range(ncells)])
    e1, e2 = x[d[:, 1]] - x[d[:, 0]], x[d[:, 2]] - x[d[:, 0]]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def recovered_reference(disc, values):
    """η_rec of `Estimators.recovered` by numpy, independently: per cell the gradient of the P1
    interpolant, the lumped average G_a = Σ_{K∋a} |K| μ ∇u_K / Σ_{K∋a} |K| (the lumped mass
    of vertex a is Σ_{K∋a} |K|/3), and ∫_K |d|² = |K|/12 (Σ_i |d_i|² + |Σ_i d_i|²), exact for the
    P1 field d = μ ∇u_K - G with vertex values d_i."""
    x = disc.V.tabulate_dof_coordinates()[:, :2]
    ncells = disc.mesh.topology.index_map(2).size_local
    d = np.array([disc.V.dofmap.cell_dofs(c) for c in range(ncells)])
    area = cell_areas(disc)
    jac = np.stack([x[d[:, 1]] - x[d[:, 0]], x[d[:, 2]] - x[d[:, 0]]], axis=1)   # rows: edges
    total = 0.0
    for mu, u in zip((disc.mu1, disc.mu2), values):
        du = np.stack([u[d[:, 1]] - u[d[:, 0]], u[d[:, 2]] - u[d[:, 0]]], axis=1)
        flux = mu * np.linalg.solve(jac, du)                                  # (cells, 2)
        weight = np.zeros(x.shape[0])
        np.add.at(weight, d, np.repeat(area[:, None], 3, axis=1))
        G = np.zeros((x.shape[0], 2))
        np.add.at(G, d, (area[:, None] * flux)[:, None, :].repeat(3, axis=1))
        G /= weight[:, None]
        diff = flux[:, None, :] - G[d]                                        # (cells, 3, 2)
        total += (area / 12 * ((diff ** 2).sum(axis=(1, 2))
                               + (diff.sum(axis=1) ** 2).sum(axis=1))).sum() / mu
    return np.sqrt(total)


def test_recovered_flux_against_numpy(setup):
    """η_rec (the Newton gate's stand-in for η_disc) equals the numpy computation to
    round-off, and vanishes for linear u1h, u2h (the average of a constant flux is itself)."""
    disc, X, *_ = setup
    n = disc.n
    est = Estimators(disc)
    values = (X[:n], X[n:2 * n])
    expected = recovered_reference(disc, values)
    assert expected > 0
    assert np.isclose(est.recovered(X), expected, rtol=TOL, atol=0)
    x = disc.V.tabulate_dof_coordinates()[:n, :2].T
    linear = np.concatenate([0.3 * x[0] - x[1], 2 * x[1] + 0.1, X[2 * n:]])
    assert est.recovered(linear) <= 1e-12 * expected
    # with linearisation=True the same assembly also gives `linearisation`'s η_lin and parts
    # (the same integrals summed in another order: round-off)
    eta_rec, lin = est.recovered(X, linearisation=True)
    assert eta_rec == pytest.approx(expected, rel=TOL)
    alone = est.linearisation(X)
    assert alone["eta_lin"] > 0
    for key, value in alone.items():
        assert lin[key] == pytest.approx(value, rel=1e-12, abs=1e-15 * alone["eta_lin"])


FORMS = ["flux_squared", "weighted_norm_squared", "cell_norm_squared", "contact_estimator",
         "energy_squared", "oscillation_squared", "recovery_load"]


@pytest.mark.parametrize("name", FORMS)
def test_a_changed_form_changes_the_result(setup, monkeypatch, name):
    """Scaling one form of forms/estimators.py by 1 + 1e-6 moves some per-cell value off the
    independent quadrature by far more than the tolerance: the comparison sees each form."""
    disc, X, sigma, alg, r, dlam, ref = setup
    original = getattr(est_module, name)
    monkeypatch.setattr(est_module, name, lambda *a, **k: (1 + 1e-6) * original(*a, **k))
    est = Estimators(disc)
    got = per_cell(est, X, sigma, alg)
    rem = est.remainder(r, dlam)
    moved = [k for k, v in got.items() if not close(v, ref[k], 1e-8)]
    if name == "weighted_norm_squared":
        moved += [] if np.isclose(rem, CPF * np.sqrt(ref["rem"].sum()), rtol=1e-8) else ["rem"]
    if name == "recovery_load":
        n = disc.n
        expected = recovered_reference(disc, (X[:n], X[n:2 * n]))
        moved += [] if np.isclose(est.recovered(X), expected, rtol=1e-8) else ["rec"]
    assert moved, name


@pytest.mark.parametrize("procs", [2, 3])
def test_same_estimators_on_several_processes(procs):
    """The global values on 2 and 3 processes equal the serial ones to 1e-12 relative (every
    rank returns the same numbers: the script checks it)."""
    runs = {}
    for p in (1, procs):
        done = mpirun([os.path.join(ROOT, "tests", "core", "mpi_estimators.py"), 16],
                      processes=p)
        assert done.returncode == 0, done.stderr[-2000:]
        runs[p] = json.loads(done.stdout.strip().splitlines()[-1])
    serial, parallel = runs[1], runs[procs]
    assert serial.keys() == parallel.keys()
    for key, value in serial.items():
        assert abs(parallel[key] - value) <= 1e-12 * abs(value), key


@pytest.fixture(scope="module")
def equilibrated():
    from membranes.estimation.equilibration import FluxEquilibration
    disc = scene(MPI.COMM_WORLD, 6)[0]
    return disc, Estimators(disc, FluxEquilibration(disc))


def test_nu_flux_divergence_and_remainder(equilibrated):
    """σ_alg = σ_disc(X', R') - σ_disc(X, R) has, on every cell, the divergence
    ∇·σ_α,alg = r_αh - r'_αh ± (λ'_h - λh) (+ for α = 1; §6) to round-off, and η_rem is
    C_PF h_Ω (Σ_α μ_α^{-1} ‖r'_αh ∓ (λ'_h - λh)‖²)^{1/2} (against the remainder's own form
    with the liftings and δλ passed in)."""
    import ufl
    from dolfinx import fem
    disc, est = equilibrated
    n = disc.n
    X, X2 = iterate(disc, 0.0), iterate(disc, 0.7)
    R, R2 = residual(disc, X), residual(disc, X2)
    alg, eta_rem = est.nu_flux(X, R, X2, R2)
    r, r2 = est.lifted(R), est.lifted(R2)
    lam, lam2 = (disc.functions(Y)[2] for Y in (X, X2))
    W = fem.FunctionSpace(disc.mesh, ("DG", 0))
    w = ufl.TestFunction(W)
    ncells = disc.mesh.topology.index_map(2).size_local
    cells = W.dofmap.list.array[:ncells]
    dx = ufl.dx(metadata={"quadrature_degree": 2})
    for a, sign in ((0, 1.0), (1, -1.0)):
        target = r[a] - r2[a] + sign * (lam2 - lam)
        defect = fem.assemble_vector(fem.form((ufl.div(alg[a]) - target) ** 2 * w * dx))
        size = fem.assemble_vector(fem.form(target ** 2 * w * dx))
        defect, size = defect.array[cells], size.array[cells]
        assert size.max() > 0
        assert np.sqrt(defect.max() / size.max()) < 1e-11, np.sqrt(defect.max() / size.max())
    dlam = X2[2 * n:] - X[2 * n:]
    assert np.isclose(eta_rem, est.remainder(r2, dlam), rtol=1e-14, atol=0)
    by_hand = CPF * np.sqrt(disc.comm.allreduce(sum(
        float(fem.assemble_scalar(fem.form(rho ** 2 / mu * dx)))
        for rho, mu in ((r2[0] - (lam2 - lam), MU1), (r2[1] + (lam2 - lam), MU2))), op=MPI.SUM))
    assert np.isclose(eta_rem, by_hand, rtol=1e-12, atol=0)


def test_evaluate_with_the_equilibration(equilibrated):
    """evaluate(X, R, σ_alg) with the ν flux measures u_h(X) against σ_disc(X'): its η_F is
    that of `assemble` with σ = σ_disc(X') (σ_disc(X) + σ_alg, to round-off), and its η_alg
    is ‖μ^{-1/2} σ_alg‖ + η_rem. Without σ_alg the default remainder is the Poincaré bound
    of the whole lifted residual; with R = 0 there is none."""
    disc, est = equilibrated
    X, X2 = iterate(disc, 0.0), iterate(disc, 0.7)
    R, R2 = residual(disc, X), residual(disc, X2)
    alg, eta_rem = est.nu_flux(X, R, X2, R2)
    got = est.evaluate(X, R, alg, eta_rem)
    (s2, _) = est.sigma_disc(X2, R2)
    direct = est.assemble(X, s2)
    assert np.isclose(got["eta_F"], direct["eta_F"], rtol=1e-12, atol=0)
    # σ_disc's measured divergence defect, as a remainder (module notes): round-off here
    defect = est.defect_remainder(est.sigma_disc(X, R)[0])
    assert 0.0 < defect <= 1e-12 * est.remainder(est.lifted(R))
    plain = est.evaluate(X, R)
    assert np.isclose(plain["eta_rem"], est.remainder(est.lifted(R)) + defect, rtol=1e-14,
                      atol=0)
    assert plain["eta_rem"] > 0 and plain["eta_alg"] == plain["eta_rem"]
    for key in ("eta_disc", "eta_lin", "eta_osc", "eta_C"):
        assert got[key] == plain[key], key
    assert got["eta_alg"] > eta_rem > 0
    # with σ_alg but no eta_rem the remainder is σ_disc's defect alone (the multilevel
    # flux's is exact in exact arithmetic): η_alg is ‖μ^{-1/2} σ_alg‖ and that defect (the
    # same sum as in `got`, less η_rem: round-off)
    bare = est.evaluate(X, R, alg)
    assert bare["eta_rem"] == defect
    assert np.isclose(bare["eta_alg"], got["eta_alg"] - eta_rem, rtol=1e-12, atol=0)


def test_an_iterate_without_residual_after_three_with_one():
    """σ_disc of an iterate given without residual (R = None: r_αh = 0, e.g. the discrete
    solution, whose R = B - A X is round-off) is solved into the Functions of the oldest
    kept iterate where two are kept (after three evaluations with residuals: the first's
    σ_disc, in the forms' own Functions, is dropped by the second's, and the second and third
    are kept in their own): its lifted residual is zeroed first, so the estimates are those
    of a fresh Estimators (to 8 ε of each value, as in the test above), not those of r_αh
    left at an earlier iterate's (then σ_disc failed its divergence check). The discrete
    solution comes from exact Newton with MUMPS."""
    from membranes.estimation.equilibration import FluxEquilibration
    from membranes.nonlinear.newton import newton
    disc = scene(MPI.COMM_WORLD, 6)[0]
    solution = newton(disc, krylov="direct")
    assert solution.converged, solution.reason
    Xs = np.array(solution.X.array_r)
    est = Estimators(disc, FluxEquilibration(disc))
    for seed in (0.0, 0.7, 0.3):
        Y = iterate(disc, seed)
        est.evaluate(Y, residual(disc, Y))
    assert len(est._recent) == 2 and all(r is not None for (_, r), _ in est._recent)
    got = est.evaluate(Xs)
    fresh = Estimators(disc, FluxEquilibration(disc)).evaluate(Xs)
    tol = 8 * np.finfo(float).eps
    assert all(close(got[k], fresh[k], tol) for k in fresh), \
        [k for k in fresh if not close(got[k], fresh[k], tol)]


def test_what_the_estimators_refuse(setup):
    """σ_disc needs the flux equilibration (an Estimators without one says so, rather than
    failing inside), and a remainder's r_αh must be DG1 Functions of the lifting's layout
    (P1 ones are refused, not copied dof by dof)."""
    from dolfinx import fem
    disc, X, *_ = setup
    est = Estimators(disc)
    with pytest.raises(ValueError, match="needs an equilibration"):
        est.sigma_disc(X)
    with pytest.raises(ValueError, match="DG1"):
        est.remainder([fem.Function(disc.V), fem.Function(disc.V)])


def test_the_estimators_refuse_forces_that_underflow(setup, monkeypatch):
    """Estimators refuses, in its set-up, data whose forces min(μ1, μ2) u_data lie below
    model.checks.UNDERFLOW_SCALE (module notes: there η_F's squares underflow and η fell
    below the error): a caller of the estimators alone (not through the driver, which checks
    the coarsest level itself) is refused too. The data scale is set to 1e-145 (μ = 1, 3)."""
    disc = setup[0]
    monkeypatch.setattr(disc, "data_scales", lambda: (1e-145, 1.0))
    with pytest.raises(ValueError, match="the estimators underflow double precision"):
        Estimators(disc)


def test_the_data_parts_wait_for_the_first_full_evaluation():
    """σ_disc's loads and η_osc are made at the first full evaluation, not in the set-up nor by
    the η_rec / η_lin gates (a run's Newton steps before that evaluation do not carry them),
    unless `eager_data` asks for them in the set-up. Either way they are the same arrays, so
    the evaluations agree to round-off: the same operations on the same data, but in two
    set-ups whose arrays lie at other addresses, and numpy's vectorised sums and products may
    group their terms by the memory alignment (seen: 24 of 72 η_K apart by one or two units in
    the last place, 4.9e-17 of 0.107). 8 ε of each array's largest entry allows for that."""
    from membranes.estimation.equilibration import FluxEquilibration
    disc = scene(MPI.COMM_WORLD, 6)[0]
    X, R = iterate(disc, 0.0), residual(disc, iterate(disc, 0.0))
    lazy = Estimators(disc, FluxEquilibration(disc))
    lazy.recovered(X, linearisation=True)
    lazy.linearisation(X)
    assert lazy._loads is None and lazy._osc_t is None
    got = lazy.evaluate(X, R)
    assert lazy._loads is not None and lazy._osc_t is not None
    eager = Estimators(disc, FluxEquilibration(disc), eager_data=True)
    assert eager._loads is not None and eager._osc_t is not None
    for a, b in zip(lazy.loads, eager.loads):
        assert all(np.array_equal(x, y) for x, y in zip(a.values, b.values))
    assert np.array_equal(lazy.osc, eager.osc)
    again = eager.evaluate(X, R)
    assert again.keys() == got.keys()
    tol = 8 * np.finfo(float).eps
    assert all(close(again[k], got[k], tol) for k in got), \
        [k for k in got if not close(again[k], got[k], tol)]
    assert got["eta_osc"] > 0                        # (the scene's loads are not in P1)


def test_the_first_sigma_disc_in_the_forms_coefficients_is_never_stale():
    """The first σ_disc on a mesh is solved into the forms' own σ Functions (no second copy);
    an evaluation at another iterate copies that iterate's σ_disc over them, and the first,
    asked for again, is then solved anew: equal to the last bit to what it was."""
    from membranes.estimation.equilibration import FluxEquilibration
    disc = scene(MPI.COMM_WORLD, 6)[0]
    est = Estimators(disc, FluxEquilibration(disc))
    X, X2 = iterate(disc, 0.0), iterate(disc, 0.7)
    R, R2 = residual(disc, X), residual(disc, X2)
    first, _ = est.sigma_disc(X, R)
    assert first[0] is est.sigma[0] and first[1] is est.sigma[1]
    before = [f.x.array.copy() for f in first]
    eta = est.evaluate(X, R)["eta"]       # (σ_disc(X) kept: no new solve, no copy)
    est.evaluate(X2, R2)                  # σ_disc(X2) into Functions of its own, then copied
    assert all(not np.array_equal(f.x.array, b) for f, b in zip(est.sigma, before))
    again, _ = est.sigma_disc(X, R)
    assert all(np.array_equal(f.x.array, b) for f, b in zip(again, before))
    # and the evaluation at X after X2 is the one before it, to the last bit: no coefficient
    # of the forms (σ, the lifted residual, the iterate) is left at X2's values
    assert est.evaluate(X, R)["eta"] == eta


def test_chunked_assemblies_equal_whole(setup, monkeypatch):
    """A CellForm (and η_rec's load) assembled a chunk of cells at a time (`chunks`, which
    bounds dolfinx's packed coefficients) gives the same per-cell integrals as one assembly
    over the mesh: each cell's integral is the same kernel call, so equal to the last bit;
    and the chunks do split the mesh here."""
    disc, X, sigma, alg, *_ = setup
    whole = Estimators(disc)
    whole_q = per_cell(whole, X, sigma, alg)
    whole_rec = whole.recovered(X, linearisation=True)
    nc = disc.mesh.topology.index_map(2).size_local
    from membranes.estimation import cell_forms
    monkeypatch.setattr(cell_forms, "CHUNK_CELLS", max(1, nc // 5))
    chunked = Estimators(disc)
    assert len(chunked.cells_alg.forms) > 2
    for key, value in per_cell(chunked, X, sigma, alg).items():
        assert np.array_equal(value, whole_q[key]), key
    rec = chunked.recovered(X, linearisation=True)
    assert len(chunked._recovery[0]) > 2
    assert rec[0] == pytest.approx(whole_rec[0], rel=1e-14)
    assert rec[1] == pytest.approx(whole_rec[1], rel=1e-14)


def test_one_kernel_for_every_chunk_count(setup):
    """A mesh that fits one chunk compiles the kernel that a mesh of many chunks uses (the
    JIT warm-up runs on tiny meshes, membranes.app.warmup): the UFL signatures of `chunks`
    with one chunk and with several are the same, and differ from the untagged form's."""
    import ufl
    from dolfinx import fem

    from membranes.estimation.cell_forms import chunks
    disc = setup[0]
    v = ufl.TestFunction(fem.FunctionSpace(disc.mesh, ("DG", 0)))
    form = v * ufl.dx(domain=disc.mesh)
    one = chunks(form, disc.mesh)
    nc = disc.mesh.topology.index_map(2).size_local
    several = chunks(form, disc.mesh, size=max(1, nc // 4))
    assert len(one) == 1 and len(several) >= 4
    assert {f.signature() for f in several} == {one[0].signature()}
    assert one[0].signature() != form.signature()
    assert sum(fem.assemble_scalar(fem.form(ufl.replace(f, {v: 1.0}))) for f in several) \
        == pytest.approx(fem.assemble_scalar(fem.form(ufl.replace(form, {v: 1.0}))), rel=1e-13)


def test_compiled_chunks_equal_forms(setup):
    """`cell_forms.compiled` (one JIT lookup for all the chunks of a form) makes the forms
    that `dolfinx.fem.form` makes chunk by chunk: the same vector to the last bit, for a form
    with coefficients and constants (the coefficients' order comes from the first chunk). The
    form's first coefficient z drops out when UFL applies the derivative in it, so the
    compiled form's coefficients are the form's second and third (FFCx's
    original_coefficient_position is not the identity)."""
    import ufl
    from dolfinx import fem

    from membranes.estimation.cell_forms import chunks, compiled
    disc = setup[0]
    V = fem.VectorFunctionSpace(disc.mesh, ("DG", 0), dim=2)
    w = ufl.TestFunction(V)
    z = fem.Function(fem.FunctionSpace(disc.mesh, ("DG", 1)))
    a, b = fem.Function(disc.V), fem.Function(fem.FunctionSpace(disc.mesh, ("RT", 2)))
    z.x.array[:] = 7.0
    a.x.array[:] = np.sin(np.arange(a.x.array.size))
    b.x.array[:] = np.cos(np.arange(b.x.array.size))
    c = fem.Constant(disc.mesh, 3.0)
    dx = ufl.dx(domain=disc.mesh)
    form = (c * a * a * w[0] + ufl.div(b) * a * w[1]) * dx \
        + ufl.derivative(z * b[0] * w[1] * dx, z, a)            # a b[0] w[1]: z drops out
    assert form.coefficients()[0] is z
    nc = disc.mesh.topology.index_map(2).size_local
    parts = chunks(form, disc.mesh, size=max(1, nc // 4))
    assert len(parts) >= 4
    by_chunk, together = (np.zeros(V.dofmap.index_map.size_local * 2) for _ in range(2))
    for part in parts:
        fem.assemble_vector(by_chunk, fem.form(part))
    for part in compiled(parts, disc.mesh):
        fem.assemble_vector(together, part)
    assert np.array_equal(by_chunk, together) and np.abs(together).max() > 0
