"""The guaranteed bound on user data, where no exact solution is known (theory §7), checked
against an overkill reference.

|||u - u_h||| ≤ η_h holds for every certified iterate u_h on T_J, and |||u - u_ref||| ≤ η_ref
for the reference u_ref, the discrete solution on T_{J+2} of the same hierarchy (two more
uniform refinements of a polygon: P1(T_J) ⊂ P1(T_{J+2}), and the hierarchy's P1 prolongations
are the inclusion). The energy norm |||v|||² = μ1 ‖∇v1‖² + μ2 ‖∇v2‖² of §1 (u only, no λ) is a
norm, so by the triangle inequality

    |||u_ref - u_h||| ≤ |||u - u_h||| + |||u - u_ref||| ≤ η_h + η_ref,

which needs no u. |||u_ref - u_h||| is computed exactly for P1 functions on T_{J+2}, as
dᵀ (μ S) d with S the stiffness matrix of T_{J+2} and d = P u_h - u_ref (zero on ∂Ω).

Tolerance: the inequality is exact; the three numbers are square roots of sums of about 10⁴
terms in double precision (the flux term formed before squaring, §7; dᵀ S d for a d that
vanishes on ∂Ω), so each carries a relative round-off below 10⁴ ε ≈ 2·10⁻¹²; RTOL = 10⁻⁹
covers it with room, and any genuine failure (a bound that is not one) is many orders above.

Cases: the demo's L-shaped domain (re-entrant corner) with its data, a slit domain (gmsh's
Crack plugin duplicates the slit's nodes: a genuine crack, interior angle 2π) with a load that
jumps across a line and a circle that cut cells, and the L shape with μ1/μ2 = 10⁴.
"""

from dataclasses import replace

import numpy as np
import pytest

from membranes import scenes, solve

J = 1                 # T_J solved; the reference on T_{J+2}
RTOL = 1e-9

JUMP = "-1 - 0.5*max(0, min(1, (x - 0.3)*1e12))"      # jumps across x = 0.3
DISK = "1 + max(0, min(1, (0.3 - x*x - (y - 0.4)**2)*1e12))"   # jumps across a circle


def l_shape(path, h):
    """(-1, 1)² without (0, 1) × (-1, 0), as in demos/demo_user_mesh.py."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        square = gmsh.model.occ.addRectangle(-1, -1, 0, 2, 2)
        quarter = gmsh.model.occ.addRectangle(0, -1, 0, 1, 1)
        gmsh.model.occ.cut([(2, square)], [(2, quarter)])
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(2, [t for _, t in gmsh.model.getEntities(2)], 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", h)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return str(path)


def slit(path, h):
    """(-1, 1)² cut along [0, 1] × {0}: the slit's nodes duplicated by gmsh's Crack plugin, so
    that its two sides are boundary of Ω."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        square = gmsh.model.occ.addRectangle(-1, -1, 0, 2, 2)
        line = gmsh.model.occ.addLine(gmsh.model.occ.addPoint(0, 0, 0),
                                      gmsh.model.occ.addPoint(1, 0, 0))
        gmsh.model.occ.fragment([(2, square)], [(1, line)])
        gmsh.model.occ.synchronize()
        crack = [t for _, t in gmsh.model.getEntities(1)
                 if np.allclose(gmsh.model.occ.getCenterOfMass(1, t), (0.5, 0, 0))]
        gmsh.model.addPhysicalGroup(1, crack, 101)
        gmsh.model.addPhysicalGroup(2, [t for _, t in gmsh.model.getEntities(2)], 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", h)
        gmsh.model.mesh.generate(2)
        gmsh.plugin.setNumber("Crack", "Dimension", 1)
        gmsh.plugin.setNumber("Crack", "PhysicalGroup", 101)
        gmsh.plugin.run("Crack")
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return str(path)


CASES = {
    "l_shape": (l_shape, dict(mu1=1.0, mu2=3.0, g=0.02, f1="-0.15 - 0.1*y",
                              f2="0.2 + 0.1*sin(2*pi*x)*cos(pi*y)")),
    "slit_jumps": (slit, dict(mu1=1.0, mu2=1.0, g=0.05, f1=JUMP, f2=DISK)),
    "l_shape_stiff": (l_shape, dict(mu1=1e4, mu2=1.0, g=0.02, f1="-2000 - 500*y", f2="0.3")),
}


@pytest.fixture(scope="module")
def references(tmp_path_factory):
    """Per case: (problem on T_0 … T_{J+2}, its reference solve on T_{J+2}), built once."""
    cache = {}

    def get(name):
        if name not in cache:
            mesher, data = CASES[name]
            msh = mesher(tmp_path_factory.mktemp(name) / f"{name}.msh", 0.25)
            problem = scenes.user(mesh=msh, levels=J + 2, **data)
            ref = solve(problem, newton="exact", solver="direct")
            assert ref.converged and ref.estimates["bound"], ref.reason
            cache[name] = (problem, ref)
        return cache[name]
    return get


def distance(problem, ref, sol):
    """|||u_ref - u_h||| on T_{J+2}, u_h prolonged from T_J by the hierarchy's P1 maps."""
    P = problem.hierarchy.prolongations[J:J + 2]
    n, m = sol.disc.n, ref.disc.n
    S = ref.disc.S
    total = 0.0
    for k, mu in enumerate((problem.mu1, problem.mu2)):
        v = P[0].createVecRight()
        v.array[:] = sol.X.array_r[k * n:(k + 1) * n]
        for Pj in P:
            w = Pj.createVecLeft()
            Pj.mult(v, w)
            v = w
        v.array[:] -= ref.X.array_r[k * m:(k + 1) * m]
        total += mu * v.dot(S * v)
    return float(np.sqrt(max(total, 0.0)))


@pytest.mark.parametrize("name,options", [
    ("l_shape", {}),
    ("l_shape", {"newton": "adaptive", "nested": False, "max_newton": 1}),
    ("l_shape", {"newton": "exact", "solver": "direct", "cfun": "fb"}),
    ("l_shape", {"newton": "inexact", "solver": "paper"}),
    ("slit_jumps", {"cfun": "fb", "alg_flux": "multilevel"}),
    ("slit_jumps", {"solver": "paper", "nested": False}),
    ("l_shape_stiff", {"cfun": "fb"}),
])
def test_bound_against_the_reference(references, name, options):
    problem, ref = references(name)
    coarse = replace(problem, hierarchy=problem.hierarchy.up_to(J))
    sol = solve(coarse, **options)
    assert sol.estimates is not None and sol.estimates["bound"]
    eta_h, eta_ref = sol.estimates["eta"], ref.estimates["eta"]
    err = distance(problem, ref, sol)
    assert err > 0.0
    assert eta_h + eta_ref >= err * (1.0 - RTOL), (eta_h, eta_ref, err)
    # the check has teeth: η_ref alone does not cover the distance, so η_h must do its part
    # (true of these cases: T_{J+2} has 16 times the cells of T_J)
    assert eta_ref < err
