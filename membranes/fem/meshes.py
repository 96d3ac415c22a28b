"""Computational domains on a communicator: the unit disk and square from gmsh, the cells of a
gmsh model (a generated domain, or a `.msh` file opened by `mesh_files`), and dolfinx meshes
given through the API or read from an XDMF file (§9, §12).

Every mesh is a dolfinx P1 triangular mesh with geometric dimension 2, partitioned by dolfinx on
the communicator it is given (default `MPI.COMM_WORLD`): gmsh meshes (or reads) on rank 0 only,
and dolfinx's `create_mesh` distributes the cells. No process holds the whole mesh afterwards.
`dolfinx.io.gmshio.read_from_msh` is broken in dolfinx 0.5.2, and its `model_to_mesh` assumes
a clean model (every node used, node tags 1..N, each cell in one physical group): nodes no cell
uses (a physical group covering part of the surfaces) crash it, and so does a surface in two
physical groups. So the triangles of a gmsh model's 2D physical groups (of every surface if it
has none; a generated disk or square, or an opened `.msh` file: `model_cells`) are taken
once each, on the nodes they use, and checked (no zero-area triangle, no triangle listed
twice, by its nodes or their places, no edge of three or more triangles, no fold: the two
triangles of an edge lie on its two sides; conforming (`conformity`): no hanging node, no
surfaces overlapping or left unjoined; the nodes in one plane z = const), and
dolfinx's `create_mesh` distributes them, without ghost cells (§12): plaza refinement of a
ghosted mesh gave two copies of a ghost cell on some processes (a file of two squares on 3
processes), and the estimators met facets of three cells.

**Reproducible partitions.** dolfinx partitions with PT-Scotch, which splits a graph with
several threads by default; its partitions then differ from run to run (on 3 and 4 processes
the parts themselves, on 2 which process gets which half). The matrices' orderings, and with
them BoomerAMG's hierarchies, block-Jacobi ILU(0) and the Krylov iterates, followed: the
same run on 2 processes could take another number of Newton steps and give another η
(BENCHMARKS.md, "Reproducible partitions on several processes").
`create_mesh` is therefore called with Scotch's documented SCOTCH_PTHREAD_NUMBER = 1 (unless
the user set it), under which the partition of a mesh on P processes is the same in every
run. The hierarchy is refined without redistribution, so it inherits T_0's partition.

A dolfinx mesh given through the API gets the same checks (`given_mesh`; an XDMF file's
cells are checked on rank 0 before dolfinx makes a mesh of them, `mesh_files`): its cells and
their nodes are gathered on rank 0 for them, as a file's mesh is read there, then let go;
the mesh is used as given, or made anew without ghost cells (`without_ghosts`) where it has
them (plaza refinement, and dolfinx's edges of a pinched mesh, failed on ghosts).

Bad input raises ValueError on every process with the same one-line message (rank 0 checks,
the message is broadcast).
"""

import contextlib
import math
import os
import signal
import sys

import numpy as np
from mpi4py import MPI

from ..model.problem import real_number
from . import conformity

GMSH_TRIANGLE = 2  # gmsh element type of the 3-node triangle
JOIN_NODES = "(its cells must share their nodes where they meet)"   # (not from gmsh)


@contextlib.contextmanager
def keeping_sigint():
    """Around an import of gmsh (4.8, also through dolfinx.io.gmshio): its first import sets
    SIGINT to its default, and only gmsh.finalize puts back the handler it found, where a gmsh
    session ran (rank 0). Ctrl-C would end the process at once, without the command line's
    clean-up (membranes.app.interrupts: staged outputs removed, one line). Puts back the
    handler found before the import. And during the import, which loads libgmsh (0.75-0.9 s
    here), gmsh's own `signal.signal(SIGINT, SIG_DFL)` is not carried out (it is handed the
    handler in place instead, which gmsh.finalize then puts back): put back only after it,
    the default killed a run interrupted in that window, silently (exit -2, a probe's)."""
    before = signal.getsignal(signal.SIGINT)
    setter = signal.signal

    def keep(signum, handler):
        return signal.getsignal(signum) if signum == signal.SIGINT else setter(signum, handler)
    signal.signal = keep
    try:
        yield
    finally:
        signal.signal = setter
        if before is not None and signal.getsignal(signal.SIGINT) is not before:
            signal.signal(signal.SIGINT, before)


