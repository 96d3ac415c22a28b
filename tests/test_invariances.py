"""Exact invariances of the discrete problem (theory §1, §2, §11), as checks of the numerics on
extreme data. Each holds for the discrete equations exactly, so each run is compared with a
reference run on the same mesh:

* data scaling: (f1, f2, g) → c (f1, f2, g) gives (u, λ) → c (u, λ) (positive homogeneity);
  the C-functions, X⁰ and every test of §8 are invariant, so the whole run is, counts
  included (§11), and η's parts scale by c (η_C and η_lin2, products, by c²);
* moduli scaling: (μ1, μ2, f1, f2) → c (μ1, μ2, f1, f2) leaves u and κλ unchanged and scales
  λ by c, the energy norm and η by √c (η_C, η_lin2 by c); the weighted rows and (a, κλ) of §3
  are invariant, so again the whole run is (with MUMPS, save for the refinement steps a
  non-invariant factorisation may need: `_assert_same_run`);
* mirror: (μ1, μ2, f1, f2) → (μ2, μ1, -f2, -f1) gives (u1, u2, λ) → (g - u2, g - u1, λ): the
  same gap and contact set, S 1 = 0 at interior rows; X⁰ = (g, 0, 0) is its own mirror;
* common displacement: (f1, f2) → (f1 + μ1 φ, f2 + μ2 φ) leaves μ2 F1 - μ1 F2, hence w and λ,
  unchanged (§10), and adds one function to both membranes.

Scaled data are multiplied by a dolfinx Constant, so that all runs of a test share their
compiled forms. Tolerances: the runs are equal in exact arithmetic and their floating-point
operations differ only in rounding (c is no power of 2). Measured here: u ≤ 2e-15, λ ≤ 6e-14
(a difference of membrane rows) relative to their largest values, η's parts ≤ 6e-15 of η (η²
for η_C, η_lin2), the energy error ≤ 2e-16. TOL = 1e-9 leaves room for the amplification by
the condition of the Newton systems (~1e3 here) without letting through anything the solver
tolerances could cause: exact Newton solves to 2e-12 and stops at 1e-10, and the adaptive
runs stop at η_alg ≤ 0.3 max(η_disc, η_lin), so a run that took another path would differ
by far more.
"""

from dataclasses import replace

import numpy as np
import pytest
import ufl
from dolfinx import fem
from petsc4py import PETSc

from membranes import scenes, solve
from membranes.linalg.krylov import EXACT_TOL
from membranes.model.problem import ExactSolution, as_builder

TOL = 1e-9
# η_lin = η_lin1 + η_lin3 + √η_lin2 is not compared itself: at an exact solve η_lin2 is at
# round-off (~1e-17 η²) and its root at ~√ε η, a deviation of the root of round-off
PARTS = ("eta", "eta_disc", "eta_alg", "eta_F", "eta_osc", "eta_C", "eta_lin1", "eta_lin2",
         "eta_lin3", "eta_rem")
QUADRATIC = ("eta_C", "eta_lin2")


def _scaled(problem, value=1.0, moduli=False):
    """The problem with f1, f2 and (moduli: μ1, μ2 and λ; else g, u and λ) multiplied by a
    Constant holding `value` (returned too, to set another value without recompiling)."""
    c = fem.Constant(problem.mesh, PETSc.ScalarType(value))
    f1, f2, ex = as_builder(problem.f1), as_builder(problem.f2), problem.exact
    if moduli:
        exact = ExactSolution(ex.u1, ex.u2, lambda x: c * ex.lam(x))
        changed = {"mu1": value * problem.mu1, "mu2": value * problem.mu2}
    else:
        exact = ExactSolution(lambda x: c * ex.u1(x), lambda x: c * ex.u2(x),
                              lambda x: c * ex.lam(x))
        changed = {"g": value * problem.g}
    return replace(problem, f1=lambda x: c * f1(x), f2=lambda x: c * f2(x), exact=exact,
                   **changed)


