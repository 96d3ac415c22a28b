"""Meshes and the refinement hierarchy (§6, §9)."""

import json

import numpy as np
import pytest
from mpi4py import MPI

from membranes.fem.hierarchy import build_hierarchy
from membranes.fem.mesh_files import read_msh
from membranes.fem.meshes import mesh_size, unit_disk, unit_square

from .conftest import aspect_ratios, mpirun, write_msh


def _boundary_edges(m):
    """The end points (edges, 2, 2) of the owned facets on ∂Ω."""
    from dolfinx import mesh as dm
    tdim = m.topology.dim
    m.topology.create_connectivity(tdim - 1, tdim)
    m.topology.create_connectivity(tdim - 1, 0)
    facets = dm.exterior_facet_indices(m.topology)
    facets = facets[facets < m.topology.index_map(tdim - 1).size_local]
    f2v = m.topology.connectivity(tdim - 1, 0)
    c2v = m.topology.connectivity(tdim, 0).array.reshape(-1, 3)
    node = np.empty(c2v.max(initial=-1) + 1, dtype=np.int64)      # vertex -> geometry node
    node[c2v.ravel()] = m.geometry.dofmap.array.reshape(-1, 3).ravel()
    ends = np.array([f2v.links(f) for f in facets], dtype=np.int64).reshape(-1, 2)
    return m.geometry.x[node[ends], :2]


def test_disk_and_square_sizes():
    """The cells tile the square exactly, and the disk's inscribed polygon: every boundary
    vertex on the unit circle, and the polygon's area plus the circular segments cut off by
    its boundary edges, Σ (θ_e - sin θ_e)/2 with θ_e = 2 arcsin(|e|/2), is π. Both to the
    round-off of summing ~1e3 cell areas (ε each: 1e-13)."""
    comm = MPI.COMM_WORLD
    for make, area in ((unit_disk, np.pi), (unit_square, 1.0)):
        m = make(0.1)
        assert m.geometry.dim == 2
        assert 0.05 < mesh_size(m) <= 0.16
        x = m.geometry.x[:, :2]
        c = m.geometry.dofmap.array.reshape(-1, 3)[:m.topology.index_map(2).size_local]
        e1, e2 = x[c[:, 1]] - x[c[:, 0]], x[c[:, 2]] - x[c[:, 0]]
        polygon = comm.allreduce(0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum())
        edges = _boundary_edges(m)
        if make is unit_square:
            assert abs(polygon - area) <= 1e-13
            side = np.minimum(np.abs(edges), np.abs(edges - 1.0)).min(axis=2)
            assert comm.allreduce(side.max(initial=0.0), op=MPI.MAX) <= 1e-15   # ends on ∂Ω
            continue
        r = np.hypot(edges[..., 0], edges[..., 1])
        assert comm.allreduce(np.abs(r - 1.0).max(initial=0.0), op=MPI.MAX) <= 1e-15
        theta = 2 * np.arcsin(np.linalg.norm(edges[:, 1] - edges[:, 0], axis=1) / 2)
        segments = comm.allreduce(0.5 * (theta - np.sin(theta)).sum())
        assert abs(polygon + segments - area) <= 1e-13
        # the inscribed polygon misses O(h²) of the disk: Σ θ³/12 ≤ 2π θ_max²/12
        assert 0.0 < area - polygon <= np.pi / 6 * comm.allreduce(theta.max(), op=MPI.MAX) ** 2


def test_hierarchy_parent_maps():
    h = build_hierarchy(unit_disk(0.3), 2)
    assert h.levels == 2
    for j in (1, 2):
        coarse, fine = h.meshes[j - 1], h.meshes[j]
        nc, nf = (m.topology.index_map(2).size_local for m in (coarse, fine))
        assert nf == 4 * nc
        parents = h.parent_cells[j - 1]
        assert parents.shape == (nf,)
        assert np.all(np.bincount(parents, minlength=nc) == 4)
        # every fine cell's centroid lies in its parent
        xf, xc = fine.geometry.x[:, :2], coarse.geometry.x[:, :2]
        cf = fine.geometry.dofmap.array.reshape(-1, 3)
        cc = coarse.geometry.dofmap.array.reshape(-1, 3)
        centroid = xf[cf].mean(axis=1)
        p = xc[cc[parents]]
        v0, v1, v2 = p[:, 0], p[:, 1], p[:, 2]
        m = np.stack([v1 - v0, v2 - v0], axis=2)
        lam = np.linalg.solve(m, (centroid - v0)[..., None])[..., 0]
        assert np.all(lam >= -1e-12) and np.all(lam.sum(axis=1) <= 1 + 1e-12)
    assert mesh_size(h.finest) == pytest.approx(mesh_size(h.meshes[0]) / 4, rel=0.3)


