"""gmsh files as user meshes (membranes.fem.meshes.read_msh, §12): physical groups that cover
part of the surfaces or overlap, files that are no .msh, and cells dolfinx cannot use."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI

from membranes import scenes, solve
from membranes.fem.mesh_files import read_msh

from .conftest import cli_bad_input, mpirun

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def two_squares(path, groups, save_all=False):
    """(0, 2) x (0, 1) as two conforming unit squares (surfaces 1 and 2), with the 2D physical
    groups `groups` ({tag: [surfaces]}), written in msh 4.1 (all elements if `save_all`)."""
    def build(gmsh):
        gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        gmsh.model.occ.addRectangle(1, 0, 0, 1, 1)
        gmsh.model.occ.fragment([(2, 1)], [(2, 2)])
        gmsh.model.occ.synchronize()
        for tag, surfaces in groups.items():
            gmsh.model.addPhysicalGroup(2, surfaces, tag)
        gmsh.option.setNumber("Mesh.SaveAll", int(save_all))
    return meshed(path, build)


def meshed(path, build):
    """Mesh what `build(gmsh)` makes at size 0.25 and write it to `path` (msh 4.1)."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        build(gmsh)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.25)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return str(path)


def grid_msh(path, extra=(), step=1, moved=None):
    """The 4 x 4 grid of (0, 1)², two triangles per square, plus the triangles `extra` (node
    indices from 0), hand-written in msh 2.2 ASCII with node tags 1, 1 + step, 1 + 2 step...;
    `moved` ({index: (x, y)}) puts nodes elsewhere."""
    xs = np.linspace(0.0, 1.0, 5)
    nodes = [(x, y) for y in xs for x in xs]
    for k, place in (moved or {}).items():
        nodes[k] = place
    cells = [c for j in range(4) for i in range(4)
             for a in [5 * j + i] for c in ((a, a + 1, a + 6), (a, a + 6, a + 5))]
    return msh22(path, nodes, cells + list(extra), step)


def msh22(path, nodes, cells, step=1):
    """The triangles `cells` (node indices from 0) on the points `nodes`, hand-written in msh
    2.2 ASCII with node tags 1, 1 + step, 1 + 2 step..."""
    lines = ["$MeshFormat", "2.2 0 8", "$EndMeshFormat", "$Nodes", str(len(nodes))]
    lines += [f"{step * i + 1} {x!r} {y!r} 0" for i, (x, y) in enumerate(nodes)]
    lines += ["$EndNodes", "$Elements", str(len(cells))]
    lines += [f"{k + 1} 2 2 1 1 {step * a + 1} {step * b + 1} {step * c + 1}"
              for k, (a, b, c) in enumerate(cells)]
    lines += ["$EndElements"]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return str(path)


def rectangles_msh(path, rectangles, points=(), tilt=0.0):
    """The rectangles (x, y, z, dx, dy), each meshed on its own nodes (no fragment), and the
    geometry points `points` (x, y, z) that no cell uses, all turned by the angle `tilt` about
    the x axis, written in msh 4.1."""
    def build(gmsh):
        for rectangle in rectangles:
            gmsh.model.occ.addRectangle(*rectangle)
        for point in points:
            gmsh.model.occ.addPoint(*point)
        if tilt:
            gmsh.model.occ.rotate(gmsh.model.occ.getEntities(2), 0, 0, 0, 1, 0, 0, tilt)
        gmsh.model.occ.synchronize()
    return meshed(path, build)


def global_counts(mesh):
    return mesh.topology.index_map(0).size_global, mesh.topology.index_map(2).size_global


def test_physical_group_of_part_of_the_surfaces(tmp_path):
    """Saved with all elements, a file whose physical group covers one square only holds the
    other square's nodes too; dolfinx 0.5.2's model_to_mesh crashed on those unused nodes
    (segmentation fault). The group's square is read, as without Mesh.SaveAll."""
    part = read_msh(two_squares(tmp_path / "all.msh", {7: [1]}, save_all=True))
    alone = read_msh(two_squares(tmp_path / "part.msh", {7: [1]}))
    assert global_counts(part) == global_counts(alone)
    x = part.geometry.x[:, 0]
    assert part.comm.allreduce(x.max(initial=0.0), op=MPI.MAX) == pytest.approx(1.0)


def test_overlapping_physical_groups(tmp_path):
    """A surface in two physical groups ('all' and 'left') is meshed once: model_to_mesh
    listed its triangles twice and the run aborted (malloc corruption)."""
    both = read_msh(two_squares(tmp_path / "both.msh", {1: [1, 2], 2: [1]}))
    one = read_msh(two_squares(tmp_path / "one.msh", {1: [1, 2]}))
    assert global_counts(both) == global_counts(one)


@pytest.mark.parametrize("case", ["collinear", "repeated vertex", "twice", "three on an edge"])
def test_cells_dolfinx_cannot_use(case, tmp_path, capsys):
    """Zero-area triangles (not converged, NaN estimators), a repeated vertex (a hang), a
    triangle listed twice (a crash) and an edge of three triangles (a traceback from the
    estimators) are refused when the file is read, with exit code 2 on the command line."""
    extra = {"collinear": [(0, 1, 2)], "repeated vertex": [(0, 0, 1)],
             "twice": [(0, 1, 6)], "three on an edge": [(0, 6, 2)]}[case]
    msh = grid_msh(tmp_path / "bad.msh", extra)
    with pytest.raises(ValueError, match="mesh file"):
        read_msh(msh)
    err = cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)
    assert msh in err


@pytest.mark.parametrize("case", ["moved vertex", "flap"])
def test_folded_mesh(case, tmp_path, capsys):
    """The centre vertex of the grid moved past its right neighbour (four triangles turn
    over), or a triangle added on the inner side of a boundary edge: no edge has more than two
    triangles, but the mesh folds over itself, and the run ended in a RuntimeError traceback
    from the estimators (σ_disc violates its divergence identity). The two triangles of an edge
    must lie on its two sides."""
    kwargs = {"moved vertex": {"moved": {12: (0.8, 0.5)}},
              "flap": {"extra": [(0, 1, 11)]}}[case]
    msh = grid_msh(tmp_path / "folded.msh", **kwargs)
    with pytest.raises(ValueError, match="folded or tangled"):
        scenes.user(mesh=msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)


