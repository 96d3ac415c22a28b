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


def _scene_values(problem, names=("u1", "u2", "lam", "f1", "f2")):
    """(X, Y, {name: values}) of a scene's exact solution and loads at interior points of every
    owned cell, evaluated by dolfinx from the scene's UFL builders."""
    import dolfinx.fem
    import ufl

    mesh = problem.mesh
    x = ufl.SpatialCoordinate(mesh)
    ex = problem.exact
    builders = {"u1": ex.u1, "u2": ex.u2, "lam": ex.lam, "f1": problem.f1, "f2": problem.f2}
    points = np.array([[0.1, 0.1], [0.2, 0.6], [0.6, 0.2], [1 / 3, 1 / 3], [0.05, 0.9]])
    cells = np.arange(mesh.topology.index_map(2).size_local, dtype=np.int32)

    def values(e):
        return dolfinx.fem.Expression(ufl.as_ufl(e), points).eval(cells).reshape(-1)
    return values(x[0]), values(x[1]), {k: values(builders[k](x)) for k in names}


def _sympy_check(u1, u2, lam, mu1, mu2, interface, X, Y, got):
    """The scene's values `got` against the sympy expressions u1, u2, λ (in x, y) and the loads
    f1 = -μ1 Δu1 - λ, f2 = -μ2 Δu2 + λ that sympy differentiates from them (§1), at the points
    (X, Y) at least 1e-6 off the interface (where λ and the loads jump; the two sides of a
    round-off difference in r² would disagree). Tolerance: 1e-12 of each field's largest value,
    round-off of a few dozen operations in double."""
    import sympy as sp

    x, y = sp.symbols("x y", real=True)
    lap = {k: sp.diff(e, x, 2) + sp.diff(e, y, 2) for k, e in (("u1", u1), ("u2", u2))}
    exact = {"u1": u1, "u2": u2, "lam": lam,
             "f1": -mu1 * lap["u1"] - lam, "f2": -mu2 * lap["u2"] + lam}
    away = np.abs(interface(np.vstack([X, Y]))) > 1e-6
    assert away.sum() > 0.9 * away.size
    for name, e in exact.items():
        want = np.broadcast_to(sp.lambdify((x, y), e, "numpy")(X, Y), X.shape)[away]
        scale = np.abs(want).max()
        assert np.allclose(got[name][away], want, rtol=0, atol=1e-12 * scale), name


def test_disk_exact_solution_solves_the_disk_data():
    """The disk scene (§9, μ1 = μ2 = 1, g = 0.05): its hand-written loads f1, f2 and its λ are
    those sympy derives from the stated solution, u1 = g (2r² - 1), u2 = u1 on the contact disk
    r² ≤ 1/2 and c (1 - r)(2r² - 1) outside, λ = 2g on the disk; c is solved here from u2 ∈ C¹
    at r = 1/√2 (the radial derivatives 4g r and 4c r (1 - r) agree), not copied. A wrong
    λ (the energy error never reads it) or a wrong load or c (an error that is no longer
    that of the data solved) shows here; and the gap and λ are complementary, u1 = g and
    u2 = 0 on the unit circle."""
    import sympy as sp
    import ufl

    problem = scenes.disk(h=0.5)
    g = scenes.DISK_G
    x, y, c = sp.symbols("x y c", real=True)
    r2 = x ** 2 + y ** 2
    r = sp.sqrt(r2)
    r0 = 1 / sp.sqrt(2)
    rr = sp.Symbol("rr", positive=True)
    outside = c * (1 - rr) * (2 * rr ** 2 - 1)                 # u2 off the contact disk
    c_val = sp.solve(sp.Eq(sp.diff(outside, rr).subs(rr, r0), 4 * g * r0), c)[0]
    inside = r2 <= sp.Rational(1, 2)
    u1 = g * (2 * r2 - 1)
    u2 = sp.Piecewise((u1, inside), (outside.subs({c: c_val, rr: r}), True))
    lam = sp.Piecewise((2 * g, inside), (0, True))
    X, Y, got = _scene_values(problem)
    _sympy_check(u1, u2, lam, 1.0, 1.0, lambda p: p[0] ** 2 + p[1] ** 2 - 0.5, X, Y, got)
    w = got["u1"] - got["u2"]
    assert w.min() >= -1e-15 and got["lam"].min() >= 0
    assert np.abs(w * got["lam"]).max() <= 1e-15
    assert float(c_val) == pytest.approx(g / (1 - 2 ** -0.5), rel=1e-14)
    ufl_x = ufl.SpatialCoordinate(problem.mesh)
    for t in np.linspace(0.0, 2 * np.pi, 7):            # u1 = g, u2 = 0 on the circle
        point = (np.cos(t), np.sin(t))
        assert np.isclose(problem.exact.u1(ufl_x)(point), g, rtol=1e-12)
        assert abs(problem.exact.u2(ufl_x)(point)) <= 1e-12 * g