def test_read_msh(tmp_path):
    m = read_msh(write_msh(tmp_path / "rect.msh", "triangles"))
    assert m.geometry.dim == 2 and m.topology.index_map(2).size_local > 50
    assert np.isclose(m.geometry.x[:, 0].max(), 2.0)


def test_prolongation_interpolates_p1():
    """P_j of a nested hierarchy (no boundary projection) maps the coarse interpolant of a
    linear function to the fine one (P1 ⊂ P1, exactly: weights 1 and 1/2), and every row
    holds one entry 1 or two entries 1/2 (plaza: coarse vertices and edge midpoints)."""
    from dolfinx import fem
    h = build_hierarchy(unit_disk(0.3), 2)
    for j in (1, 2):
        Vc, Vf = (fem.FunctionSpace(h.meshes[i], ("Lagrange", 1)) for i in (j - 1, j))
        P = h.prolongations[j - 1]
        uc, uf = fem.Function(Vc), fem.Function(Vf)
        for u in (uc, uf):
            u.interpolate(lambda x: 0.3 + 2.0 * x[0] - 0.7 * x[1])
        n = Vf.dofmap.index_map.size_local
        out = P.createVecLeft()
        xc = P.createVecRight()
        xc.array[:] = uc.x.array[:Vc.dofmap.index_map.size_local]
        P.mult(xc, out)
        assert np.abs(out.array - uf.x.array[:n]).max() <= 1e-14
        ia, ja, a = P.getValuesCSR()
        rows = np.diff(ia)
        assert set(rows.tolist()) <= {1, 2}
        assert np.all(np.where(np.repeat(rows, rows) == 1, a == 1.0, a == 0.5))
        for v in (out, xc):
            v.destroy()


def linear(x):
    return 0.3 + 2.0 * x[0] - 0.7 * x[1]


def test_prolongations_are_made_at_first_use():
    """The hierarchy makes P_j only when they are read (a run on T_J alone never does), shares
    them with its `up_to` views, and where a projection moved the boundary vertices computes
    them from plaza's positions: the prolonged interpolant of a linear function is its value
    at the coarse vertices and edge midpoints, also at the moved vertices. (The projection
    here moves them by a third of the radius: far enough that their moved positions would
    round to other barycentric coordinates; the circle's moves them by about h²/8.)"""
    from dolfinx import fem
    h = build_hierarchy(unit_disk(0.5), 2, projection=lambda p: 1.3 * p)
    assert h.made == []
    P1 = h.up_to(1).prolongations[0]
    assert len(h.made) == 1 and h.prolongation(1) is P1 and len(h.made) == 1
    assert h.prolongations[0] is P1 and len(h.made) == 2
    for j in (0, 3):
        with pytest.raises(ValueError, match=f"no prolongation P_{j} in a hierarchy of 2"):
            h.prolongation(j)
    for j in (1, 2):
        Vc, Vf = (fem.FunctionSpace(h.meshes[i], ("Lagrange", 1)) for i in (j - 1, j))
        uc = fem.Function(Vc)
        uc.interpolate(linear)
        xc = h.prolongations[j - 1].createVecRight()
        xc.array[:] = uc.x.array[:Vc.dofmap.index_map.size_local]
        out = h.prolongations[j - 1].createVecLeft()
        h.prolongations[j - 1].mult(xc, out)
        # the fine vertices at plaza's positions (the moved ones put back)
        nodes, before = h.unmoved[j - 1]
        assert len(nodes) > 0
        x = h.meshes[j].geometry.x[:, :2].copy()
        x[nodes] = before
        gdofs = h.meshes[j].geometry.dofmap.array.reshape(-1, 3)
        vdofs = Vf.dofmap.list.array.reshape(-1, 3)
        at = np.empty(Vf.dofmap.index_map.size_local + Vf.dofmap.index_map.num_ghosts, int)
        at[vdofs.ravel()] = gdofs.ravel()
        n = Vf.dofmap.index_map.size_local
        assert np.abs(out.array - linear(x[at[:n]].T)).max() <= 1e-14
        for v in (out, xc):
            v.destroy()