def test_surface_meshed_twice(tmp_path, capsys):
    """A rectangle added twice, each meshed on its own nodes: the same triangles twice, on
    other nodes at the same places, were taken for two separate membranes on top of each
    other (the energy doubled, no word said). Refused as a triangle listed twice."""
    msh = rectangles_msh(tmp_path / "twice.msh", [(0, 0, 0, 1, 1), (0, 0, 0, 1, 1)])
    with pytest.raises(ValueError, match="twice"):
        read_msh(msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)


@pytest.mark.parametrize("second", [(1, 0, 0, 1, 1), (1, 0.1, 0, 1, 0.7), (0.6, 0.3, 0, 1, 1),
                                    (0.3, 0.35, 0, 0.3, 0.3)])
def test_surfaces_not_joined(second, tmp_path, capsys):
    """A unit square and a second rectangle, each meshed on its own nodes (no fragment):
    side by side, the nodes along x = 1 are there twice, at the same places (equal
    rectangles) or interleaved (the second shorter), and the mesh is cut there; overlapping
    or inside the square, two membranes lie on top of each other. The run solved that other
    problem, held at g along the cut or the inner rim, and certified it without a word.
    Refused, naming the boundary nodes in or on a triangle they are not a vertex of; the
    two squares joined by fragment are read."""
    msh = rectangles_msh(tmp_path / "apart.msh", [(0, 0, 0, 1, 1), second])
    with pytest.raises(ValueError, match="not conforming: .* boundary node") as refused:
        read_msh(msh)
    if second == (1, 0, 0, 1, 1):           # the seam's nodes twice, at the same places
        assert "at the place of a node of a part of the mesh not joined" in str(refused.value)
        assert "on another boundary edge" not in str(refused.value)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)
    assert global_counts(read_msh(two_squares(tmp_path / "joined.msh", {1: [1, 2]})))[1] > 0


def test_surfaces_crossing_like_a_plus_sign(tmp_path, capsys):
    """The strips (0, 1) x (0.4, 0.6) and (0.4, 0.6) x (0, 1), each in two triangles on its
    own four corners, crossing like a plus sign: no node of one lies in a triangle of the
    other, but their boundary edges cross at eight points, and two membranes lie on top of
    each other in (0.4, 0.6)². This was read and certified. Refused, naming the eight ends
    of the crossing edges; the plus joined by fragment is read."""
    nodes = [(0, 0.4), (1, 0.4), (1, 0.6), (0, 0.6), (0.4, 0), (0.6, 0), (0.6, 1), (0.4, 1)]
    cells = [(0, 1, 2), (0, 2, 3), (4, 5, 6), (4, 6, 7)]
    msh = msh22(tmp_path / "plus.msh", nodes, cells)
    with pytest.raises(ValueError, match="not conforming: 8 boundary node"):
        read_msh(msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)

    def plus(gmsh):
        gmsh.model.occ.addRectangle(0, 0.4, 0, 1, 0.2)
        gmsh.model.occ.addRectangle(0.4, 0, 0, 0.2, 1)
        gmsh.model.occ.fragment([(2, 1)], [(2, 2)])
        gmsh.model.occ.synchronize()
    assert global_counts(read_msh(meshed(tmp_path / "joined.msh", plus)))[1] > 0


def test_hanging_node(tmp_path, capsys):
    """(0, 2) x (0, 1): the left square in two triangles, the right one in three around the
    node (1, 0.5), which lies inside the left square's edge from (1, 0) to (1, 1): a hanging
    node, so that edge was a boundary (held at g) and the mesh cut along it. Refused."""
    nodes = [(0, 0), (1, 0), (1, 1), (0, 1), (2, 0), (2, 1), (1, 0.5)]
    cells = [(0, 1, 2), (0, 2, 3), (1, 4, 6), (4, 5, 6), (5, 2, 6)]
    msh = msh22(tmp_path / "hanging.msh", nodes, cells)
    with pytest.raises(ValueError, match=r"1 boundary node\(s\): 1 on another boundary edge \(a "
                                         r"hanging node"):
        read_msh(msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)
    nodes[6] = (1.5, 0.5)                       # the same cells, conforming: no hanging node
    read_msh(msh22(tmp_path / "conforming.msh", nodes, cells + [(1, 6, 2)]))


@pytest.mark.parametrize("scale, words", [(1e200, r"node coordinates up to 1e\+200, beyond"),
                                           (1e-200, "triangles as small as 3.54e-201"),
                                           (1e-150, "triangles as small as 3.54e-151")])
def test_mesh_scales_beyond_double_precision(tmp_path, capsys, scale, words):
    """The unit square's 4 x 4 grid, 32 triangles, scaled: by 1e200 it was refused as "32
    degenerate triangle(s)" after two RuntimeWarnings (the squares of its edges overflow),
    by 1e-200 as degenerate too (they underflow to 0). Refused naming the scale, before
    any square is taken; by 1e-150 too, whose longest edges' squares times the area test's
    1e-12 are no normal doubles. Scaled by 1e150 it is read (the data's own checks
    follow)."""
    nodes = [(0.25 * i, 0.25 * j) for j in range(5) for i in range(5)]
    cells = [c for j in range(4) for i in range(4) for c in
             ((5 * j + i, 5 * j + i + 1, 5 * j + i + 6), (5 * j + i, 5 * j + i + 6, 5 * j + i + 5))]
    msh = msh22(tmp_path / "scaled.msh", [(scale * x, scale * y) for x, y in nodes], cells)
    with pytest.raises(ValueError, match=words):
        read_msh(msh)
    assert "rescale the mesh" in cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)
    large = msh22(tmp_path / "large.msh", [(1e150 * x, 1e150 * y) for x, y in nodes], cells)
    assert global_counts(read_msh(large)) == (25, 32)