@contextlib.contextmanager
def gmsh_session():
    with keeping_sigint():
        import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        yield gmsh
    finally:
        gmsh.finalize()


def target_size(h):
    """`h` as a positive finite float (the gmsh target size); ValueError otherwise."""
    h = real_number("mesh size h", h)    # (a bool is no number: True meshed at h = 1)
    if not np.isfinite(h) or h <= 0:
        raise ValueError(f"mesh size h must be a positive finite number, got {h}")
    return h


def on_rank0(comm, build, session=gmsh_session):
    """Run `build(gmsh)` in a gmsh session on rank 0 (`build(None)` for a `session` of
    contextlib.nullcontext: a file read without gmsh); it returns the coarse mesh as (cells,
    x) (`model_cells`), which dolfinx distributes on `comm` without ghost cells (module
    notes). A ValueError on rank 0 reaches every rank, any other error as a RuntimeError."""
    error, arrays = None, None
    with contextlib.ExitStack() as stack:
        if comm.rank == 0:
            try:                     # (gmsh failing to start too: the others wait below)
                arrays = build(stack.enter_context(session()))
            except Exception as e:   # (every process must leave the broadcast below)
                error = str(e) if isinstance(e, ValueError) else (type(e).__name__, str(e))
        error = comm.bcast(error, root=0)
        if isinstance(error, tuple):
            raise RuntimeError(f"reading the coarse mesh on rank 0 failed: {error[0]}: "
                               f"{error[1]}")
        if error is not None:
            raise ValueError(error)
        cells, x = arrays if comm.rank == 0 else \
            (np.empty((0, 3), dtype=np.int64), np.empty((0, 2)))
    return distribute(comm, cells, x)


def distribute(comm, cells, x):
    """dolfinx's mesh of the triangles `cells` (global indices of nodes, int64) on the nodes
    whose coordinates `x` this process holds (in blocks of consecutive indices, process by
    process), partitioned on `comm` without ghost cells (module notes). Collective."""
    from dolfinx.mesh import GhostMode, create_mesh
    with keeping_sigint():
        from dolfinx.io import gmshio
    with one_scotch_thread():
        return create_mesh(comm, cells, x, gmshio.ufl_mesh(GMSH_TRIANGLE, 2),
                           ghost_mode=GhostMode.none)


@contextlib.contextmanager
def one_scotch_thread():
    """SCOTCH_PTHREAD_NUMBER = 1 while dolfinx partitions (module notes: reproducible
    partitions), unless the user has set it; the environment is restored afterwards."""
    name = "SCOTCH_PTHREAD_NUMBER"
    if name in os.environ:
        yield
        return
    os.environ[name] = "1"
    try:
        yield
    finally:
        os.environ.pop(name, None)


def _shape(shape, h):
    def build(gmsh):
        gmsh.model.add(shape)
        if shape == "disk":
            gmsh.model.occ.addDisk(0.0, 0.0, 0.0, 1.0, 1.0)
        else:
            gmsh.model.occ.addRectangle(0.0, 0.0, 0.0, 1.0, 1.0)
        gmsh.model.occ.synchronize()
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        gmsh.model.addPhysicalGroup(2, surfaces, 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMin", 0.0)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", h)
        gmsh.model.mesh.generate(2)
        return model_cells(gmsh, f"the generated unit {shape}", conforming=True)
    return build


def unit_disk(h, comm=MPI.COMM_WORLD):
    """Unstructured mesh of the unit disk with target cell size h (§9): at most h, and at
    most the size gmsh gives the geometry's points, so that h above about 0.3 gives the same
    mesh (71 vertices)."""
    return on_rank0(comm, _shape("disk", target_size(h)))


def unit_square(h, comm=MPI.COMM_WORLD):
    """Unstructured mesh of (0, 1)² with target cell size h: at most h, and at most the size
    gmsh gives the corners, so that h above about 0.15 gives the same mesh (98 vertices)."""
    return on_rank0(comm, _shape("square", target_size(h)))


