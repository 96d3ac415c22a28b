"""Data that jump across a circle cutting cells are integrated accurately (DESIGN §7, §9)."""

import math

import numpy as np

from membranes.discretisation import composite_rule, cut_cells
from membranes.meshes import mesh_size

from .conftest import scene


def test_composite_rule_integrates_polynomials():
    pts, wts = composite_rule(4, 2)
    assert abs(wts.sum() - 0.5) < 1e-15
    # ∫_T x² y dx = 1/60 on the reference triangle; degree 3 > 2 so only the composite
    # refinement makes it close: error O((1/4)^3) of the piece size, checked loosely
    exact = 1.0 / 60.0
    assert abs((wts * pts[:, 0] ** 2 * pts[:, 1]).sum() - exact) < 1e-4
    pts, wts = composite_rule(3, 4)
    assert abs((wts * pts[:, 0] ** 2 * pts[:, 1]).sum() - exact) < 1e-15


def test_disk_load_integral_against_exact_areas():
    """Σ_a F1_a = ∫ f1 = -10g |{r ≤ 1/√2}| - 8g (|Ω_h| - π/2), Ω_h the polygon.

    The composite rule misplaces at most the area of the sub-triangles the circle crosses:
    a band of width 2δ (δ = h/16, the sub-triangle diameter) along a circle of length π√2, so
    |error| ≤ jump · 2δ · π√2 with jump = 2g.
    """
    problem = scene("disk", 0.1)
    from membranes.discretisation import discretise
    d = discretise(problem)
    g = problem.g
    area = d.D.sum()
    exact = -10 * g * math.pi / 2 - 8 * g * (area - math.pi / 2)
    delta = mesh_size(problem.mesh) / 16
    bound = 2 * g * 2 * delta * math.pi * math.sqrt(2)
    assert abs(d.F1.sum() - exact) <= bound
    assert len(cut_cells(problem.mesh, problem.interface)) > 20
    # without the composite rule on cut cells the error is larger (a sanity check that the
    # composite rule is what makes the difference)
    import ufl
    from membranes.discretisation import assemble_vector_array, DATA_DEGREE
    x = ufl.SpatialCoordinate(problem.mesh)
    v = ufl.TestFunction(d.V)
    plain = assemble_vector_array(problem.f1(x) * v * ufl.dx(
        domain=problem.mesh, metadata={"quadrature_degree": DATA_DEGREE})).sum()
    assert abs(d.F1.sum() - exact) < abs(plain - exact)
    assert np.isfinite(d.F2).all()


def test_cached_forms_are_dolfinx_forms_and_tell_rules_apart():
    """`form` (one kernel per form signature and process) assembles what dolfinx.fem.form
    assembles, on every level of a hierarchy; its cheap signature (`form_signature`, the
    metadata hashed from their bytes) separates and identifies forms as UFL's signature does,
    a custom rule's points included."""
    import ufl
    from dolfinx import fem
    from membranes.discretisation import (assemble_vector_array, composite_rule,
                                          data_measures, form, form_signature, load, over)
    problem = scene("disk", 0.3, levels=1)
    forms = []
    for mesh in problem.hierarchy.meshes:
        V = fem.FunctionSpace(mesh, ("Lagrange", 1))
        v = ufl.TestFunction(V)
        f2 = load(problem.f2, mesh)
        L = over(data_measures(mesh, problem.interface), lambda dx: f2 * v * dx)
        mine, theirs = assemble_vector_array(form(L)), assemble_vector_array(fem.form(L))
        # the same kernel: equal to round-off (in fact bit for bit)
        assert np.abs(mine - theirs).max() <= 1e-15 * np.abs(theirs).max()
        pts, wts = composite_rule(8, 2)                       # another custom rule
        other = {"quadrature_rule": "custom", "quadrature_degree": 6,
                 "quadrature_points": pts.tolist(), "quadrature_weights": wts.tolist()}
        dx = ufl.Measure("dx", domain=mesh, subdomain_data=data_measures(
            mesh, problem.interface)[1].subdomain_data())
        forms += [L, f2 * v * dx(1, metadata=other), v * ufl.dx, 2.0 * v * ufl.dx,
                  ufl.inner(ufl.grad(v), ufl.grad(ufl.TrialFunction(V))) * ufl.dx]
    for a in forms:
        for b in forms:
            assert (form_signature(a) == form_signature(b)) == (a.signature() == b.signature())
    assert len({form_signature(a) for a in forms}) == 5       # each form on both levels