@pytest.mark.parametrize("offset, found", [(1e-7, 0), (1e-9, 1), (-1e-3, 2), (-1e-9, 1)])
def test_a_node_near_a_triangle_not_its_own(offset, found):
    """The triangle (0, 0), (1, 0), (0.5, -1) below, and above it two triangles on the node
    m = (0.5, δ), δ = `offset` × |m|'s shortest edge (about 0.5): m lies off the triangle by
    δ (inside it for δ < 0, the triangles overlapping). It counts as a hanging node within
    1e-8 of its shortest edge (one node); inside, the angles of the triangles above and
    below overlap at (0, 0) and (1, 0) by about 2 δ, beyond 1e-8 radians (two nodes)."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    x = np.array([(0, 0), (1, 0), (0.5, 0), (0.5, -1), (0.5, 1)], dtype=float)
    x[2, 1] = 0.5 * offset
    cells = np.array([(0, 3, 1), (0, 2, 4), (2, 1, 4)])
    edges = np.array([(0, 3), (3, 1), (1, 0), (0, 2), (4, 0), (2, 1), (1, 4)])
    assert counted(nonconforming_nodes(x, cells, edges)) == found
    assert counted(nonconforming_nodes(x, cells[:, ::-1], edges)) == found      # either orientation


def test_a_crack_narrower_than_its_edges():
    """The unit square's two triangles, the second on its own copies of the diagonal's ends
    moved 1e-12 off it: a crack. Each of the four ends lies 1.4e-12 off the other triangle,
    within 1e-8 of its boundary edges (about 1), though its twin is nearer still."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    shift = np.array([-1e-12, 1e-12])
    x = np.array([(0, 0), (1, 0), (1, 1), (0, 1), (0, 0) + shift, (1, 1) + shift])
    cells = np.array([(0, 1, 2), (4, 5, 3)])
    edges = np.array([(0, 1), (1, 2), (2, 0), (4, 5), (5, 3), (3, 4)])
    assert counted(nonconforming_nodes(x, cells, edges)) == 4


@pytest.mark.parametrize("tip, found", [(False, 0), (True, 0), ("moved", 0), ("apart", 6)])
def test_a_crack_is_no_hanging_node(tip, found):
    """The unit square in four triangles about its centre c, the last on its own copy of the
    corner (0, 0) (and of c if `tip`): a crack from the corner to c (and on to the corner
    (0, 1)), its faces joined through the mesh at c (at (0, 1)), as gmsh's Crack plugin
    makes them: no hanging node, also with the copy 1.4e-12 off its twin ("moved", within
    1e-8 of the edges: the same place). The last triangle on copies of all its nodes,
    moved by (-1, 1)·1e-12, is a part of the mesh joined to none: refused, its three nodes
    and the three they lie 1.4e-12 off."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    x = np.array([(0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0.5), (0, 0), (0.5, 0.5), (0, 1)])
    last = {False: (3, 5, 4), True: (3, 5, 6), "moved": (3, 5, 4), "apart": (7, 5, 6)}[tip]
    if tip in ("moved", "apart"):
        x[5:] += (-1e-12, 1e-12)
    cells = np.array([(0, 1, 4), (1, 2, 4), (2, 3, 4), last])
    sides = np.sort(cells[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, count = np.unique(sides, axis=0, return_counts=True)
    assert counted(nonconforming_nodes(x, cells, unique[count == 1])) == found


def test_graded_corner_has_no_hanging_node():
    """A fan of triangles from (1, 0) onto the nodes (0, 10^-k), k = 0 … 12, and (0, 0): at
    the corner, edges of length about 1 meet edges down to 1e-12. The small edges' nodes lie
    within 1e-8 of the long edges' length of the large triangles, but far from them measured
    by their own edges: no hanging node."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    heights = np.r_[10.0 ** -np.arange(13), 0.0]
    x = np.vstack([[(1, 0)], np.c_[np.zeros(14), heights]])
    cells = np.array([(0, k + 1, k + 2) for k in range(13)])
    ring = np.arange(len(x))
    assert counted(nonconforming_nodes(x, cells, np.c_[ring, np.roll(ring, -1)])) == 0


def test_a_part_in_a_hole_and_a_part_across_the_ring(tmp_path, capsys):
    """(0, 3)² without (1, 2)², and a square meshed on its own nodes: inside the hole it is
    a second membrane beside the ring (a ray from it crosses the ring's boundary twice),
    and is read; across the ring's inner rim, or inside the ring, two membranes overlap:
    refused."""
    def ring_and(square):
        def build(gmsh):
            gmsh.model.occ.cut([(2, gmsh.model.occ.addRectangle(0, 0, 0, 3, 3))],
                               [(2, gmsh.model.occ.addRectangle(1, 1, 0, 1, 1))])
            gmsh.model.occ.addRectangle(*square)
            gmsh.model.occ.synchronize()
        return build
    inner = read_msh(meshed(tmp_path / "hole.msh", ring_and((1.25, 1.25, 0, 0.5, 0.5))))
    assert global_counts(inner)[1] > 0
    for name, square in (("across", (0.8, 1.25, 0, 0.5, 0.5)), ("in", (0.2, 0.2, 0, 0.5, 0.5))):
        msh = meshed(tmp_path / f"{name}.msh", ring_and(square))
        with pytest.raises(ValueError, match="not conforming"):
            read_msh(msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)


def test_a_boundary_layer_is_checked_in_bounded_memory():
    """(0, 1) x (0, 1e-4) in 200 x 200 rectangles of aspect 1e4, each in two triangles (40401
    nodes): every triangle's circle holds boundary nodes of the long sides, 6 per triangle
    on average, that lie far outside the triangle. A first check measured every such pair
    (peak 111 MB of arrays for 2.6 MB of mesh; 3 GB and 16 s at 10^6 nodes); the checks on
    the boundary edges alone hold about 13 MB here, asserted below 50 MB (tracemalloc's
    count of numpy's arrays, the same on every machine)."""
    import tracemalloc

    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    n = 200
    grid = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1e-4, n + 1))
    x = np.c_[grid[0].ravel(), grid[1].ravel()]
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    a = (j * (n + 1) + i).ravel()
    cells = np.r_[np.c_[a, a + 1, a + n + 2], np.c_[a, a + n + 2, a + n + 1]]
    ring = np.r_[np.arange(n), n + (n + 1) * np.arange(n), (n + 1) ** 2 - 1 - np.arange(n),
                 (n + 1) * np.arange(n, 0, -1)]
    tracemalloc.start()
    try:
        assert counted(nonconforming_nodes(x, cells, np.c_[ring, np.roll(ring, -1)])) == 0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6