def structured_square(nx, ny, grading=1.0, comm=MPI.COMM_WORLD):
    """(0, 1)² cut into nx × ny rectangles, each split into two right triangles (dolfinx's
    create_unit_square), then mapped by (x, y) -> (x^p, y^p), p = `grading` ≥ 1: cells shrink
    towards the corner (0, 0). For stiff and extreme cases (§11): nx ≠ ny gives anisotropic
    cells, a small nx, ny a mesh of a handful of cells."""
    from dolfinx import mesh as dmesh
    for name, value in (("nx", nx), ("ny", ny)):
        if int(value) != value or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value}")
    grading = float(grading)
    if not (np.isfinite(grading) and grading >= 1.0):
        raise ValueError(f"grading must be a finite number >= 1, got {grading}")
    m = dmesh.create_unit_square(comm, int(nx), int(ny), dmesh.CellType.triangle,
                                 dmesh.GhostMode.none)
    m.geometry.x[:, :2] = m.geometry.x[:, :2] ** grading
    return m


def model_cells(gmsh, what, conforming=False):
    """(cells, x) of gmsh's current model (`what` names it in messages): its triangles in 2D
    physical groups (in every surface if it has none), each once, as rows of indices into x,
    the (n, 2) coordinates of the n nodes they use (module notes). ValueError for degenerate,
    repeated, overlapping or folded cells, for a mesh that is not conforming (`conformity`;
    not looked for where the model is `conforming`: one surface meshed by gmsh), and for nodes
    off one plane z = const (a plane z = c is taken as z = 0; nodes no triangle uses are not
    looked at)."""
    groups = gmsh.model.getPhysicalGroups(2)
    surfaces = sorted({int(e) for _, tag in groups
                       for e in gmsh.model.getEntitiesForPhysicalGroup(2, tag)}) if groups \
        else [tag for _, tag in gmsh.model.getEntities(2)]
    tags, nodes = [np.empty(0, dtype=np.int64)], [np.empty(0, dtype=np.int64)]
    for surface in surfaces:
        _, element_tags, element_nodes = gmsh.model.mesh.getElements(2, surface)
        tags += [np.asarray(t, dtype=np.int64) for t in element_tags]
        nodes += [np.asarray(n, dtype=np.int64) for n in element_nodes]
    tags, nodes = np.concatenate(tags), np.concatenate(nodes).reshape(-1, 3)
    _, first = np.unique(tags, return_index=True)          # an element in two surfaces
    nodes = nodes[np.sort(first)]
    if not len(nodes):
        raise ValueError(f"{what} has no triangles in its physical surfaces")
    node_tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(node_tags)
    node_tags, coords = np.asarray(node_tags)[order], coords.reshape(-1, 3)[order]
    used, cells = np.unique(nodes, return_inverse=True)
    at = np.minimum(np.searchsorted(node_tags, used), len(node_tags) - 1)
    if not np.array_equal(node_tags[at], used):
        raise ValueError(f"{what} has triangles on nodes it does not list")
    x, cells = coords[at], cells.reshape(-1, 3).astype(np.int64)
    return checked_cells(in_the_plane(x, what), cells, what, conforming)[:2]


def in_the_plane(x, what):
    """The (n, 2) coordinates (x, y) of the n nodes x (n, 3) of triangles (`what` names them
    in messages), which must lie in one plane z = const, taken as z = 0: ValueError if their
    z are not finite or differ by more than 1e-12 of the nodes' extent in the plane, plus
    the round-off of z's own size (8 ε max |z|: a plane moved to z = c by a computation).
    The tolerance is not relative to |z| alone: a mesh at z = 1e12 tilted by 0.4 rad passed
    that way, and was solved on its projection."""
    z = x[:, 2]
    extent = max(np.ptp(x[:, 0]), np.ptp(x[:, 1])) if len(x) else 0.0
    if not np.all(np.isfinite(z)):
        raise ValueError(f"{what} has non-finite node coordinates")
    if len(x) and np.ptp(z) > 1e-12 * extent + 8 * np.finfo(float).eps * np.abs(z).max():
        raise ValueError(f"{what} is 3D (its triangles' nodes have z from {z.min():g} to "
                         f"{z.max():g}, a spread of {np.ptp(z):.3g} over an extent of "
                         f"{extent:.3g} in the plane: not one plane z = const)")
    return np.ascontiguousarray(x[:, :2])


