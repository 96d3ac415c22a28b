"""The radial family of exact solutions (scenes.radial; groundwork for §11's cases):
contact disk, near-total contact, grazing contact and no contact, for any μ1, μ2, g. Every
case converges with min and Fischer–Burmeister, complementarity holds at round-off (fb: at its
tolerance), and the guaranteed bound holds at the final iterate."""

import numpy as np
import pytest

from membranes import scenes, solve


@pytest.mark.parametrize("kwargs", [{"rho": 0.5}, {"rho": 0.95}, {"rho": 0.0},
                                    {"contact": False}, {"rho": 0.5, "mu1": 1e-3}],
                         ids=["contact", "near-total", "grazing", "none", "stiff"])
@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_radial_cases(kwargs, cfun):
    run = solve(scenes.radial(h=0.1, **kwargs), cfun=cfun, newton="exact", solver="direct")
    assert run.converged, run.reason
    s = run.summary()
    assert run.complementarity_violation() <= 1e-10
    assert s["bound_guaranteed"] and s["eta"] >= run.energy_error


def test_radial_bad_parameters():
    for kwargs in ({"rho": 1.0}, {"rho": -0.1}, {"mu1": 0.0}, {"g": float("nan")},
                   {"rho": False}, {"rho": True}):
        with pytest.raises(ValueError):
            scenes.radial(h=0.3, **kwargs)


def _closed_form(X, Y, mu1, mu2, g, rho, contact):
    """u1, u2, λ, f1, f2 of the radial family from the formulas of scenes.py, by hand."""
    r2 = X ** 2 + Y ** 2
    u2 = 0.5 * g * (r2 - 1)
    if not contact:
        w, lap_w, lam = 0.5 * g * (1 + r2), 2 * g, 0 * r2
    else:
        t = (r2 - rho ** 2) / (1 - rho ** 2)
        out = r2 > rho ** 2
        w = np.where(out, g * t ** 2, 0.0)
        lap_w = np.where(out, 8 * g * (2 * r2 - rho ** 2) / (1 - rho ** 2) ** 2, 0.0)
        lam = np.where(r2 < rho ** 2, 4 * g, 0.0) if rho > 0 else 0 * r2
    return u2 + w, u2, lam, -mu1 * (2 * g + lap_w) - lam, -2 * mu2 * g + lam


@pytest.mark.parametrize("mu1, mu2, g, rho, contact", [
    (1.0, 1.0, 0.05, 0.5, True), (1e-6, 1.0, 0.05, 0.5, True), (1.0, 1e6, 1e-12, 0.9, True),
    (2.0, 3.0, 1e3, 0.0, True), (5.0, 0.2, 0.3, 0.2, False)])
def test_radial_exact_solution(mu1, mu2, g, rho, contact):
    """The scene's UFL data (loads differentiated by UFL) are the closed-form ones, and the
    exact solution meets the boundary values and complementarity (§1) at sampled points."""
    import dolfinx.fem
    import ufl

    problem = scenes.radial(h=0.5, mu1=mu1, mu2=mu2, g=g, rho=rho, contact=contact)
    mesh = problem.mesh
    x = ufl.SpatialCoordinate(mesh)
    ex = problem.exact
    points = np.array([[0.1, 0.1], [0.2, 0.6], [0.6, 0.2], [0.3, 0.3], [0.05, 0.9]])
    cells = np.arange(mesh.topology.index_map(2).size_local, dtype=np.int32)
    values = []
    for e in (x[0], x[1], ex.u1(x), ex.u2(x), ex.lam(x), problem.f1(x), problem.f2(x)):
        e = ufl.as_ufl(e)
        if e.ufl_domain() is None:                      # λ = 0 folds to a UFL zero
            values.append(np.full(len(cells) * len(points), float(e)))
        else:
            values.append(dolfinx.fem.Expression(e, points).eval(cells).reshape(-1))
    X, Y, *got = values
    for name, a, b in zip(("u1", "u2", "lam", "f1", "f2"), got,
                          _closed_form(X, Y, mu1, mu2, g, rho, contact)):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max()), name
    u1, u2, lam = got[:3]
    assert (u1 - u2).min() >= 0 and lam.min() >= 0 and not np.any((u1 - u2) * lam)
    for t in np.linspace(0.0, 2 * np.pi, 7):            # u1 = g, u2 = 0 on the circle
        point = (np.cos(t), np.sin(t))
        assert np.isclose(ex.u1(x)(point), g, rtol=1e-12)
        assert abs(ex.u2(x)(point)) <= 1e-12 * g


@pytest.mark.parametrize("options", [{"newton": "exact", "solver": "direct"}, {}],
                         ids=["exact", "adaptive"])
def test_zero_loads_complementarity_at_round_off(options):
    """Zero loads: the solution is (g, 0, 0) and λ_data = 0 (§11). Newton-FB from a zero guess
    (contact, with w = λ = 0, at every vertex: the kink) ends with λ at round-off of either
    sign; the violation measures it against the pressure that moves the gap by the
    displacement scale, not against λ's own round-off (which made it 1). Tolerance: that of
    the radial cases, a relative residual 1e-10 with room."""
    run = solve(scenes.user(domain="square", h=0.3, levels=1), cfun="fb", initial_guess="zero",
                **options)
    assert run.converged, run.reason
    assert run.complementarity_violation() <= 1e-10
