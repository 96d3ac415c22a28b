"""Is a file's mesh a conforming mesh of one domain? (§9, §12: P1 on a triangulation of Ω)

`meshes` checks single cells and edges first: no zero-area triangle, none listed twice, no
edge of three triangles, no fold (the two triangles of an edge on one side of it). Triangles
that pass can still be no triangulation of a domain, and dolfinx reads them silently. Each
of these comes from a mistake a user makes in gmsh, and each makes another problem, which
the bound would then certify:

- a hanging node, a vertex inside a neighbour's edge: that edge is a boundary, held at g;
- two surfaces meshed on their own nodes (no `fragment`) along a common curve, its nodes
  twice at the same places or interleaved: the mesh is cut along the curve, held at g;
- two such surfaces overlapping, crossing, or one inside the other: two membranes lie on
  top of each other.

All show on the boundary, so all four checks below look at the boundary edges (m of them)
and their end nodes, never at every triangle: their cost is that of the m edges (k-d
trees) and one pass over the cells, whatever the cells' shapes, but for many long
boundary edges close together (thousands of parallel slivers apart, nested rings), whose
searches meet each other's edges. With L the shorter of the two edges compared (a node's
own: its shortest boundary edge), a node is *on* an edge within 1e-8 L (plus the
coordinates' round-off).

1. A boundary node on a boundary edge it does not end. At one of the edge's ends, it is a
   node at the place of another: the two faces of a crack (gmsh's Crack plugin duplicates a
   slit's nodes) if the two lie in one connected mesh, two parts not joined if not.
2. Two boundary edges that cross.
3. A connected part of the mesh inside another (ray casting through the other's boundary).
4. At a boundary node, two of its triangles' angles overlapping (a tangle that shares its
   nodes). The nodes at one place that check 1 takes for a crack's faces count as one node
   here: a crack's faces lie on its two sides, the angles of their triangles apart; a strip
   wound onto itself, its nodes where those of its start are, overlaps there.

A mesh that wraps twice around a domain without a boundary crossing is not found.
"""

import itertools

import numpy as np

from .segments import ranges

TOL = 1e-8      # relative to the shorter edge compared: a node on an edge, an angle


# what each kind of node found says, for the error message
FOUND = {"hanging": "on another boundary edge (a hanging node, or a seam of surfaces meshed "
                    "on nodes of their own, its nodes at different places)",
         "apart": "at the place of a node of a part of the mesh not joined to theirs (surfaces "
                  "meshed on nodes of their own)",
         "crossing": "on boundary edges that cross (overlapping surfaces)",
         "inside": "inside another part of the mesh (overlapping surfaces)",
         "angles": "where triangles overlap"}


def nonconforming_nodes(x, cells, edges):
    """{kind: boundary nodes} of the kinds of `FOUND` (checks 1-4 of the module notes;
    check 1 gives "hanging" and "apart"): the boundary nodes (ends of `edges`, the (m, 2)
    boundary edges, indices into the (n, 2) coordinates x; `cells` the (T, 3) triangles)
    that show the mesh is no conforming mesh of one domain. All empty for a conforming
    mesh, the faces of cracks included."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    a, b = x[edges[:, 0]], x[edges[:, 1]]
    length = np.hypot(*(b - a).T)
    own = np.full(len(x), np.inf)                 # a boundary node's shortest boundary edge
    np.minimum.at(own, edges.ravel(), np.repeat(length, 2))
    round_off = 8 * np.finfo(float).eps * np.abs(x).max()
    links = coo_matrix((np.ones(2 * len(cells)), (cells[:, :2].ravel(), cells[:, 1:].ravel())),
                       shape=(len(x),) * 2)
    parts, part = connected_components(links, directed=False)
    found = dict.fromkeys(FOUND, np.empty(0, dtype=np.int64))
    found["hanging"], found["apart"], twins = _on_edges(x, edges, length, own, round_off, part)
    found["crossing"] = _crossing(x, edges, length, own, round_off)
    if parts > 1:
        found["inside"] = _inside_other_parts(x, edges, part, parts)
    pairs = coo_matrix((np.ones(len(twins)), twins.T), shape=(len(x),) * 2)
    place = connected_components(pairs, directed=False)[1]      # twins: one place
    slack = np.full(len(x), TOL)
    slack[twins.ravel()] = 3 * TOL + 2 * round_off / own[twins.ravel()]
    found["angles"] = _overlapping_angles(x, cells, own < np.inf, place, slack)
    return found


def total(found):
    """How many nodes `nonconforming_nodes` found, each once."""
    return len(np.unique(np.concatenate(list(found.values()))))


def message(found):
    """What `nonconforming_nodes` found, in words: its count, then each kind's."""
    kinds = [f"{len(np.unique(nodes))} {FOUND[kind]}" for kind, nodes in found.items()
             if len(nodes)]
    return f"{total(found)} boundary node(s): {'; '.join(kinds)}"