# The sizes a mesh's squares can take (`checked_cells`): coordinates whose squares (the areas,
# the edges' squared lengths) overflow, and triangles whose squared longest edge, times the
# 1e-12 of the area test, is no longer a normal double (sqrt(2.2e-308 / 1e-12) ≈ 1.5e-148).
LARGEST_COORDINATE = 1e150
SMALLEST_TRIANGLE = math.sqrt(sys.float_info.min / 1e-12)


def checked_cells(x, cells, what, conforming=False,
                  fix="(join surfaces with gmsh's fragment)"):
    """(cells, x, boundary edges), the triangles `cells` ((T, 3) indices into the (n, 2)
    coordinates `x`) checked as `model_cells` says (`what` names them in messages, `fix`
    ends that of a mesh that is not conforming; the conformity is not looked for where they
    are `conforming`), and their boundary edges ((m, 2) node pairs)."""
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} has non-finite node coordinates")
    size = np.abs(x).max(initial=0.0)
    if size > LARGEST_COORDINATE:
        raise ValueError(f"{what} has node coordinates up to {size:.3g}, beyond "
                         f"{LARGEST_COORDINATE:.0e}, whose squares overflow double precision: "
                         f"rescale the mesh")
    p = x[cells]
    if len(p):
        small = np.max([np.hypot(*(p[:, i] - p[:, i - 1]).T) for i in range(3)], axis=0).min()
        # (a triangle of size 0, its nodes on one point, is degenerate: below, not a scale)
        if 0.0 < small < SMALLEST_TRIANGLE:
            raise ValueError(f"{what} has triangles as small as {small:.3g} (longest edge), "
                             f"below {SMALLEST_TRIANGLE:.1e}, whose areas underflow double "
                             f"precision: rescale the mesh")
    flat = np.count_nonzero(degenerate(p))
    if flat:
        raise ValueError(f"{what} has {flat} degenerate triangle(s) (zero area or "
                         f"a repeated vertex)")
    # the same three nodes, or three nodes at the same places (a surface meshed twice)
    corners = np.sort(p.view([("x", float), ("y", float)])[..., 0], axis=1)
    corners = corners.view(float).reshape(-1, 6)
    corners = corners[np.lexsort(corners.T[::-1])]
    twice = np.count_nonzero((corners[1:] == corners[:-1]).all(axis=1))
    if twice:
        raise ValueError(f"{what} lists {twice} triangle(s) twice (overlapping "
                         f"surfaces?)")
    # edge i of a triangle: the one opposite its vertex i, from its lower node to its higher
    ends = np.sort(cells[:, [[1, 2], [2, 0], [0, 1]]], axis=2).reshape(-1, 2)
    _, first, edge, shared = np.unique(ends[:, 0] * len(x) + ends[:, 1], return_index=True,
                                       return_inverse=True, return_counts=True)
    if shared.max() > 2:
        raise ValueError(f"{what} has {np.count_nonzero(shared > 2)} edge(s) of "
                         f"three or more triangles (overlapping surfaces?)")
    # the two triangles of an edge lie on its two sides, unless the mesh folds over there
    a, b = x[ends[:, 0]], x[ends[:, 1]]
    d, e = b - a, p.reshape(-1, 2) - a
    side = np.sign(d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0])
    folded = np.count_nonzero(np.abs(np.bincount(edge, weights=side)) > 1.5)
    if folded:
        raise ValueError(f"{what} has {folded} edge(s) whose two triangles lie on the same "
                         f"side (a folded or tangled mesh)")
    edges = ends[first[shared == 1]]
    if not conforming:
        found = conformity.nonconforming_nodes(x, cells, edges)
        if conformity.total(found):
            raise ValueError(f"{what} is not conforming: {conformity.message(found)} "
                             f"{fix}")
    return cells, x, edges