def test_disk_and_square_parameters_are_those_of_the_design():
    """The data the sympy checks above take from scenes.py (DISK_G, SQUARE) are those DESIGN.md
    states: the disk scene is the paper's case μ1 = μ2 = 1, g = 0.05 (§9; the checks derive
    the rest from g, so another g passed them), the square's μ1 = 1, μ2 = 2, g = 0.1 with its
    contact zone s ≥ 1/2 (the module's header); exact numbers of the specification."""
    disk = scenes.disk(h=0.5)
    assert (disk.mu1, disk.mu2, disk.g) == (1.0, 1.0, 0.05)
    square = scenes.square(h=0.5)
    assert (square.mu1, square.mu2, square.g, scenes.SQUARE["s0"]) == (1.0, 2.0, 0.1, 0.5)


def test_square_exact_solution_solves_the_square_data():
    """The square scene (manufactured, μ1 = 1, μ2 = 2, g = 0.1): u2 = (g/2) sin πx sin πy,
    u1 = u2 + w with w = g ((s0 - s)/s0)² off Z = {s ≥ s0} and 0 on Z, λ = λ0 (s - s0)/(1 - s0)
    on Z; the scene's loads (UFL differentiates them) are sympy's -μ1 Δu1 - λ and
    -μ2 Δu2 + λ, so a wrong sign of λ in a load (the solution then solves other data, and
    the energy error is measured against the wrong solution) shows here. The gap and λ are
    complementary."""
    import sympy as sp

    problem = scenes.square(h=0.3)
    k = scenes.SQUARE
    x, y = sp.symbols("x y", real=True)
    s = 16 * x * (1 - x) * y * (1 - y)
    g, s0, lam0 = k["g"], k["s0"], k["lam0"]
    u2 = g / 2 * sp.sin(sp.pi * x) * sp.sin(sp.pi * y)
    u1 = u2 + sp.Piecewise((g * ((s0 - s) / s0) ** 2, s < s0), (0, True))
    lam = sp.Piecewise((lam0 * (s - s0) / (1 - s0), s > s0), (0, True))
    X, Y, got = _scene_values(problem)
    _sympy_check(u1, u2, lam, k["mu1"], k["mu2"], problem.interface, X, Y, got)
    w = got["u1"] - got["u2"]
    assert w.min() >= -1e-15 and got["lam"].min() >= 0
    assert np.abs(w * got["lam"]).max() <= 1e-15
    assert got["lam"].max() > 0.1 * lam0                  # the contact zone is sampled


def test_no_interface_where_the_data_do_not_jump():
    """A scene declares an interface only where its data jump (the module's header): the
    radial scene's λ and loads are smooth with no contact (λ = 0) and with grazing contact
    (ρ = 0: λ = 0 off the origin), so it declares none and the driver spends no composite
    rule on cells at a level set r² that cuts no cell; with a contact disk it declares one.
    The user scene knows no jump of its formulas: none either."""
    assert scenes.radial(h=0.5, rho=0.0).interface is None
    assert scenes.radial(h=0.5, contact=False).interface is None
    assert scenes.radial(h=0.5, rho=0.5).interface is not None
    assert scenes.user(h=0.5, f1="-1").interface is None


def test_interfaces_are_where_the_data_jump():
    """A scene's level set (Problem.interface, the cells it cuts get the composite rule, §7,
    §9) vanishes where its λ and loads jump: on the circle r = ρ of the radial scene (ρ = 0.5
    and 0.3; r² - ρ², not r² - ρ), on r = 1/√2 for the disk, negative inside; and its sign
    separates λ > 0 from λ = 0 at sampled points (the square's contact zone s ≥ 1/2 included).
    Tolerance: round-off of r² on the unit circle's scale."""
    import ufl

    t = np.linspace(0.0, 2 * np.pi, 13)
    for problem, radius in ((scenes.radial(h=0.5, rho=0.5), 0.5),
                            (scenes.radial(h=0.5, rho=0.3), 0.3),
                            (scenes.disk(h=0.5), 2 ** -0.5)):
        for scale, sign in ((1.0, 0), (0.9, -1), (1.1, 1)):
            p = scale * radius * np.vstack([np.cos(t), np.sin(t)])
            level = problem.interface(p)
            if sign == 0:
                assert np.abs(level).max() <= 1e-15, problem.description
            else:
                assert np.all(np.sign(level) == sign), problem.description
    for problem in (scenes.radial(h=0.5, rho=0.5), scenes.disk(h=0.5), scenes.square(h=0.3)):
        x = ufl.SpatialCoordinate(problem.mesh)
        rng = np.random.default_rng(1)
        lo = 0.0 if problem.name == "square" else -0.7
        for p in rng.uniform(lo, 0.7, size=(40, 2)):
            lam = float(problem.exact.lam(x)(tuple(p)))
            level = float(problem.interface(p.reshape(2, 1))[0])
            if abs(level) > 1e-9:
                inside = level > 0 if problem.name == "square" else level < 0
                assert (lam > 0) == inside, (problem.description, p)
