"""The discretisation's boundary vertices and stiffness matrices (DESIGN §2)."""

import numpy as np
import pytest

from membranes import meshes
from membranes.discretisation import (SHIPMENT, boundary_dofs, completed, discretise,
                                      discretise_in_parts)

from .conftest import scene


def _exterior_facet_dofs(V):
    """dolfinx's own: the dofs on the exterior facets of V's mesh."""
    from dolfinx import fem, mesh as dmesh
    V.mesh.topology.create_connectivity(1, 2)
    return fem.locate_dofs_topological(V, 1, dmesh.exterior_facet_indices(V.mesh.topology))


@pytest.mark.parametrize("mesh_of", [
    lambda: scene("disk", 0.3, levels=2).mesh,                      # refined hierarchy
    lambda: scene("square", 0.25).mesh,
    lambda: meshes.structured_square(7, 3, grading=2.0),             # boundary corner cells
])
def test_boundary_vertices_are_those_of_exterior_facets(mesh_of):
    """The count of cells per edge (one: a boundary edge) finds dolfinx's exterior-facet dofs,
    the same set in the same (increasing) order."""
    from dolfinx import fem
    mesh = mesh_of()
    V = fem.FunctionSpace(mesh, ("Lagrange", 1))
    ours = boundary_dofs(V)
    assert ours.dtype == np.int32
    assert np.array_equal(ours, _exterior_facet_dofs(V))


def test_boundary_dofs_leave_the_mesh_edges_alone():
    """The boundary count computes no mesh entities (process 0 of a multi-process run sets
    up no estimators and never needs them); the flux equilibration creates the edge-to-cell
    connectivity where it reads dolfinx's exterior facets, and its exterior edges are then
    those of the boundary vertices."""
    from dolfinx import fem
    from membranes.equilibration import PatchSpace
    mesh = meshes.unit_disk(0.4)
    V = fem.FunctionSpace(mesh, ("Lagrange", 1))
    boundary = boundary_dofs(V)
    assert mesh.topology.connectivity(1, 2) is None
    space = PatchSpace(V)
    assert mesh.topology.connectivity(1, 2) is not None
    cells = space.geo.cells
    on = np.zeros(len(V.tabulate_dof_coordinates()), dtype=bool)
    on[boundary] = True
    # edge e of a cell is opposite its vertex e: both other vertices are boundary vertices
    for e in range(3):
        ends = np.delete(cells, e, axis=1)
        assert np.all(on[ends[space.exterior_edge[:, e]]])
    # a closed polygon: as many boundary edges as boundary vertices
    assert space.exterior_edge.sum() == len(boundary)


def test_membrane_stiffness_is_mu_times_s():
    """S_α = μ_α S entry for entry (μ1 ≠ μ2: two matrices on S's index arrays)."""
    import ufl
    from forms.membrane import membrane_bilinear
    from membranes.discretisation import assemble_matrix_csr
    d = discretise(scene("radial", 0.3, mu1=2.5, mu2=0.75))
    S = assemble_matrix_csr(membrane_bilinear(1.0, ufl.TrialFunction(d.V),
                                              ufl.TestFunction(d.V)))
    assert d.S2.shape == d.S1.shape == (d.n, d.n)
    assert np.array_equal(d.S1.data, 2.5 * S.data)
    assert np.array_equal(d.S2.data, 0.75 * S.data)
    assert np.array_equal(d.S2.indices, d.S1.indices)
    # a constant has zero energy: the rows of S sum to zero (round-off of the entries)
    assert np.abs(d.S1 @ np.ones(d.n)).max() < 1e-12 * np.abs(d.S1.data).max()