def test_planes_and_unused_nodes_off_z_0(tmp_path):
    """A mesh in the plane z = 1 is the same 2D mesh as in z = 0, and a geometry point at
    z = 3 that no triangle uses is not part of the mesh: both were refused as 3D, because
    every node of the file was held to z = 0. Triangles off one plane z = c still are."""
    flat = read_msh(rectangles_msh(tmp_path / "flat.msh", [(0, 0, 0, 2, 1)]))
    high = read_msh(rectangles_msh(tmp_path / "high.msh", [(0, 0, 1, 2, 1)]))
    assert global_counts(high) == global_counts(flat)
    for m in (flat, high):
        assert m.geometry.x[:, 2].max(initial=0.0) == 0.0
    coords = [np.unique(np.concatenate(m.comm.allgather(m.geometry.x[:, :2])), axis=0)
              for m in (flat, high)]
    assert np.array_equal(coords[0], coords[1])
    point = read_msh(rectangles_msh(tmp_path / "point.msh", [(0, 0, 0, 2, 1)], [(1, 0.5, 3)]))
    x = point.geometry.x[:, :2]
    assert point.comm.allreduce(x.max(initial=0.0), op=MPI.MAX) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="is 3D"):
        read_msh(rectangles_msh(tmp_path / "tilted.msh", [(0, 0, 0, 2, 1)], tilt=0.1))


def test_gmsh_error_without_a_reason(tmp_path, monkeypatch):
    """gmsh 4.8 raises Exception('') on some corrupt binary files (0xff bytes in the
    $Elements of a msh 4.1 file): the message ended in 'cannot read mesh file …: '."""
    import gmsh

    def fail(path):
        raise Exception("")
    monkeypatch.setattr(gmsh, "open", fail)
    with pytest.raises(ValueError, match=r"cannot read mesh file .*: \S"):
        read_msh(grid_msh(tmp_path / "grid.msh"))


@pytest.mark.parametrize("text", [
    'SystemCall "touch {marker}";',
    "Point(1) = {{0, 0, 0}}; Point(2) = {{1, 0, 0}}; Point(3) = {{0, 1, 0}};\n"
    "Line(1) = {{1, 2}}; Line(2) = {{2, 3}}; Line(3) = {{3, 1}};\n"
    "Curve Loop(1) = {{1, 2, 3}}; Plane Surface(1) = {{1}}; Mesh 2;",
    "", "hello world"])
def test_not_a_msh_file(text, tmp_path, capsys):
    """gmsh.open runs any file that is no .msh as a .geo script: a SystemCall in it ran a
    shell command, a script with 'Mesh 2' was meshed (past the size check), and plain text
    gave gmsh's 'Unknown variable'. A file must begin with $MeshFormat."""
    marker = tmp_path / "ran"
    msh = tmp_path / "not.msh"
    msh.write_text(text.format(marker=marker))
    with pytest.raises(ValueError, match="is not a gmsh .msh file"):
        read_msh(str(msh))
    assert not marker.exists()
    cli_bad_input(["--mesh", str(msh)], tmp_path / "out", capsys)


def test_node_tags_with_gaps(tmp_path):
    """Node tags 1, 3, 5, ... (another mesher's numbering, or nodes of a removed part):
    model_to_mesh needs tags 1..N and failed with an empty message ('cannot convert the gmsh
    model to a dolfinx mesh: ')."""
    assert global_counts(read_msh(grid_msh(tmp_path / "gaps.msh", step=2))) == (25, 32)


def test_api_mesh_with_h_or_domain(tmp_path):
    """As `--mesh` with `--h` or `--domain` on the command line: h and domain were ignored
    without a word (h = -1 too)."""
    msh = grid_msh(tmp_path / "grid.msh")
    for kwargs in ({"h": 0.1}, {"h": -1}, {"domain": "square"}):
        with pytest.raises(ValueError, match="not both"):
            scenes.user(mesh=msh, **kwargs)
    assert scenes.user(mesh=msh).mesh.topology.index_map(0).size_global == 25


def test_api_mesh_that_is_no_path(tmp_path):
    """scenes.user(mesh=fd) with an int: the size check took it for an open file descriptor,
    read from it and closed it (the process lost that file), then a TypeError traceback. A
    mesh that is no str, bytes or os.PathLike is refused before any file is touched; a bytes
    path is a path."""
    msh = grid_msh(tmp_path / "grid.msh")
    fd = os.open(msh, os.O_RDONLY)
    try:
        for bad in (fd, 2.5, [msh]):
            with pytest.raises(ValueError, match=r"mesh must be the path of a \.msh or "
                                                 r"\.xdmf file \(or a dolfinx Mesh\), got "):
                scenes.user(mesh=bad)
        os.fstat(fd)                                   # (OSError if it was closed)
    finally:
        os.close(fd)
    problem = scenes.user(mesh=os.fsencode(msh))
    assert problem.mesh.topology.index_map(0).size_global == 25
    assert problem.domain == msh


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_refined_file_mesh_on_three_processes(tmp_path):
    """Two squares refined once on 3 processes: plaza refinement of the ghosted mesh that
    model_to_mesh made gave two copies of a ghost cell on some processes, and the estimators
    stopped with 'a facet without cells or with more than two'. The file's mesh is now
    unghosted, and the run gives the serial η. Exact Newton with MUMPS: its iterates do not
    depend on the partition (the adaptive run's Krylov iterates, and so where it stops, do),
    so η agrees to round-off, ε times the systems' condition ≲ 1e3 (asserted 1e-10, measured
    6e-15), with the same Newton steps."""
    same_on_three_processes(two_squares(tmp_path / "two.msh", {7: [1], 8: [2]}))