def _pairs(tree, centres, radii, alone=0):
    """(i, j): the tree's points j within radii[i] of centres[i], for the centres with more
    than `alone` of them (a k-d tree of scipy's)."""
    within = tree.query_ball_point(centres, radii, return_length=True)
    more = np.flatnonzero(within > alone)
    near = tree.query_ball_point(centres[more], radii[more])
    i = np.repeat(more, within[more])
    return i, np.fromiter(itertools.chain.from_iterable(near), dtype=np.int64, count=len(i))


def _on_edges(x, edges, length, own, round_off, part):
    """Check 1: boundary nodes on a boundary edge they do not end: inside it ("hanging"),
    and at the place of its end in a part not joined to theirs ("apart"); and a crack's
    faces, (k, 2) pairs of twins (node, end at its place) in one part. A node on a segment
    lies within half its length of its midpoint."""
    from scipy.spatial import cKDTree
    nodes = np.unique(edges)
    a, b = x[edges[:, 0]], x[edges[:, 1]]
    edge, node = _pairs(cKDTree(x[nodes]), (a + b) / 2,
                        length * (0.5 + TOL) + round_off, alone=2)
    node = nodes[node]
    keep = (edges[edge, 0] != node) & (edges[edge, 1] != node)
    edge, node = edge[keep], node[keep]
    d, q = b[edge] - a[edge], x[node] - a[edge]
    t = np.clip((q * d).sum(axis=1) / (d * d).sum(axis=1), 0.0, 1.0)
    tol = TOL * np.minimum(own[node], length[edge]) + round_off
    on = np.hypot(*(t[:, None] * d - q).T) <= tol
    end = edges[edge, (t > 0.5).astype(int)]
    twin = np.hypot(*(x[end] - x[node]).T) <= tol
    joined = part[node] == part[end]
    crack = on & twin & joined
    return node[on & ~twin], node[on & twin & ~joined], np.c_[node[crack], end[crack]]


def _crossing(x, edges, length, own, round_off):
    """Check 2: the ends of boundary edges that cross. Where two edges cross, the shorter
    one's midpoint lies within the longer one's length of the longer one's midpoint. An end
    on the other edge's line (a common end, or one that check 1 finds) is no crossing; *on*
    as in check 1, with the end's own shortest edge: an end 1e-9 off a line, its edge to
    there 0.7 long but another of 0.01, is no hanging node and must cross."""
    from scipy.spatial import cKDTree
    a, b = x[edges[:, 0]], x[edges[:, 1]]
    mid = (a + b) / 2
    e, f = _pairs(cKDTree(mid), mid, length * (1 + TOL) + round_off, alone=1)
    keep = (length[f] < length[e]) | ((length[f] == length[e]) & (f > e))
    e, f = e[keep], f[keep]

    def sides(e, f):
        """Which side of edge e each end of edge f lies on: +1, -1, or 0 if on its line."""
        d = (b[e] - a[e]) / length[e][:, None]
        out = []
        for end in edges[f].T:
            q = x[end] - a[e]
            dist = d[:, 0] * q[:, 1] - d[:, 1] * q[:, 0]
            tol = TOL * np.minimum(length[e], own[end]) + round_off
            out.append(np.where(np.abs(dist) <= tol, 0, np.sign(dist)))
        return out[0] * out[1] < 0

    cross = sides(e, f) & sides(f, e)
    return np.unique(edges[np.r_[e[cross], f[cross]]])


def _inside_other_parts(x, edges, part, parts):
    """Check 3: for every connected part, one boundary node of it that lies inside another
    part: a ray from it in +x crosses that part's boundary edges an odd number of times.
    (A part inside another's hole crosses it an even number of times: it is read.) Only the
    parts whose bounding box holds the node are looked at, so that many small parts side
    by side cost little (not a loop over the parts, each through all edges: quadratic);
    edges and pairs in pieces (`_ranges`), in bounded memory."""
    rep = np.full(parts, -1)
    rep[part[edges[:, 0]]] = edges[:, 0]
    has = np.flatnonzero(rep >= 0)                              # parts with an edge
    owner = part[edges[:, 0]]
    order = np.argsort(owner, kind="stable")
    owner, a, b = owner[order], x[edges[order, 0]], x[edges[order, 1]]
    first = np.searchsorted(owner, np.arange(parts))              # a part's edges, in order
    count = np.diff(np.r_[first, len(owner)])
    low, high = np.full((parts, 2), np.inf), np.full((parts, 2), -np.inf)
    np.minimum.at(low, owner, np.minimum(a, b))
    np.maximum.at(high, owner, np.maximum(a, b))
    node, box = _in_boxes(x[rep[has]], low, high)                 # rep[has[node]] in box
    node = has[node]
    keep = node != box
    node, box = rep[node[keep]], box[keep]
    found = []
    for k, at in _ranges(first[box], count[box]):
        px, py = x[node[k]].T
        straddle = (a[at, 1] > py) != (b[at, 1] > py)
        k, at, px, py = k[straddle], at[straddle], px[straddle], py[straddle]
        cut = a[at, 0] + (py - a[at, 1]) * (b[at, 0] - a[at, 0]) / (b[at, 1] - a[at, 1])
        odd = np.bincount(k[cut > px], minlength=len(box)) % 2 == 1
        found.append(node[odd])
    return np.concatenate(found + [np.empty(0, dtype=np.int64)])