@pytest.mark.parametrize("name", ["disk", "square", "radial", "user"])
def test_every_scene_reports_its_refinements(name):
    """A scene's `progress` gets one line per refinement, with the refined mesh's size."""
    from membranes import scenes
    lines = []
    problem = scenes.make(name, h=0.5, levels=2, progress=lines.append)
    sizes = [m.topology.index_map(0).size_global for m in problem.hierarchy.meshes[1:]]
    assert [line.split(" vertices in ")[0] for line in lines] == \
        [f"refinement {j} of 2: {n:,}" for j, n in enumerate(sizes, 1)]
    assert all(line.endswith(" s") for line in lines)


@pytest.mark.parametrize("name", ["square", "user"])
def test_a_scene_on_a_given_mesh_reports_its_refinements(name):
    """The same on a dolfinx mesh given as T_0 (square and user scenes): one line per
    refinement with the refined mesh's size."""
    from dolfinx.mesh import create_unit_square

    from membranes import scenes
    lines = []
    mesh = create_unit_square(MPI.COMM_WORLD, 2, 2)
    problem = scenes.make(name, mesh=mesh, levels=2, progress=lines.append)
    sizes = [m.topology.index_map(0).size_global for m in problem.hierarchy.meshes[1:]]
    assert [line.split(" vertices in ")[0] for line in lines] == \
        [f"refinement {j} of 2: {n:,}" for j, n in enumerate(sizes, 1)]


def test_refinement_progress_on_stderr_or_refused(capsys):
    """progress=True prints the lines on stderr, as `solve`'s; anything else that is not a
    callable is refused before any refinement, and by `solve` before any solve (one check,
    `model.progress.reporter`)."""
    from membranes import scenes, solve
    problem = scenes.disk(h=0.5, levels=1, progress=True)
    assert capsys.readouterr().err.startswith("refinement 1 of 1: ")
    with pytest.raises(ValueError, match="progress must be True, False, None or a callable"):
        build_hierarchy(unit_disk(0.5), 1, progress="yes")
    with pytest.raises(ValueError, match="progress must be True, False, None or a callable"):
        solve(problem, progress="yes")
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("quiet", [False, None])
def test_no_progress_prints_nothing(quiet, capsys):
    """progress=False (what `--quiet` gives) and None print no line, neither while a
    hierarchy is refined nor while `solve` runs: only True prints on stderr."""
    from membranes import scenes, solve
    problem = scenes.disk(h=0.5, levels=1, progress=quiet)
    assert solve(problem, newton="exact", estimators=False, progress=quiet).converged
    captured = capsys.readouterr()
    assert (captured.out, captured.err) == ("", "")


def test_a_run_on_the_finest_mesh_makes_no_prolongation():
    """Lean runs: `nested=False` solves T_J alone and leaves the hierarchy's prolongations
    unmade; the nested default makes them."""
    from membranes import scenes, solve
    alone, nested = scenes.disk(h=0.4, levels=1), scenes.disk(h=0.4, levels=1)
    assert solve(alone, nested=False, estimators=False).converged
    assert alone.hierarchy.made == []
    assert solve(nested, estimators=False).converged
    assert len(nested.hierarchy.made) == 1


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_processes_without_cells(tmp_path):
    """One triangle on 3 processes: dolfinx gives it to one of them, and plaza refinement
    (no redistribution) leaves the other two without a cell on every level. The whole run
    (nested Newton, the patch engine, the estimators, the outputs) must work there too, with
    the serial run's η to round-off (a reshape of an empty dofmap failed before)."""
    from membranes import scenes, solve
    msh = str(write_msh(tmp_path / "one.msh", "one"))
    serial = solve(scenes.user(mesh=msh, levels=1, f1="-1"))
    out = tmp_path / "out"
    proc = mpirun(["-m", "membranes.app.cli", "solve", "--mesh", msh, "--levels", "1", "--f1",
                   "-1", "--quiet", "--out", out], processes=3)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert line["processes"] == 3 and line["n_cells"] == 4
    assert line["eta"] == pytest.approx(serial.estimates["eta"], rel=1e-10)
    assert (out / "solution.xdmf").exists()