def same_on_three_processes(path):
    """The mesh file at `path` refined once, exact Newton with MUMPS, serially in this process
    and by the command line on 3 processes: the same Newton steps, η to 1e-10 (as above)."""
    serial = solve(scenes.user(mesh=path, levels=1, f1="-1"), newton="exact", solver="direct")
    proc = mpirun(["-m", "membranes.app.cli", "solve", "--mesh", path, "--levels", "1", "--f1",
                   "-1", "--newton", "exact", "--solver", "direct", "--quiet"], processes=3,
                  timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert line["processes"] == 3 and line["newton_iterations"] == serial.newton_iterations
    assert line["eta"] == pytest.approx(serial.estimates["eta"], rel=1e-10)


def test_max_vertices_counts_a_file_exactly(tmp_path, capsys):
    """The size check took T_0 = 2 V_0 for a file (its header gives only V_0): the 4 x 4
    grid at 3 levels has 1 089 vertices (V_0 = 25, T_0 = 32) and was refused under
    --max-vertices 1089 as 'about 1 593'. The header now gives a lower bound, and the mesh
    read the exact count, Euler characteristic included (a ring: χ = 0)."""
    from membranes.app.cli import main
    from membranes.model import checks
    msh = grid_msh(tmp_path / "grid.msh")
    problem = scenes.user(mesh=msh, levels=3, max_vertices=1089)
    assert problem.mesh.topology.index_map(0).size_global == 1089
    with pytest.raises(ValueError, match="about 1089 vertices, more than the limit"):
        scenes.user(mesh=msh, levels=3, max_vertices=1088)
    err = cli_bad_input(["--mesh", msh, "--levels", "3", "--max-vertices", "1088"],
                        tmp_path / "out", capsys)
    assert "at most 2 levels" in err
    assert checks.refined_vertices(8, 8, 2, euler=0) == 80     # a ring of 8 triangles
    assert main(["solve", "--quiet", "--mesh", msh, "--levels", "3",
                 "--max-vertices", "1089"]) == 0


def _with_node_tag(path, tag, binary, where="node"):
    """The file at `path` with the first node tag of its first element set to `tag`; of a
    binary file also the tag of that element itself (`where` "element"), or the first node
    tag of its first triangle, in a later block ("triangles")."""
    import struct
    data = bytearray(open(path, "rb").read())
    start = data.index(b"$Elements\n") + len(b"$Elements\n")
    if binary:                      # MSH 4.1: 4 size_t, a block (3 int, a size_t), elements
        at = start + 32
        if where == "triangles":    # (blocks of points, lines, then triangles: tag + nodes)
            while struct.unpack_from("<i", data, at + 8)[0] != 2:
                kind, count = struct.unpack_from("<iQ", data, at + 8)
                at += 20 + 8 * {15: 2, 1: 3}[kind] * count
        at += 20 if where == "element" else 28
        data[at:at + 8] = struct.pack("<Q", tag)
    else:                           # the line after the section and block headers
        lines = data[start:].split(b"\n")
        words = lines[2].split(b" ")
        words[1] = str(tag).encode()
        lines[2] = b" ".join(words)
        data[start:] = b"\n".join(lines)
    open(path, "wb").write(data)
    return path


@pytest.mark.parametrize("nodes, cells, reason", [
    # a sliver: area 5e-14 against a longest edge of 1 (2 |K| <= 1e-12 h²)
    ([(0, 0), (1, 0), (0.5, 1e-13)], [(0, 1, 2)], r"has 1 degenerate triangle\(s\) \(zero area"),
    # a unit square's corners moved by 1e16 (ulp 2): its nodes collapse in pairs, and one
    # triangle onto a point, refused as "triangles as small as 0 ...: rescale the mesh" (a
    # probe's, 2026-12-03), which no rescaling cures
    ([(1e16, 1e16), (1e16 + 0.5, 1e16), (1e16 + 0.5, 1e16 + 0.5), (1e16, 1e16 + 0.5),
      (1e16 + 0.25, 1e16 + 0.25)], [(0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)],
     r"has 4 degenerate triangle\(s\) \(zero area"),
    # three triangles on the edge (0, 0)-(1, 0): two of them overlap
    ([(0, 0), (1, 0), (0.5, 1), (0.5, -1), (0.5, -2)], [(0, 1, 2), (0, 1, 3), (0, 1, 4)],
     r"has 1 edge\(s\) of three or more triangles \(overlapping surfaces\?\)$")])
def test_cells_refused_for_what_they_are(nodes, cells, reason, tmp_path):
    """Each was refused all the same by a later check (not conforming) had its own been
    lost; the message names the defect."""
    with pytest.raises(ValueError, match=reason):
        read_msh(msh22(tmp_path / "cells.msh", nodes, cells))


def test_mixed_cells_and_a_quadratic_mesh_are_named(tmp_path):
    """A .msh file of triangles and quadrilaterals (a refusal by cell type, which a later
    check made "5 edge(s) ... folded" when the types were not all compared), and a dolfinx
    mesh of P2 triangles (made "not conforming: 30 boundary node(s)" without its own check):
    each refused for what it is."""
    import ufl
    from dolfinx.mesh import create_mesh

    def mixed(gmsh):
        a = gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        b = gmsh.model.occ.addRectangle(1, 0, 0, 1, 1)
        gmsh.model.occ.fragment([(2, a)], [(2, b)])
        gmsh.model.occ.synchronize()
        gmsh.model.mesh.setRecombine(2, b)
    with pytest.raises(ValueError, match=r"is not a linear triangular mesh \(cells: Triangle 3, "
                                         r"Quadrilateral 4\)$"):
        read_msh(meshed(tmp_path / "mixed.msh", mixed))
    x = np.array([(0, 0), (1, 0), (0, 1), (0.5, 0.5), (0, 0.5), (0.5, 0)])
    p2 = create_mesh(MPI.COMM_SELF, np.array([[0, 1, 2, 3, 4, 5]]), x,
                     ufl.Mesh(ufl.VectorElement("Lagrange", ufl.triangle, 2)))
    with pytest.raises(ValueError, match=r"^mesh must have an affine geometry \(P1 triangles in "
                                         r"the plane\), got degree 2"):
        scenes.user(mesh=p2)


def test_msh_1_tags_and_a_nodes_header_across_the_first_read(tmp_path):
    """Two file layouts the header readers met in no test: a MSH 1 file (sections $NOD and
    $ELM) with an element's node tag of 2^32 + 1, which gmsh reads as node 1, is refused by
    the tag guard (its $ELM section was looked for too); and a file whose $Nodes line
    begins 3 bytes before the end of the first 64 KiB read (a $Comments section before it)
    still gives its node count."""
    import gmsh

    from membranes.model.mesh_headers import mesh_file_vertices
    msh = str(tmp_path / "one.msh")
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.25)
        gmsh.model.mesh.generate(2)
        gmsh.option.setNumber("Mesh.MshFileVersion", 1)
        gmsh.write(msh)
    finally:
        gmsh.finalize()
    lines = open(msh).read().split("\n")
    first = lines.index("$ELM") + 2                 # "tag type physical elementary n nodes…"
    words = lines[first].split()
    words[5] = str(2 ** 32 + 1)
    lines[first] = " ".join(words)
    open(msh, "w").write("\n".join(lines))
    with pytest.raises(ValueError, match=r"has a tag of 2\^31 or more in its elements"):
        read_msh(msh)
    nodes = [(0.1 * i, 0.1 * j) for j in range(11) for i in range(11)]
    cells = [(11 * j + i, 11 * j + i + 1, 11 * j + i + 12) for j in range(10) for i in range(10)]
    text = open(msh22(tmp_path / "late.msh", nodes, cells)).read()
    head, rest = text.split("$Nodes", 1)
    pad = (1 << 16) - 3 - len(head) - len("$Comments\n\n$EndComments\n")
    open(tmp_path / "late.msh", "w").write(head + "$Comments\n" + "x" * pad +
                                           "\n$EndComments\n$Nodes" + rest)
    assert open(tmp_path / "late.msh", "rb").read().index(b"$Nodes") == (1 << 16) - 3
    assert mesh_file_vertices(str(tmp_path / "late.msh")) == 121