def given_mesh(mesh, what="mesh", domain=None):
    """A dolfinx mesh given through the API (`scenes.square(mesh=...)`, `scenes.user`) as the
    coarse mesh T_0, checked as a file's mesh is (§2: P1 on a conforming triangulation in
    the plane; module notes): ValueError, the same on every process and naming it as
    `what`, unless it is a dolfinx Mesh of triangles with an affine (degree 1) geometry of
    dimension 2, or of dimension 3 with its nodes in one plane z = const (as gmshio's
    `model_to_mesh` makes a 2D model by default; `without_ghosts` makes it anew in 2D),
    whose cells pass `checked_cells`. For those checks its owned cells and their
    nodes (by the input indices it was created from: a vertex dolfinx made twice, where
    parts meet at it alone, is one node) are gathered on rank 0, as a file's mesh is read
    there, and let go after; the copies of a node on several processes must agree. `domain`
    (x, cells, boundary edges) ↦ what is wrong (None: nothing), run there too, checks the
    domain the cells cover (a scene's). Collective; returns the mesh."""
    from dolfinx.mesh import CellType, Mesh
    if not isinstance(mesh, Mesh):
        raise ValueError(f"{what} must be a dolfinx Mesh, got {type(mesh).__name__}")
    if mesh.topology.cell_type != CellType.triangle:
        raise ValueError(f"{what} is not a triangular mesh (cells: "
                         f"{mesh.topology.cell_type.name})")
    degree = mesh.ufl_domain().ufl_coordinate_element().degree()
    if degree != 1 or mesh.geometry.dim not in (2, 3):
        raise ValueError(f"{what} must have an affine geometry (P1 triangles in the plane), "
                         f"got degree {degree} in dimension {mesh.geometry.dim}")
    g = mesh.geometry
    local = g.dofmap.array.reshape(-1, 3)[:owned_cells(mesh)]
    used = np.unique(local)
    ids = np.asarray(g.input_global_indices, dtype=np.int64)
    parts = mesh.comm.gather((ids[local], ids[used], g.x[used]), root=0)   # (x, y, z)
    error = None
    if mesh.comm.rank == 0:
        cells, nodes, x = (np.concatenate([part[k] for part in parts]) for k in range(3))
        try:
            if not np.all(np.isfinite(x)):          # (every copy: the same words at any P)
                raise ValueError(f"{what} has non-finite node coordinates")
            nodes, first, copy = np.unique(nodes, return_index=True, return_inverse=True)
            moved = np.count_nonzero(np.any(x != x[first][copy], axis=1))
            if moved:
                raise ValueError(f"{what} has {moved} copies of nodes on several processes "
                                 f"at other places than the node's first copy")
            if not len(cells):
                raise ValueError(f"{what} has no cells")
            cells, x, edges = checked_cells(
                in_the_plane(x[first], what), np.searchsorted(nodes, cells), what,
                fix=JOIN_NODES)
            error = domain(x, cells, edges) if domain is not None else None
        except Exception as e:       # (every process must leave the broadcast below)
            error = str(e) if isinstance(e, ValueError) else (type(e).__name__, str(e))
    del parts
    error = mesh.comm.bcast(error, root=0)
    if isinstance(error, tuple):
        raise RuntimeError(f"checking {what} on rank 0 failed: {error[0]}: {error[1]}")
    if error is not None:
        raise ValueError(error)
    return mesh


def without_ghosts(mesh):
    """`mesh` itself if no process holds ghost cells and its geometry is 2D, else the same
    triangles distributed anew by dolfinx without ghost cells, on their nodes' (x, y)
    (module notes: plaza refinement of a ghosted mesh, as dolfinx's default
    GhostMode.shared_facet makes them, gave two copies of a ghost cell on 3 processes; a
    planar mesh of dimension 3, checked by `given_mesh`, is made 2D). Each process hands
    over its owned cells and geometry nodes only. Collective."""
    if mesh.geometry.dim == 2 and \
            not mesh.comm.allreduce(mesh.topology.index_map(2).num_ghosts, op=MPI.SUM):
        return mesh
    nodes = mesh.geometry.index_map()
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)[:owned_cells(mesh)]
    cells = np.asarray(nodes.local_to_global(cells.ravel()), dtype=np.int64).reshape(-1, 3)
    return distribute(mesh.comm, cells,
                       np.ascontiguousarray(mesh.geometry.x[:nodes.size_local, :2]))


def owned_cells(mesh):
    return mesh.topology.index_map(2).size_local


def cell_vertices(mesh):
    """Coordinates (c, 3, 2) of the vertices of the owned cells."""
    x = mesh.geometry.x[:, :2]
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)[:owned_cells(mesh)]
    return x[cells]