PARTITIONS = """
import json, os
from mpi4py import MPI
from membranes.fem.meshes import unit_disk
comm, parts = MPI.COMM_WORLD, []
for _ in range(3):
    m = unit_disk(0.05, comm)
    n = m.topology.index_map(2).size_local
    centres = m.geometry.x[:, :2][m.geometry.dofmap.array.reshape(-1, 3)[:n]].mean(axis=1)
    parts.append([n, centres.sum(axis=0).round(9).tolist()])
parts = comm.gather(parts)
if comm.rank == 0:
    print(json.dumps({"parts": parts, "left": "SCOTCH_PTHREAD_NUMBER" in os.environ}))
"""


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_partitions_are_the_same_in_every_run():
    """The disk on 4 processes, made three times in a run and in two runs: every process gets
    the same cells each time (their number and the sum of their centres). With PT-Scotch's
    threads (SCOTCH_PTHREAD_NUMBER=4 set by hand) the parts differed between the three
    meshes of one run, and so did Newton's steps and η between runs (fem.meshes notes)."""
    runs = []
    for _ in range(2):
        proc = mpirun(["-c", PARTITIONS], processes=4, unset=("SCOTCH_PTHREAD_NUMBER",))
        assert proc.returncode == 0, proc.stdout + proc.stderr
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    for run in runs:
        assert not run["left"]                     # the environment is restored
        for rank in run["parts"]:
            assert rank[0][0] > 0 and rank[1:] == [rank[0], rank[0]]
    assert runs[0]["parts"] == runs[1]["parts"]


def test_poincare_constant_of_each_domain():
    """C_PF h_Ω of §7: 1/j_{0,1} on the unit disk, whichever scene meshes it (the user scene
    took the bounding box's 1/(π √(1/4 + 1/4)) = 0.450 there, 8 % above the disk's 0.416);
    1/(π √2) on the unit square. j_{0,1}, the first positive zero of J_0, comes from mpmath,
    independently of the constant in scenes.py: a larger one gives a smaller C_PF and an η
    that is no guaranteed bound, a smaller one a needlessly large η. Tolerance: the double
    nearest j_{0,1} (rel 1e-15)."""
    import mpmath

    from membranes.model import scenes
    j01 = float(mpmath.besseljzero(0, 1))
    assert abs(float(mpmath.besselj(0, j01))) <= 1e-15
    for scene in (scenes.disk(h=0.5), scenes.radial(h=0.5), scenes.user(h=0.5)):
        assert scene.poincare_constant() == pytest.approx(1.0 / j01, rel=1e-15), scene.name
    for scene in (scenes.square(h=0.5), scenes.user(h=0.5, domain="square")):
        assert scene.poincare_constant() == pytest.approx(1 / (np.pi * np.sqrt(2)), rel=1e-12)


def test_sizes_and_shapes_of_a_structured_mesh():
    """mesh_size, cell_diameters, triangle_areas and aspect_ratios against the closed forms of
    dolfinx's structured square (n × n squares of side 1/n, each cut into two right triangles
    along a diagonal): h_K is the diagonal √2/n (the *longest* edge, §7's h_K, not a leg 1/n),
    |K| = 1/(2 n²), and h_K²/(2|K|) = 2; the square's corners give h = √2/n too. Tolerance:
    round-off of a few operations on coordinates of size 1. And the bad sizes are refused
    before gmsh runs (h = 0 asked gmsh for cells of size 0), a grading p < 1 as documented."""
    from membranes.fem.meshes import (
        cell_diameters,
        cell_vertices,
        structured_square,
        target_size,
        triangle_areas,
    )
    n = 4
    mesh = structured_square(n, n)
    assert np.allclose(cell_diameters(mesh), np.sqrt(2.0) / n, rtol=1e-14)
    assert mesh_size(mesh) == pytest.approx(np.sqrt(2.0) / n, rel=1e-14)
    assert np.allclose(triangle_areas(cell_vertices(mesh)), 0.5 / n ** 2, rtol=1e-14)
    assert np.allclose(aspect_ratios(mesh), 2.0, rtol=1e-13)
    for bad in (0.0, -0.0, -1.0, float("inf"), float("nan")):   # no gmsh run at h = 0
        with pytest.raises(ValueError, match="mesh size h must be a positive finite number"):
            target_size(bad)
    with pytest.raises(ValueError, match="grading must be a finite number >= 1"):
        structured_square(2, 2, grading=0.5)          # (p < 1: cells grow towards (0, 0))