@pytest.mark.parametrize("lead", [b"\n", b"  ", b"\xef\xbb\xbf"])
def test_a_msh_file_with_bytes_before_its_header(lead, tmp_path, capsys):
    """gmsh picks its reader by a file's first bytes: a .msh file with a blank line, spaces or
    a UTF-8 byte-order mark before $MeshFormat was parsed as a .geo script ("syntax error",
    or a codec's message). Refused naming the cause; without them the file is read."""
    msh = msh22(tmp_path / "lead.msh", [(0, 0), (1, 0), (0, 1)], [(0, 1, 2)])
    text = open(msh, "rb").read()
    open(msh, "wb").write(lead + text)
    with pytest.raises(ValueError, match=r"has blank space or a byte-order mark before its "
                                         r"\$MeshFormat line, which gmsh cannot read"):
        read_msh(msh)
    cli_bad_input(["--mesh", msh], tmp_path / "out", capsys)
    open(msh, "wb").write(text)
    assert global_counts(read_msh(msh)) == (3, 1)


def _line_ends(path, crlf):
    """The file at `path` with its lines ending in CR LF (as written on Windows), or LF."""
    data = open(path, "rb").read().replace(b"\r\n", b"\n")
    open(path, "wb").write(data.replace(b"\n", b"\r\n") if crlf else data)
    return path


@pytest.mark.parametrize("tag, binary, crlf, where", [
    (2 ** 31 + 5, 1, False, "node"), (2 ** 32 + 1, 0, False, "node"),
    (2 ** 31 + 5, 0, True, "node"), (2 ** 32 + 1, 0, True, "node"),
    (2 ** 31 + 5, 1, False, "element"), (2 ** 31 + 5, 1, False, "triangles")])