def test_estimator_process_discretisation_takes_process_0s_arrays():
    """Without stiffness (the estimator processes, membranes.pipeline), D, F1, F2 and the
    boundary given by process 0's discretisation (Link.ship) are those it would make itself,
    bit for bit (the same code on the same mesh), and they are taken, not made again: an
    array marked as shipped comes back as that very array. Where they have not come after
    the space and the data measures, the parts yield SHIPMENT and take them when resumed;
    resumed without them, they make all four."""
    problem = scene("disk", 0.3, levels=1)
    full, own = discretise(problem), discretise(problem, stiffness=False)
    for name in ("D", "F1", "F2", "boundary"):
        assert np.array_equal(getattr(full, name), getattr(own, name))
    marked = np.full(full.n, 7.0)
    given = (full.D, full.F1, marked, full.boundary)
    shipped = discretise(problem, stiffness=False, given=lambda: given)
    assert shipped.F2 is not None and np.array_equal(shipped.F2, marked)
    assert np.array_equal(shipped.F1, own.F1) and np.array_equal(shipped.D, own.D)
    asked = []

    def late():      # nothing at the first question
        asked.append(1)
        return given if len(asked) > 1 else None
    parts = discretise_in_parts(problem, stiffness=False, given=late)
    yielded = [next(parts), next(parts)]
    assert yielded == [None, SHIPMENT] and len(asked) == 1
    half = completed(parts)
    assert len(asked) == 2 and np.array_equal(half.F2, marked)
    assert np.shares_memory(half.D, full.D)          # taken, not made
    asked.clear()
    never = discretise(problem, stiffness=False, given=lambda: asked.append(1))
    assert len(asked) == 2
    for name in ("D", "F1", "F2", "boundary"):
        assert np.array_equal(getattr(never, name), getattr(own, name))
    # with stiffness (process 0) nothing is asked
    assert np.array_equal(discretise(problem, given=late).F2, full.F2) and len(asked) == 2


@pytest.mark.parametrize("mesh_of", [
    lambda: scene("disk", 0.3, levels=2).mesh,                      # refined hierarchy
    lambda: scene("square", 0.25).mesh,
    lambda: meshes.structured_square(7, 3, grading=2.0),             # right angles: zeros
])
def test_compiled_assembly_is_dolfinx_assembly(mesh_of):
    """The compiled passes give dolfinx's assembly of S = (∇ψ_b, ∇ψ_a) and D = (ψ_a, 1) bit
    for bit (the same sparsity, stored zeros included, the same arithmetic, the same order of
    the cells' sums) and dolfinx's exterior-facet dofs."""
    import ufl
    from dolfinx import fem
    from forms.membrane import contact_weight, membrane_bilinear
    from membranes.discretisation import (assemble_matrix_csr, assemble_vector_array,
                                          p1_assembly)
    V = fem.FunctionSpace(mesh_of(), ("Lagrange", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    S, D, boundary = p1_assembly(V)
    reference = assemble_matrix_csr(membrane_bilinear(1.0, u, v))
    for name in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(S, name), getattr(reference, name)), name
    assert S.shape == reference.shape
    assert np.array_equal(D, assemble_vector_array(contact_weight(v)))
    assert boundary.dtype == np.int32 and np.array_equal(boundary, _exterior_facet_dofs(V))


def test_plain_pages_inside_solve_and_restored(monkeypatch):
    """Inside `solve` numpy gives large arrays no huge-page advice (discretisation.plain_pages);
    numpy's own setting, either way, is back afterwards, also when the run raises."""
    from numpy.core import multiarray
    from membranes import driver, solve
    seen = []
    real = driver._solve_nested

    def spy(*args, **kwargs):
        seen.append(multiarray._get_madvise_hugepage())
        return real(*args, **kwargs)
    monkeypatch.setattr(driver, "_solve_nested", spy)
    before = multiarray._get_madvise_hugepage()
    try:
        for setting in (True, False):
            multiarray._set_madvise_hugepage(setting)
            solve(scene("disk", 0.4, levels=1), newton="adaptive", cfun="min",
                  system="eliminated")
            assert multiarray._get_madvise_hugepage() is setting
            with pytest.raises(ValueError):
                solve(scene("disk", 0.4), newton="nonsense")
            assert multiarray._get_madvise_hugepage() is setting
        assert seen == [False, False]
    finally:
        multiarray._set_madvise_hugepage(before)


def test_a_run_does_not_depend_on_the_blas_threads_around_it():
    """`solve` runs with BLAS on one thread (discretisation.as_one_run): the same iterate bit
    for bit whether the caller allows OpenBLAS one thread or two. Without it the two differ
    (5.8e-14 relative on this run, measured): GMRES's dot products and norms on vectors of
    more than 10⁴ entries (here 2N ≈ 1.4e4 on T_3) are split among OpenBLAS's threads, which
    sums in another order. On a machine of one core the test cannot tell the difference."""
    from threadpoolctl import threadpool_limits
    from membranes import solve
    problem = scene("disk", 0.2, levels=3)
    X = []
    for threads in (2, 1):
        with threadpool_limits(limits=threads, user_api="blas"):
            X.append(solve(problem, newton="adaptive", cfun="min", system="eliminated",
                           petsc_options={"pc_type": "vertex_amg"}).X)
    assert np.array_equal(X[0], X[1])
