"""Data that jump across a circle cutting cells are integrated accurately (theory §7, §9)."""

import math

import numpy as np
import pytest

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


def _crossed_by_circle(mesh, rho):
    """The local cells the circle r = ρ crosses, exactly: min_T r < ρ < max_T r, with
    max_T r the largest |v| of T's vertices and min_T r = dist(0, T): 0 if the origin lies in
    T (three edge orientations of one sign), else the least distance from 0 to an edge."""
    x = mesh.geometry.x[:, :2]
    ncells = mesh.topology.index_map(2).size_local
    v = x[mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells]]           # (cells, 3, 2)
    far = np.linalg.norm(v, axis=2).max(axis=1)
    near = np.full(ncells, np.inf)
    turns = []
    for i in range(3):
        a, e = v[:, i], v[:, (i + 1) % 3] - v[:, i]
        t = np.clip(-(a * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
        near = np.minimum(near, np.linalg.norm(a + t[:, None] * e, axis=1))
        turns.append(np.sign(e[:, 0] * -a[:, 1] - e[:, 1] * -a[:, 0]))
    near[(turns[0] == turns[1]) & (turns[1] == turns[2])] = 0.0
    return set(np.flatnonzero((near < rho) & (rho < far)).tolist())


@pytest.mark.parametrize("h, rho", [(0.3, 0.1), (0.2, 0.08)])
def test_cut_cells_are_the_cells_the_circle_crosses(h, rho):
    """A circle r = ρ that encloses no vertex (so no cell has vertices on both sides):
    cut_cells finds exactly the cells it crosses, by the exact geometry. ρ ≥ h/4 is what its
    grid of 4 intervals per edge promises to resolve (its notes). Found ⊆ truth always holds
    (the samples lie in the cell: a sign change among them is a crossing), so the test is
    found ⊇ truth, here equality. That holds on these meshes, not in general: a circle that
    clips a cell within a sample spacing of a vertex or an edge is missed. Here each crossed
    cell has min(ρ - dist(0, T), max |v| - ρ) ≥ 0.1 h (measured 0.15 h and 0.10 h), so the
    equality is no matter of round-off. Sampling the vertices only finds none of the 3
    crossed cells, and their loads lose the composite rule (F2 changes by 4e-3 relative at
    h = 0.3)."""
    problem = scene("radial", h, rho=rho)
    truth = _crossed_by_circle(problem.mesh, rho)
    assert truth                                       # (the circle crosses cells)
    assert set(cut_cells(problem.mesh, problem.interface).tolist()) == truth


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


def test_energy_error_integrates_cut_cells_with_the_composite_rule():
    """The exact solution of the disk has a kinked u2 across r = 1/√2, so the energy error
    needs the composite rule on the cut cells as the data do (energy_error's notes): at the
    discrete solution it equals an independent sum — the same integrand by degree 6 on the
    other cells and a finer composite rule (32² pieces) on the cut ones — to well below what
    a smooth rule on the cut cells is off by. The composite rule's error falls like 1 / n (the
    band of sub-triangles the circle crosses): 16² pieces leave about twice the 32² rule's,
    measured 5e-7 of the error apart at h = 0.2, against 1e-4 for the smooth rule."""
    import ufl
    from dolfinx import fem
    from mpi4py import MPI
    from petsc4py import PETSc

    from membranes.estimation.energy_error import EnergyError
    from membranes.fem.quadrature import DATA_DEGREE
    from membranes.forms.estimators import energy_squared

    from .conftest import solved
    sol = solved("disk", 0.2)
    d = sol.disc
    mesh, exact = d.mesh, d.problem.exact
    x = ufl.SpatialCoordinate(mesh)
    u1h, u2h, _ = d.functions(sol.X)
    mu1, mu2 = (fem.Constant(mesh, PETSc.ScalarType(m)) for m in (d.mu1, d.mu2))
    e1, e2 = exact.u1(x) - u1h, exact.u2(x) - u2h
    one = fem.Constant(mesh, PETSc.ScalarType(1.0))
    smooth, cut = d.dx_data
    assert d.comm.allreduce(len(cut_cells(mesh, d.problem.interface)), op=MPI.SUM) > 10

    def total(dx_cut):
        form = (energy_squared(mu1, mu2, e1, e2, one, smooth)
                + energy_squared(mu1, mu2, e1, e2, one, dx_cut))
        return math.sqrt(d.comm.allreduce(fem.assemble_scalar(fem.form(form)), op=MPI.SUM))

    pts, wts = composite_rule(32, 4)
    fine = total(cut.reconstruct(metadata={
        "quadrature_rule": "custom", "quadrature_degree": DATA_DEGREE,
        "quadrature_points": pts.tolist(), "quadrature_weights": wts.tolist()}))
    plain = total(cut.reconstruct(metadata={"quadrature_degree": DATA_DEGREE}))
    got = EnergyError(d)(sol.X)
    assert abs(plain / fine - 1) > 2e-5              # the smooth rule is off …
    assert abs(got / fine - 1) < 5e-6                # … the product's is not


def test_cells_with_vertices_on_both_sides_are_cut_and_tagged():
    """On the disk scene's T_0 (h = 0.1) the circle r = 1/√2 passes between vertices: every
    cell with vertices on both sides is cut whichever vertex is the odd one out (a sampling
    that skipped two of the vertices and their edge missed 16 of 98), and the data measure's
    composite rule is on exactly the cut cells (tag 1). Both exact: sets of cells."""
    from membranes.fem.discretisation import discretise
    problem = scene("disk", 0.1)
    mesh = problem.mesh
    n = mesh.topology.index_map(2).size_local
    phi = problem.interface(mesh.geometry.x[:, :2].T)[
        mesh.geometry.dofmap.array.reshape(-1, 3)[:n]]
    split = set(np.flatnonzero((phi.min(axis=1) < 0) & (phi.max(axis=1) > 0)).tolist())
    cut = set(cut_cells(mesh, problem.interface).tolist())
    assert len(split) > 50 and split <= cut
    tags = discretise(problem).dx_data[1].subdomain_data()
    assert set(tags.find(1).tolist()) == cut


def test_a_constant_load_is_its_value():
    """A constant load enters as a dolfinx Constant of its value, sign included, and the
    loads' sum is f |Ω_h| (round-off of a sum of about 500 terms: 1e-13 relative)."""
    from membranes import scenes
    from membranes.fem.discretisation import discretise
    from membranes.fem.meshes import triangle_areas
    from membranes.fem.quadrature import load
    problem = scenes.user(f1="-1.5", f2="0", h=0.2, domain="square")
    mesh = problem.mesh
    assert float(load(-1.5, mesh).value) == -1.5
    disc = discretise(problem)
    n = mesh.topology.index_map(2).size_local
    area = triangle_areas(mesh.geometry.x[:, :2][mesh.geometry.dofmap.array.reshape(-1, 3)[:n]])
    assert disc.F1.sum() == pytest.approx(-1.5 * area.sum(), rel=1e-13)