def test_element_node_tags_of_2_to_the_31_or_more(tag, binary, crlf, where, tmp_path):
    """A corrupt byte in a MSH 4.1 file's element node tags: gmsh 4.8 crashed on tags from
    2^31 to 2^32 - 1 (a segmentation fault inside gmsh.open, exit -11: 3 of 40 random byte
    corruptions of a binary file), and read 2^32 + 1 as node 1 without a word. Such a file
    is refused before gmsh opens it: exit 2, one line (a child process: the crash would end
    this one). Also with its lines ending in CR LF, which gmsh reads: the check looked for
    "$Elements" and a LF, missed their section, and let gmsh crash or wrap the tag. In a
    binary file the tag may be an element's own, or in a block after the first (the check
    steps from block to block)."""
    def build(gmsh):
        gmsh.model.occ.addRectangle(0, 0, 0, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.Binary", binary)
    msh = meshed(tmp_path / "one.msh", build)
    original = open(msh, "rb").read()
    _line_ends(_with_node_tag(msh, tag, binary, where), crlf)
    env = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-m", "membranes.app.cli", "solve", "--mesh", msh,
                           "--quiet", "--out", str(tmp_path / "out")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert proc.stderr.strip() == f"membranes: error: mesh file {msh!r} has a tag of 2^31 " \
        f"or more in its elements ({tag}): a corrupt file?"
    assert not (tmp_path / "out").exists()
    # the same file with the tag it had is read
    open(msh, "wb").write(original)
    assert read_msh(_line_ends(msh, crlf)).topology.index_map(2).size_global > 0


def test_pinch_vertex_on_two_processes(tmp_path):
    """Two 4 x 4 grids of squares, (0, 1)² and (1, 2)², touching at the one node (1, 1): a
    pinch, where the cells of each square meet the other's at that vertex alone. dolfinx
    0.5.2 finds the vertices processes share through facets, so on 2 processes the pinch
    may become two vertices (README, "On several processes"); it lies on ∂Ω, u = g there,
    and the solution does not change: exact Newton with MUMPS gives the serial η to
    round-off (asserted 1e-10, measured 2.5e-13 at J = 3), with the same Newton steps."""
    xs = np.linspace(0.0, 1.0, 5)
    nodes = [(x, y) for y in xs for x in xs]
    nodes += [(1 + x, 1 + y) for y in xs for x in xs][1:]
    second = [24] + list(range(25, 49))                 # its corner (1, 1) is node 24
    cells = [c for j in range(4) for i in range(4) for a in [5 * j + i]
             for c in ((a, a + 1, a + 6), (a, a + 6, a + 5))]
    cells += [tuple(second[k] for k in c) for c in cells]
    msh = msh22(tmp_path / "pinch.msh", nodes, cells)
    args = ["--mesh", msh, "--levels", "2", "--f1", "-1", "--f2", "0.3", "--newton", "exact",
            "--solver", "direct"]
    serial = solve(scenes.user(mesh=msh, levels=2, f1="-1", f2="0.3"), newton="exact",
                   solver="direct")
    proc = mpirun(["-m", "membranes.app.cli", "solve", *args, "--quiet"], processes=2,
                  timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    line = json.loads(proc.stdout.strip().splitlines()[-1])
    assert line["n_vertices"] - serial.per_level[-1]["n_vertices"] in (0, 1)
    assert line["newton_iterations"] == serial.newton_iterations
    assert line["eta"] == pytest.approx(serial.estimates["eta"], rel=1e-10)


def test_an_edge_from_just_outside_a_part_into_it():
    """The rectangle (-1, 1) x (-1, 0) and a separate triangle with two corners 1e-9 above
    its top edge, joined by an edge of 0.01, and the third, (0.5, -0.5), deep inside it:
    two membranes overlap. The corners are no hanging nodes (1e-9 is beyond 1e-8 of their
    shortest edge), but two of the triangle's edges cross the rectangle's top. With the
    crossing test's tolerance taken from the longer edges (1e-8 of about 0.7) the corners
    were on the top's line, nothing crossed, and the overlap was read: its five ends."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    x = np.array([(-1, -1), (1, -1), (1, 0), (-1, 0), (0, 1e-9), (0.01, 1e-9), (0.5, -0.5)])
    cells = np.array([(0, 1, 2), (0, 2, 3), (4, 5, 6)])
    edges = np.array([(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 4)])
    assert counted(nonconforming_nodes(x, cells, edges)) == 5
    assert counted(nonconforming_nodes(x, cells[:, ::-1], edges[::-1])) == 5


@pytest.mark.parametrize("turns, found", [(8, 0), (10, 12)])
def test_a_strip_wound_onto_itself_is_no_crack(turns, found):
    """The ring 1 < r < 2 as a strip of `turns` eighths of a turn, one triangle pair each,
    on nodes of its own at every angle: 8 eighths meet at angle 0 on two copies of its
    nodes, a crack (a slit ring) and read; 10 lap over the first two eighths, their nodes
    at the same places, a connected mesh: two membranes on top of each other. The nodes at
    one place were taken for a crack's faces, each alone showed nothing, and the mesh was
    read. At one place, the angles of all their triangles are compared: the 12 nodes."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    angle = np.pi / 4 * np.arange(turns + 1)
    x = np.vstack([np.c_[r * np.cos(angle), r * np.sin(angle)] for r in (1, 2)])
    k = np.arange(turns)
    cells = np.r_[np.c_[k, k + 1, k + turns + 2], np.c_[k, k + turns + 2, k + turns + 1]]
    sides = np.sort(cells[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, count = np.unique(sides, axis=0, return_counts=True)
    assert counted(nonconforming_nodes(x, cells, unique[count == 1])) == found
    assert counted(nonconforming_nodes(x, cells[:, ::-1], unique[count == 1])) == found


def test_many_parts_and_a_part_inside_a_thin_one():
    """30000 separate triangles (90000 nodes, all on the boundary), each in a cell of a
    grid, none inside another: read. Check 3 looks for a part's node only in the parts
    whose bounding box holds it, found along an axis or in a square about the box,
    whichever holds fewer nodes (a ray through all edges for each part took 9.3 s here).
    A long thin triangle below the grid (its box thin in y: found along the y axis) with a
    small triangle inside it, and a small triangle inside the grid's first (found in the
    square about its box): those two nodes are refused."""
    from membranes.fem.conformity import nonconforming_nodes
    from membranes.fem.conformity import total as counted
    k = 30000
    corner = np.c_[np.arange(k) % 173, np.arange(k) // 173] * 1.0
    corner += np.random.default_rng(0).random((k, 2)) * 0.3
    x = (corner[:, None] + [(0, 0), (0.5, 0), (0.2, 0.4)]).reshape(-1, 2)
    cells = np.arange(3 * k).reshape(k, 3)
    sides = [[0, 1], [1, 2], [2, 0]]
    assert counted(nonconforming_nodes(x, cells, cells[:, sides].reshape(-1, 2))) == 0
    thin = [(-5, -2), (200, -2), (200, -1.5), (150, -1.95), (150.1, -1.95), (150.05, -1.9)]
    small = corner[0] + [(0.2, 0.1), (0.25, 0.1), (0.22, 0.15)]
    x = np.vstack([x, thin, small])
    cells = np.vstack([cells, 3 * k + np.array([(0, 1, 2), (3, 4, 5), (6, 7, 8)])])
    assert counted(nonconforming_nodes(x, cells, cells[:, sides].reshape(-1, 2))) == 2


def _grid(n, shift=(0.0, 0.0)):
    """Nodes and triangles of an n x n grid of squares over (0, 1)² moved by `shift`."""
    xs = np.linspace(0.0, 1.0, n + 1)
    nodes = np.array([(x + shift[0], y + shift[1]) for y in xs for x in xs])
    cells = np.array([c for j in range(n) for i in range(n) for a in [(n + 1) * j + i]
                      for c in ((a, a + 1, a + n + 2), (a, a + n + 2, a + n + 1))])
    return nodes, cells


def _dolfinx_mesh(nodes, cells, comm=MPI.COMM_WORLD):
    """A dolfinx mesh of the triangles `cells` on `nodes`, given on rank 0 of `comm`."""
    from dolfinx.io import gmshio
    from dolfinx.mesh import create_mesh
    if comm.rank:
        nodes, cells = np.zeros((0, 2)), np.zeros((0, 3), dtype=np.int64)
    return create_mesh(comm, np.asarray(cells, dtype=np.int64), np.asarray(nodes, dtype=float),
                       gmshio.ufl_mesh(2, 2))


def test_a_dolfinx_mesh_is_a_user_mesh(tmp_path):
    """scenes.user(mesh=<dolfinx Mesh>): the same triangles as a .msh file give the file's
    solution (exact Newton, MUMPS: η to round-off, asserted 1e-10), on a hierarchy of the
    same sizes; h or domain with it are refused as with a file."""
    nodes, cells = _grid(6)
    data = {"f1": "-1 + x", "f2": "0.5", "mu2": 3.0, "levels": 1}
    from_file = solve(scenes.user(mesh=msh22(tmp_path / "grid.msh", nodes, cells), **data),
                      newton="exact", solver="direct")
    problem = scenes.user(mesh=_dolfinx_mesh(nodes, cells), **data)
    assert problem.description.startswith("given mesh, mu1 = 1.0, mu2 = 3.0")
    given = solve(problem, newton="exact", solver="direct")
    assert given.per_level[-1]["n_vertices"] == from_file.per_level[-1]["n_vertices"] == 169
    assert given.estimates["eta"] == pytest.approx(from_file.estimates["eta"], rel=1e-10)
    for kwargs in ({"h": 0.1}, {"domain": "square"}):
        with pytest.raises(ValueError, match="not both"):
            scenes.user(mesh=problem.hierarchy.meshes[0], **kwargs)


def test_a_planar_dolfinx_mesh_of_dimension_3(tmp_path):
    """A dolfinx mesh whose nodes have three coordinates in one plane z = c (what gmshio's
    model_to_mesh makes of a 2D model by default) was refused; it is made anew in 2D and
    gives the 2D mesh's solution (exact Newton, MUMPS: η to round-off, asserted 1e-10), in
    the user and square scenes. Nodes off one plane are refused, in one line."""
    from dolfinx.io import gmshio
    from dolfinx.mesh import create_mesh

    def raised(nodes, cells, z):
        nodes = np.hstack([nodes, np.reshape(z, (-1, 1)) * np.ones((len(nodes), 1))])
        return create_mesh(MPI.COMM_WORLD, np.asarray(cells, dtype=np.int64), nodes,
                           gmshio.ufl_mesh(2, 3))

    nodes, cells = _grid(6)
    data = {"f1": "-1 + x", "f2": "0.5", "levels": 1}
    flat = solve(scenes.user(mesh=_dolfinx_mesh(nodes, cells), **data), newton="exact",
                 solver="direct")
    for make in (scenes.user, lambda mesh, **kw: scenes.square(mesh=mesh, levels=1)):
        problem = make(mesh=raised(nodes, cells, 0.25), **data) if make is scenes.user \
            else make(raised(nodes, cells, -3.0))
        assert problem.mesh.geometry.dim == 2
        sol = solve(problem, newton="exact", solver="direct")
        assert sol.per_level[-1]["n_vertices"] == 169
        if make is scenes.user:
            assert sol.estimates["eta"] == pytest.approx(flat.estimates["eta"], rel=1e-10)
        else:
            square = solve(scenes.square(mesh=_dolfinx_mesh(nodes, cells), levels=1),
                           newton="exact", solver="direct")
            assert sol.estimates["eta"] == pytest.approx(square.estimates["eta"], rel=1e-10)
    with pytest.raises(ValueError, match=r"^mesh is 3D \(its triangles' nodes have z from 0 "
                                         r"to 1, a spread of 1 over an extent of 1 in the "
                                         r"plane: not one plane z = const\)$"):
        scenes.user(mesh=raised(nodes, cells, nodes[:, 0]))


def test_a_dolfinx_mesh_of_two_unjoined_squares_is_refused():
    """Two unit squares side by side, each on nodes of its own (the seam's nodes twice), made
    a dolfinx mesh: read as a mesh cut along the seam, as such a file was. Refused as the
    file is, by the same checks, gathered on rank 0."""
    left, cells = _grid(2)
    right, _ = _grid(2, shift=(1.0, 0.0))
    mesh = _dolfinx_mesh(np.vstack([left, right]), np.vstack([cells, cells + len(left)]))
    with pytest.raises(ValueError, match=r"^mesh is not conforming: 6 boundary node\(s\): 6 at "
                                         r"the place of a node of a part of the mesh not joined "
                                         r"to theirs .* \(its cells must share their nodes "
                                         r"where they meet\)$"):
        scenes.user(mesh=mesh)


GIVEN = """
import json, sys
import numpy as np
from mpi4py import MPI
import dolfinx.mesh as dm
from dolfinx.io import gmshio
from membranes import scenes, solve
nodes, cells = (np.array(a) for a in json.loads(sys.argv[1]))
if MPI.COMM_WORLD.rank:
    nodes, cells = np.zeros((0, 2)), np.zeros((0, 3), dtype=np.int64)
pinch = dm.create_mesh(MPI.COMM_WORLD, cells.astype(np.int64), nodes.astype(float),
                       gmshio.ufl_mesh(2, 2))
grid = dm.create_unit_square(MPI.COMM_WORLD, 6, 6)          # with ghost cells
out = []
for mesh in (pinch, grid):
    sol = solve(scenes.user(mesh=mesh, levels=1, f1="-1", f2="0.3"), newton="exact",
                solver="direct")
    out.append(sol.estimates["eta"])
if MPI.COMM_WORLD.rank == 0:
    print(json.dumps(out))
"""


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_dolfinx_meshes_on_three_processes():
    """On 3 processes: two squares touching at one corner (a pinch, which dolfinx 0.5.2
    makes two vertices there, README) given as a dolfinx mesh is one node by its input
    index, so the conformity check reads it as serially (it took the two copies for parts
    not joined, at one place); and dolfinx's own grid with ghost cells is refined. Both give
    the serial η (exact Newton, MUMPS; asserted 1e-10)."""
    from dolfinx.mesh import create_unit_square
    first, cells = _grid(2)
    second, _ = _grid(2, shift=(1.0, 1.0))
    nodes = np.vstack([first, second])
    cells = np.vstack([cells, cells + len(first)])
    nodes, inverse = np.unique(nodes, axis=0, return_inverse=True)   # (1, 1) once
    cells = inverse.ravel()[cells]
    serial = [solve(scenes.user(mesh=mesh, levels=1, f1="-1", f2="0.3"), newton="exact",
                    solver="direct").estimates["eta"]
              for mesh in (_dolfinx_mesh(nodes, cells, MPI.COMM_SELF),
                           create_unit_square(MPI.COMM_SELF, 6, 6))]
    proc = mpirun(["-c", GIVEN, json.dumps([nodes.tolist(), cells.tolist()])], processes=3,
                  timeout=240)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == pytest.approx(serial, rel=1e-10)