def on_boundary(mesh, cell_nodes, imap):
    """Bool over the local entries (owned and ghost) of a vertex-based numbering of `mesh`
    (P1 dofs, P1 geometry nodes): the vertex lies on ∂Ω (§2, §9). `cell_nodes` ((cells, 3)):
    the entries of each cell's vertices, in the cell's vertex order; `imap`: the numbering's
    dolfinx IndexMap. A facet lies on ∂Ω if exactly one cell of the whole mesh has it: every
    process counts the facets of its *owned* cells, the counts are added on each facet's owner
    and sent back to its ghosts, and the flags of the vertices of those facets are combined
    likewise (§12). Counting owned cells only makes the answer independent of the ghost mode:
    a facet on a process boundary is counted from both sides, one on the outer rim of a ghost
    layer (one local cell, a ghost) is not taken for ∂Ω, and every local copy of a boundary
    vertex is flagged, also one that only ghost cells hold. Collective."""
    from dolfinx import la
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim, tdim - 1)
    nc = owned_cells(mesh)
    c2f = mesh.topology.connectivity(tdim, tdim - 1).array.reshape(-1, 3)[:nc]
    count = la.vector(mesh.topology.index_map(tdim - 1))
    count.array[:] = np.bincount(c2f.ravel(), minlength=count.array.size)
    count.scatter_reverse(la.ScatterMode.add)
    count.scatter_forward()
    # the vertices of local facet i of a triangle are its vertices other than vertex i
    cells = cell_nodes[:nc]
    on = la.vector(imap)
    on.array[:] = 0.0
    for i in range(3):
        exterior = count.array[c2f[:, i]] == 1.0
        for j in range(3):
            if j != i:
                on.array[cells[exterior, j]] = 1.0
    on.scatter_reverse(la.ScatterMode.add)
    on.scatter_forward()
    return on.array > 0.0


def triangle_areas(p):
    """|K| of the triangles with vertex coordinates p ((c, 3, 2)): half the absolute cross
    product of two edges. The cell masses M_K = |K|/12 (I + 1 1ᵀ) of the DG1 algebra (§4, §6)
    use it."""
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def longest_edges(p):
    """h_K, the longest edge of the triangles with vertex coordinates p ((c, 3, 2))."""
    edges = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 1], p[:, 0] - p[:, 2]], axis=1)
    return np.sqrt((edges ** 2).sum(axis=2)).max(axis=1)


def smallest_altitudes(p):
    """a_K = 2 |K| / h_K, the smallest altitude of the triangles with vertex coordinates p
    ((c, 3, 2)): the scale a position's round-off ε |x| is measured against."""
    return 2.0 * triangle_areas(p) / longest_edges(p)


def offsets(p):
    """|x|_K / a_K, the largest coordinate of each triangle with vertex coordinates p
    ((c, 3, 2)) over its smallest altitude: ε times it is the rounding of its positions as a
    fraction of the cell (a mesh far from the origin for the size of its cells)."""
    return np.abs(p).max(axis=(1, 2), initial=0.0) / smallest_altitudes(p)


def degenerate(p):
    """Whether each triangle with vertex coordinates p ((c, 3, 2)) is degenerate: 2 |K| ≤
    1e-12 h_K² (zero area, a repeated vertex, or a sliver of that flatness)."""
    return 2.0 * triangle_areas(p) <= 1e-12 * longest_edges(p) ** 2


def cell_diameters(mesh):
    """Longest edge h_K of every owned cell."""
    return longest_edges(cell_vertices(mesh))


def stretches(p):
    """Longest edge over smallest altitude, h_K² / (2 |K|), of the triangles with vertex
    coordinates p ((c, 3, 2))."""
    return longest_edges(p) ** 2 / (2.0 * triangle_areas(p))


def mesh_size(mesh):
    """h = max_K h_K over all processes."""
    local = cell_diameters(mesh).max(initial=0.0)
    return mesh.comm.allreduce(local, op=MPI.MAX)


def mesh_counts(mesh):
    """(V, T, χ): the global numbers of vertices and triangles and the Euler characteristic
    V - E + T (collective; makes the edges)."""
    mesh.topology.create_entities(1)
    v, e, t = (mesh.topology.index_map(d).size_global for d in (0, 1, 2))
    return v, t, v - e + t
