"""The conformity checks of a mesh's boundary (membranes.fem.conformity) on small meshes
built for one check each: what a mutation round (2026-12-01) found that no other test told
apart. The meshes of files and the CLI's refusals are in test_user_meshes.py."""

import numpy as np
import pytest

from membranes.fem.conformity import _in_boxes, _ranges, nonconforming_nodes


def boundary_edges(cells):
    """The edges of one triangle only (node pairs)."""
    sides = np.sort(np.asarray(cells)[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    unique, count = np.unique(sides, axis=0, return_counts=True)
    return unique[count == 1]


def found_in(x, cells):
    """{check: nodes} found, the same in both orientations of the triangles."""
    x, cells = np.asarray(x, dtype=float), np.asarray(cells)
    found = nonconforming_nodes(x, cells, boundary_edges(cells))
    other = nonconforming_nodes(x, cells[:, ::-1], boundary_edges(cells))
    nodes = {k: sorted(int(i) for i in v) for k, v in found.items() if len(v)}
    assert nodes == {k: sorted(int(i) for i in v) for k, v in other.items() if len(v)}
    return nodes


def test_a_crossing_near_the_far_end_of_a_long_edge():
    """The triangle (0, 0), (100, 0), (50, 50) and a thin one from (99, 0.01), inside it
    near its bottom edge's end, out to x = 150: they overlap. The thin one's other nodes lie
    outside the first, so only the crossing of the bottom edge (length 100) by the thin
    triangle's edges (length about 51) shows it: their midpoints are 74.5 apart, within the
    longer edge's length but beyond half of it and beyond the shorter edge's."""
    x = [(0, 0), (100, 0), (50, 50), (99, 0.01), (150, -1), (150, -1.1)]
    assert found_in(x, [(0, 1, 2), (3, 4, 5)]) == {"crossing": [0, 1, 3, 4, 5]}


def test_an_edge_beyond_another_edges_end_is_no_crossing():
    """A simple polygon whose boundary zigzags below the line y = 0 of its first edge, beyond
    that edge's end (the edge from (1.2, -0.1) to (1.3, 0.1) straddles the line, not the
    edge): a conforming mesh, nothing found."""
    x = [(0, 0), (1, 0), (1.2, -0.1), (1.3, 0.1), (2, 0.1), (2, 1), (0, 1)]
    cells = [(6, 0, 1), (6, 1, 3), (1, 2, 3), (6, 3, 4), (6, 4, 5)]
    assert found_in(x, cells) == {}


@pytest.mark.parametrize("x", [
    # a small triangle inside a large one whose last node has the smallest x (the large
    # part's box spans the nodes of all its edges' ends, not of their starts alone)
    [(0.2, 0.45), (0.25, 0.45), (0.22, 0.5), (1, 0), (1, 1), (0, 0.5)],
    # a ray from the small triangle crosses only the large one's last edge
    [(2, 1), (3, 1), (2.5, 2), (0, -10), (10, 0), (0, 10)]])
def test_a_part_inside_another_found_from_its_box_and_last_edge(x):
    """Two triangles on nodes of their own, the first inside the second: two membranes on
    top of each other, found by the ray test from one node of the inner part (whichever
    stands for it)."""
    found = found_in(x, [(0, 1, 2), (3, 4, 5)])
    assert list(found) == ["inside"] and len(found["inside"]) == 1
    assert found["inside"][0] in (0, 1, 2)


def test_triangles_overlapping_by_twice_the_tolerance():
    """The triangle (0, 0), (1, 0), (0.5, -1) below, and two above on the node (0.5, -1e-8)
    inside it: not a hanging node (1e-8 off the edge, beyond 1e-8 of its shortest edge,
    about 0.5), but the angles at (0, 0) and (1, 0) overlap by about 2e-8 radians, twice
    the 1e-8 allowed."""
    x = [(0, 0), (1, 0), (0.5, -1e-8), (0.5, -1), (0.5, 1)]
    assert found_in(x, [(0, 3, 1), (0, 2, 4), (2, 1, 4)]) == {"angles": [0, 1]}


@pytest.mark.parametrize("theta", [0.1, 0.7, 1.3])
def test_a_hanging_node_far_from_the_origin(theta):
    """test_user_meshes' hanging node (the midpoint of the left square's right edge, a node
    of the right square's triangles only), scaled by 1e-3, turned by θ and moved to (1e6,
    1e6), the node computed as the mesher would, (x1 + x2)/2: its distance to the edge is
    round-off of 1e6 (about 1e-10), far beyond 1e-8 of the 1e-3 edges, and is allowed as
    such: one hanging node (and, at some angles, the angles of its edge's ends, which
    overlap by the same round-off over 1e-3 radians)."""
    base = np.array([(0, 0), (1, 0), (1, 1), (0, 1), (2, 0), (2, 1), (1, 0.5)])
    turn = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    x = 1e6 + 1e-3 * base @ turn.T
    x[6] = 0.5 * (x[1] + x[2])
    found = found_in(x, [(0, 1, 2), (0, 2, 3), (1, 4, 6), (4, 5, 6), (5, 2, 6)])
    assert found["hanging"] == [6] and set(found) <= {"hanging", "angles"}
    assert found.get("angles", [1, 2]) == [1, 2]


def test_a_node_near_an_edge_far_from_the_origin():
    """test_user_meshes' node near a triangle not its own, 2e-8 above the edge (four times
    the 5e-9 allowed for its edges of about 0.5), moved by (1e4, 1e4), whose round-off is
    about 2e-12: no hanging node, nothing found."""
    x = np.array([(0, 0), (1, 0), (0.5, 2e-8), (0.5, -1), (0.5, 1)]) + 1e4
    assert found_in(x, [(0, 3, 1), (0, 2, 4), (2, 1, 4)]) == {}


def test_a_crack_whose_copies_moved_apart_within_the_tolerance():
    """The crack of test_user_meshes from the corner (0, 0) through the centre c, the last
    triangle on its own copies of both, each copy moved 4.2e-9 off its twin in opposite
    directions (within 1e-8 of the edges, about 0.7: the same place): a crack, nothing
    found; the angles at a crack's nodes may differ by the twins' own distance."""
    x = np.array([(0, 0), (1, 0), (1, 1), (0, 1), (0.5, 0.5), (0, 0), (0.5, 0.5)])
    x[5] += (-3e-9, 3e-9)
    x[6] += (3e-9, -3e-9)
    assert found_in(x, [(0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 5, 6)]) == {}


def test_points_in_boxes_in_pieces():
    """The pairs (point, box) of `_in_boxes` are the same whether its candidate ranges are
    cut into pieces of 7 or not (the pieces bound its memory on large meshes; no mesh of
    the tests has 2^20 candidates), and `_ranges` cuts three ranges of 2 entries into one
    piece each (range k, its entries), skipping none."""
    rng = np.random.default_rng(1)
    points = rng.random((500, 2))
    low = 0.9 * rng.random((200, 2))
    high = low + 0.3 * rng.random((200, 2))
    whole = sorted(zip(*_in_boxes(points, low, high)))
    assert len(whole) > 1000
    assert sorted(zip(*_in_boxes(points, low, high, piece=7))) == whole
    pieces = [(np.asarray(k).tolist(), np.asarray(at).tolist())
              for k, at in _ranges(np.array([0, 10, 20]), np.array([2, 2, 2]), piece=2)]
    assert pieces == [([0, 0], [0, 1]), ([1, 1], [10, 11]), ([2, 2], [20, 21])]