def _in_boxes(points, low, high, piece=1 << 20):
    """(i, j): the points i in the boxes low[j] <= p <= high[j]. A box's points are looked
    for in the smallest of: its range on the x axis, on the y axis (points sorted on each),
    or the square about it (a k-d tree's, max norm); a grid of small boxes takes the square,
    thin ones along an axis an axis. In pieces of about `piece` candidates."""
    from scipy.spatial import cKDTree
    order = np.argsort(points, axis=0, kind="stable")
    begin, count = [], []
    for k in (0, 1):
        on = points[order[:, k], k]
        begin.append(np.searchsorted(on, low[:, k], side="left"))
        count.append(np.maximum(np.searchsorted(on, high[:, k], side="right") - begin[k], 0))
    tree = cKDTree(points)
    real = np.all(low <= high, axis=1)                  # a part with no edge: no box
    centre, radius = np.zeros_like(low), np.zeros(len(low))
    centre[real] = (low[real] + high[real]) / 2
    radius[real] = (high[real] - low[real]).max(axis=1) / 2
    count.append(np.where(real, tree.query_ball_point(centre, radius, p=np.inf,
                                                     return_length=True), 0))
    way = np.argmin(count, axis=0)
    out_i, out_j = [np.empty(0, dtype=np.int64)], [np.empty(0, dtype=np.int64)]

    def keep(i, j):
        inside = np.all((points[i] >= low[j]) & (points[i] <= high[j]), axis=1)
        out_i.append(i[inside])
        out_j.append(j[inside])

    for k in (0, 1):
        box = np.flatnonzero(way == k)
        for j, at in _ranges(begin[k][box], count[k][box], piece):
            keep(order[at, k], box[j])
    box = np.flatnonzero(way == 2)
    cut = np.searchsorted(np.cumsum(count[2][box]), np.arange(piece, count[2][box].sum(), piece))
    for some in np.split(box, np.unique(cut)):
        if len(some):
            near = tree.query_ball_point(centre[some], radius[some], p=np.inf)
            keep(np.fromiter(itertools.chain.from_iterable(near), dtype=np.int64,
                             count=count[2][some].sum()),
                 np.repeat(some, count[2][some]))
    return np.concatenate(out_i), np.concatenate(out_j)


def _ranges(begin, count, piece=1 << 20):
    """Pieces (k, at) of the ranges at = begin[k], …, begin[k] + count[k] - 1, k = 0, 1, …,
    whole ranges of about `piece` elements together (bounded memory)."""
    end = np.cumsum(count)
    k = 0
    while k < len(count):
        stop = max(int(np.searchsorted(end, end[k] - count[k] + piece, side="right")), k + 1)
        yield np.repeat(np.arange(k, stop), count[k:stop]), ranges(begin[k:stop], count[k:stop])
        k = stop


def _overlapping_angles(x, cells, boundary, place, slack):
    """Check 4: boundary nodes where two of their triangles' angles overlap: each
    triangle's angle at a node is the arc from one edge's direction to the other's; at a
    node, sorted by their start, each must end before the next starts (within TOL radians,
    the angle seen from the shorter edge that 1e-8 of it subtends), around the full turn.
    Nodes of one `place` (twins) are one node; `slack` is the overlap allowed at a node
    (TOL; at twins, also the turn of the edges by the up to 1e-8 of them between twins)."""
    at = np.argwhere(boundary[cells])                    # (cell, corner) at a boundary node
    cell, corner = at[:, 0], at[:, 1]
    p = x[cells[cell]]
    here = p[np.arange(len(cell)), corner]
    u = p[np.arange(len(cell)), (corner + 1) % 3] - here
    v = p[np.arange(len(cell)), (corner + 2) % 3] - here
    turn = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    ccw = turn[:, None] > 0
    u, v = np.where(ccw, u, v), np.where(ccw, v, u)        # from u to v anticlockwise
    start = np.arctan2(u[:, 1], u[:, 0]) % (2 * np.pi)
    span = np.arctan2(np.abs(turn), (u * v).sum(axis=1))
    node = cells[cell, corner]
    order = np.lexsort((start, place[node]))
    node, start, span = node[order], start[order], span[order]
    new = place[node][1:] != place[node][:-1]
    first, last = np.r_[True, new], np.r_[new, True]
    # the next angle's start at the place; for its last angle, the first's a full turn on
    after = np.r_[start[1:], 0.0]
    after[last] = start[first] + 2 * np.pi
    over = np.unique(place[node[start + span > after + slack[node]]])
    return np.flatnonzero(np.isin(place, over) & boundary)