SIZES = """
import json
from mpi4py import MPI
from membranes.fem.meshes import mesh_counts, mesh_size, unit_disk
m = unit_disk(0.3, MPI.COMM_WORLD)
local = m.topology.index_map(2).size_local
out = [mesh_size(m), list(mesh_counts(m)), local]
out = MPI.COMM_WORLD.gather(out)
if MPI.COMM_WORLD.rank == 0:
    print(json.dumps(out))
"""


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_sizes_and_counts_are_global_on_several_processes(tmp_path):
    """mesh_size (h = max_K h_K over *all* processes, what summary.json reports) and
    mesh_counts (V, T, χ) of the disk on 3 processes are the serial mesh's on every
    process: exactly, as the partition only distributes the same cells (dolfinx keeps the
    coordinates)."""
    from membranes.fem.meshes import mesh_counts
    serial = unit_disk(0.3)
    want = [mesh_size(serial), list(mesh_counts(serial))]
    script = tmp_path / "sizes.py"
    script.write_text(SIZES)
    proc = mpirun([script], processes=3)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    ranks = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(ranks) == 3 and all(r[2] > 0 for r in ranks)
    assert sum(r[2] for r in ranks) == want[1][1]
    for r in ranks:
        assert r[:2] == want


def test_poincare_constant_of_a_rectangle_is_its_own():
    """Without a scene's constant, C_PF h_Ω is 1/sqrt(λ_1) of the mesh's bounding box a × b,
    λ_1 = π² (1/a² + 1/b²) (§7; Ω inside the box, λ_1 falls as the domain grows, so the bound
    is guaranteed): on 2 × 1 and 1 × 3 rectangles, whose two sides differ (on the unit square
    a and b cannot be told apart). Tolerance: round-off of the coordinates' scaling."""
    from membranes import Problem
    from membranes.fem.meshes import structured_square
    for a, b in ((2.0, 1.0), (1.0, 3.0)):
        mesh = structured_square(3, 2)
        mesh.geometry.x[:, 0] *= a
        mesh.geometry.x[:, 1] *= b
        problem = Problem("box", build_hierarchy(mesh, 0), 1.0, 1.0, 0.1, 0.0, 0.0)
        want = 1.0 / (np.pi * np.sqrt(1.0 / a ** 2 + 1.0 / b ** 2))
        assert problem.poincare_constant() == pytest.approx(want, rel=1e-14), (a, b)


