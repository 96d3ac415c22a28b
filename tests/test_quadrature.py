"""Data that jump across a circle cutting cells are integrated accurately (theory §7, §9)."""

import math

import numpy as np

from membranes.fem.meshes import mesh_size
from membranes.fem.quadrature import composite_rule, cut_cells

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
    from membranes.fem.discretisation import assemble_vector, discretise
    d = discretise(problem)
    g = problem.g
    area = d.D.sum()              # PETSc Vec sums are global
    exact = -10 * g * math.pi / 2 - 8 * g * (area - math.pi / 2)
    delta = mesh_size(problem.mesh) / 16
    bound = 2 * g * 2 * delta * math.pi * math.sqrt(2)
    assert abs(d.F1.sum() - exact) <= bound
    assert len(cut_cells(problem.mesh, problem.interface)) > 20
    # without the composite rule on cut cells the error is larger (a sanity check that the
    # composite rule is what makes the difference)
    import ufl

    from membranes.fem.quadrature import DATA_DEGREE
    x = ufl.SpatialCoordinate(problem.mesh)
    v = ufl.TestFunction(d.V)
    plain = assemble_vector(problem.f1(x) * v * ufl.dx(
        domain=problem.mesh, metadata={"quadrature_degree": DATA_DEGREE})).sum()
    assert abs(d.F1.sum() - exact) < abs(plain - exact)
    assert np.isfinite(d.F2.array).all()