def _parts(sol):
    u1, u2, lam = sol.disc.split(sol.X)
    return np.array(u1), np.array(u2), np.array(lam)


def _deviation(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


def _assert_same_run(ref, run, u_maps, eta_scale, err_scale, direct=False):
    """`run` is `ref` transformed: the same counts, u_maps(run's (u1, u2, λ)) = ref's, its η
    parts eta_scale(name) times ref's, its energy error err_scale times ref's. `direct`: the
    runs solve with MUMPS, whose factors are not invariant (pivoting and round-off follow the
    scaled entries): the same Newton steps, and every step solved to the exact variant's
    2e-12 in both runs, by refinement where the back-solve left more (at μ = 1e-16 with FB
    one step's back-solve left ‖R_alg‖/‖B‖ = 4.4e-7), so the refinement steps, which count
    as linear iterations, may differ."""
    assert run.converged, run.reason
    if direct:
        assert run.newton_iterations == ref.newton_iterations
        for sol in (ref, run):
            assert all(rec["alg_residual"] <= EXACT_TOL for rec in sol.history
                       if rec.get("alg_residual") is not None)
    else:
        assert (run.newton_iterations, run.linear_iterations) == \
            (ref.newton_iterations, ref.linear_iterations)
    for name, a, b in zip(("u1", "u2", "lam"), u_maps(*_parts(run)), _parts(ref)):
        assert _deviation(a, b) <= TOL, (name, _deviation(a, b))
    eta = ref.estimates["eta"]
    for name in PARTS:          # measured against η (η²): parts at round-off compare too
        a, b = run.estimates[name], ref.estimates[name]
        assert abs(a / eta_scale(name) - b) <= TOL * eta ** (2 if name in QUADRATIC else 1), \
            (name, a, b)
    if ref.energy_error is not None:
        assert abs(run.energy_error / err_scale - ref.energy_error) <= \
            TOL * ref.energy_error


@pytest.mark.parametrize("cfun, newton, solver", [("min", "adaptive", "amg"),
                                                  ("fb", "exact", "direct")])
def test_data_scaling(cfun, newton, solver):
    """c = 1e-12 and 1e12 on the radial scene (exact solution): the run of c = 1, scaled."""
    problem = _scaled(scenes.radial(h=0.1, rho=0.5))
    options = {"cfun": cfun, "newton": newton, "solver": solver}
    ref = solve(problem, **options)
    for c in (1e-12, 1e12):
        run = solve(_scaled(problem, c), **options)
        _assert_same_run(ref, run, lambda u1, u2, lam: (u1 / c, u2 / c, lam / c),
                         lambda name: c ** 2 if name in QUADRATIC else c, c,
                         direct=solver == "direct")


@pytest.mark.parametrize("cfun, newton, solver, petsc_options", [
    ("fb", "exact", "paper", None), ("min", "adaptive", "paper", None),
    ("fb", "exact", "amg", "-pc_type ilu")])
def test_moduli_scaling_incomplete_factorisations(cfun, newton, solver, petsc_options):
    """μ1 = μ2 = 1e12 (and 1e-12) on the disk with ILU(0) (the paper preset's, or the user's
    on the eliminated system): u unchanged, λ, η², the energy error² scaled by c. With
    PETSc's absolute zero-pivot threshold of ILU (2.2e-14) the λ pivots, of size κ h² ∝ 1/c,
    were taken for zero: DIVERGED_PCSETUP_FAILED at Newton step 2 to 5 (krylov notes)."""
    problem = _scaled(scenes.disk(h=0.1), moduli=True)
    options = {"cfun": cfun, "newton": newton, "solver": solver,
               "petsc_options": petsc_options}
    ref = solve(problem, **options)
    for c in (1e-12, 1e12):
        run = solve(_scaled(problem, c, moduli=True), **options)
        _assert_same_run(ref, run, lambda u1, u2, lam: (u1, u2, lam / c),
                         lambda name: c if name in QUADRATIC else np.sqrt(c), np.sqrt(c))


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_moduli_scaling_direct(cfun):
    """μ1 = μ2 = 1e-16 (and 1e16) on the disk with MUMPS: u unchanged, λ, η², the energy
    error² scaled by c. MUMPS's default scaling (ICNTL(8) = 77) is not invariant under the
    1/μ of the λ column: at c = 1e-16 exact Newton ended at a relative residual of ~1e-12
    with η_alg at ~0.9 η (krylov notes)."""
    problem = _scaled(scenes.disk(h=0.1), moduli=True)
    options = {"cfun": cfun, "newton": "exact", "solver": "direct"}
    ref = solve(problem, **options)
    for c in (1e-16, 1e16):
        run = solve(_scaled(problem, c, moduli=True), **options)
        _assert_same_run(ref, run, lambda u1, u2, lam: (u1, u2, lam / c),
                         lambda name: c if name in QUADRATIC else np.sqrt(c), np.sqrt(c),
                         direct=True)


@pytest.mark.parametrize("cfun, newton, solver", [("min", "adaptive", "amg"),
                                                  ("fb", "exact", "direct")])
def test_domain_scaling(cfun, newton, solver):
    """The square of side L = 1e-6 and 1e6 (a mesh in other units) with the same loads and g
    times L²: u scales by L², λ is unchanged, η's parts scale by L² (the energy norm of u:
    ∇u by L, the area by L²; η_C, η_lin2 by L⁴). κ carries the length unit ℓ² (ℓ = L here,
    `system.length_unit`), so C(a, κλ) and every weighted row scale by L² and the run is the
    same, counts included. With κ without ℓ² both runs here fail at L = 1e-6 (and with
    f1 = -1 and J = 2 every method diverged at its second Newton step, relative residual
    1.2e13). On T_0 only: the refined meshes of the squares of side 1e-3 and 1e6 came out
    with their vertices numbered otherwise than at side 1, so their solver paths differ."""
    from membranes.fem.meshes import structured_square
    options = {"cfun": cfun, "newton": newton, "solver": solver}

    def run(L):
        mesh = structured_square(8, 8)
        mesh.geometry.x[:, :2] *= L
        return solve(scenes.user(mesh=mesh, f1=f"-1 + 0.5 * y / {L!r}", f2="1",
                                 g=0.05 * L * L), **options)
    ref = run(1.0)
    assert ref.converged and ref.newton_iterations >= 3        # (a contact set to find)
    for L in (1e-6, 1e6):
        _assert_same_run(ref, run(L), lambda u1, u2, lam: (u1 / L ** 2, u2 / L ** 2, lam),
                         lambda name: L ** 4 if name in QUADRATIC else L ** 2, L ** 2,
                         direct=solver == "direct")


def test_a_large_domain_until_its_pressures_underflow():
    """A mesh scaled by L with loads by 1/L² has the same solution (u unchanged, λ by 1/L²)
    and the same η. At L = 1e50 (pressures 1e-100) the run is that of L = 1; at L = 1e100
    the pressures 1e-200 square to 0 in η_osc, η_lin2, η_lin3, with forces μ u of 1: before
    the pressures' check (`checks.check_force_scale`) adaptive Newton stopped at an iterate
    with negative pressures (complementarity violation 1.0) whose η was 0.954 of the energy
    error on a rotated square (probe, 2026-12-03). Now ValueError."""
    from membranes.fem.meshes import structured_square

    def run(L):
        mesh = structured_square(8, 8)
        mesh.geometry.x[:, :2] *= L
        return solve(scenes.user(mesh=mesh, f1=repr(-1.0 / L ** 2), f2=repr(0.5 / L ** 2)))
    ref, big = run(1.0), run(1e50)
    assert ref.converged and big.converged
    assert big.newton_iterations == ref.newton_iterations
    # the same run to round-off: η's parts are computed from scaled quantities (ε · a few)
    assert big.estimates["eta"] == pytest.approx(ref.estimates["eta"], rel=1e-12)
    with pytest.raises(ValueError, match="forces and pressures of size .* = 1e-200"):
        run(1e100)


def test_moduli_and_data_scaling_until_the_forces_underflow():
    """Moduli by 1e-20 and data by 1e-100 on the radial scene, adaptive: forces μ u of
    1e-120, and the run of c = 1 scaled (u by 1e-100, λ by 1e-120, η and the energy error by
    1e-110, η_C and η_lin2 by 1e-220). Moduli by 1e-40 and data by 1e-130: forces of 1e-170,
    whose squares in the estimators underflow (η_F read 0 and η fell to 0.13 times the
    energy error, in a run said converged with a guaranteed bound): ValueError."""
    problem = scenes.radial(h=0.1, rho=0.5)
    options = {"cfun": "min", "newton": "adaptive", "solver": "amg"}
    ref = solve(problem, **options)
    cm, cd = 1e-20, 1e-100
    run = solve(_scaled(_scaled(problem, cm, moduli=True), cd), **options)
    _assert_same_run(ref, run, lambda u1, u2, lam: (u1 / cd, u2 / cd, lam / (cm * cd)),
                     lambda name: cm * cd ** 2 if name in QUADRATIC else np.sqrt(cm) * cd,
                     np.sqrt(cm) * cd)
    with pytest.raises(ValueError, match="the estimators underflow double precision"):
        solve(_scaled(_scaled(problem, 1e-40, moduli=True), 1e-130), **options)


def test_mirror():
    """The square scene (μ1 = 1 ≠ μ2 = 2) with the membranes' roles swapped, exact Newton
    on the eliminated system: (g - u2, g - u1, λ), the same η parts and energy error, the
    same Newton steps (the linear solves, on other unknowns, may take other Krylov paths)."""
    p = scenes.square(h=0.1)
    f1, f2, ex, g = as_builder(p.f1), as_builder(p.f2), p.exact, p.g
    mirror = replace(p, mu1=p.mu2, mu2=p.mu1, f1=lambda x: -f2(x), f2=lambda x: -f1(x),
                     exact=ExactSolution(lambda x: g - ex.u2(x), lambda x: g - ex.u1(x),
                                         ex.lam))
    ref, run = (solve(q, newton="exact", solver="amg", cfun="min") for q in (p, mirror))
    run.linear_iterations = ref.linear_iterations          # (not an invariant here)
    _assert_same_run(ref, run, lambda u1, u2, lam: (g - u2, g - u1, lam), lambda name: 1.0,
                     1.0)


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_common_displacement(cfun):
    """Loads (f1 + μ1 φ, f2 + μ2 φ): λ and the gap unchanged, u1 and u2 moved by the same
    function v (the discrete solution of -Δv = φ, v = 0 on ∂Ω), on the square (μ1 ≠ μ2)."""
    p = scenes.square(h=0.1)
    f1, f2 = as_builder(p.f1), as_builder(p.f2)

    def phi(x):
        return 3.0 * ufl.sin(2 * ufl.pi * x[0]) + 1.0
    moved = replace(p, f1=lambda x: f1(x) + p.mu1 * phi(x),
                    f2=lambda x: f2(x) + p.mu2 * phi(x), exact=None)
    ref, run = (_parts(solve(q, newton="exact", solver="direct", cfun=cfun,
                             estimators=False)) for q in (p, moved))
    v1, v2 = run[0] - ref[0], run[1] - ref[1]
    assert np.abs(v1).max() > 0.1                           # the membranes did move
    assert _deviation(v2, v1) <= TOL
    assert _deviation(run[2], ref[2]) <= TOL