def test_the_plane_of_a_mesh_is_measured_against_its_extent():
    """Nodes in one plane z = c are taken as z = 0, whatever c; the tolerance of the plane is
    1e-12 of the nodes' extent in it, plus z's own round-off, not 1e-12 |z|: a plane tilted
    by 0.4 at z = 1e12 passed (1e-12 |z| = 1 there) and was solved on its projection."""
    from membranes.fem.meshes import in_the_plane
    xy = np.array([(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
    for c in (0.0, -3.0, 1e12):
        assert np.array_equal(in_the_plane(np.column_stack([xy, np.full(4, c)]), "m"), xy)
    for z, message in ((1e12 + 0.4 * xy[:, 0], "m is 3D"), (1e-11 * xy[:, 1], "m is 3D"),
                       (np.array([0.0, 0.0, np.nan, 0.0]), "non-finite")):
        with pytest.raises(ValueError, match=message):
            in_the_plane(np.column_stack([xy, z]), "m")
    assert np.array_equal(in_the_plane(np.column_stack([xy, 1e-13 * xy[:, 1]]), "m"), xy)
    # a plane moved to z = 1e5 + 0.3 by a computation: z differ by its round-off (1.5e-11)
    moved = 1e5 + 0.3 + np.array([0.0, 1.4551915228366852e-11, 0.0, 0.0])
    assert np.array_equal(in_the_plane(np.column_stack([xy, moved]), "m"), xy)
    # four of its ulps (5.8e-11 < 8 ε |z| = 1.8e-10; one ulp passed ε |z| alone too)
    moved = 1e5 + 0.3 + np.array([0.0, 4 * 1.4551915228366852e-11, 0.0, 0.0])
    assert np.array_equal(in_the_plane(np.column_stack([xy, moved]), "m"), xy)
    # the extent is the larger side's: a strip 100 x 1 may have z spread by 1e-11
    strip = xy * [100.0, 1.0]
    assert np.array_equal(in_the_plane(np.column_stack([strip, 1e-11 * xy[:, 1]]), "m"), strip)


def test_a_reader_failing_to_start_on_rank_0_is_an_error_on_every_rank():
    """`on_rank0`: gmsh failing as its session starts on rank 0 was raised there alone, before
    the broadcast the other ranks wait in; it now goes through it, as a RuntimeError (an
    error other than ValueError in the reader alike)."""
    import contextlib

    from mpi4py import MPI

    from membranes.fem.meshes import on_rank0

    @contextlib.contextmanager
    def broken():
        raise OSError("gmsh: cannot open display")
        yield

    def failing(_):
        raise KeyError("node")
    for session, build, message in ((broken, lambda g: None, "OSError: gmsh: cannot open"),
                                    (contextlib.nullcontext, failing, "KeyError: 'node'")):
        with pytest.raises(RuntimeError, match=f"on rank 0 failed: {message}"):
            on_rank0(MPI.COMM_WORLD, build, session)


def test_refined_boundary_vertices_lie_on_the_circle():
    """Every boundary vertex of the disk's T_2 lies on the unit circle to round-off (1e-15:
    the projection divides by the radius), the new ones included (§9); and a hierarchy cut
    to its first levels keeps the projection that put them there."""
    from membranes import scenes
    from membranes.fem.hierarchy import boundary_vertices
    hierarchy = scenes.disk(h=0.3, levels=2).hierarchy
    mesh = hierarchy.finest
    radius = np.hypot(*mesh.geometry.x[boundary_vertices(mesh), :2].T)
    assert len(radius) == 92 and np.abs(radius - 1.0).max() <= 1e-15     # (4 x 23)
    assert hierarchy.up_to(1).projection is hierarchy.projection is not None


def test_the_user_scene_refines_its_own_domain():
    """The user scene moves new boundary vertices onto the circle on the unit disk only (§9):
    on the unit square the midpoints of its boundary edges stay on the sides, so T_2 is
    still a mesh of (0, 1)² (every boundary vertex on a side, the cells' area 1); moved
    onto the circle, (1, y) went to (1, y)/√(1 + y²), off the square. On the disk, as for
    the disk scene, every boundary vertex of T_2 lies on the circle. Tolerance: round-off
    (a midpoint of a side keeps its coordinate 0 or 1 exactly; the projection divides by
    the radius, 1e-15; the area is a sum of a few hundred products, 1e-13)."""
    from membranes import scenes
    from membranes.fem.hierarchy import boundary_vertices
    from membranes.fem.meshes import triangle_areas
    mesh = scenes.user(domain="square", h=0.3, levels=2).hierarchy.finest
    x = mesh.geometry.x[boundary_vertices(mesh), :2]
    assert len(x) > 0
    assert np.all(np.any((x == 0.0) | (x == 1.0), axis=1))
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)
    assert triangle_areas(mesh.geometry.x[cells, :2]).sum() == pytest.approx(1.0, abs=1e-13)
    mesh = scenes.user(domain="disk", h=0.3, levels=2).hierarchy.finest
    radius = np.hypot(*mesh.geometry.x[boundary_vertices(mesh), :2].T)
    assert len(radius) == 92 and np.abs(radius - 1.0).max() <= 1e-15     # (as the disk's)


def test_scenes_mesh_at_the_default_size_without_h():
    """A scene built without h meshes its domain at DEFAULT_H, 0.05 (the command line's
    documented default for --h, which it leaves to the scene): the disk, square and user
    scenes' coarse meshes are gmsh's meshes at that size (gmsh is deterministic: the vertex
    counts are equal, exactly)."""
    from membranes import scenes
    assert scenes.DEFAULT_H == 0.05

    def count(mesh):
        return mesh.topology.index_map(0).size_global
    disk, square = count(unit_disk(0.05)), count(unit_square(0.05))
    assert disk != square
    for problem, expected in ((scenes.disk(), disk), (scenes.square(), square),
                              (scenes.user(f1="-1"), disk),
                              (scenes.user(domain="square"), square)):
        assert count(problem.mesh) == expected, problem.description
