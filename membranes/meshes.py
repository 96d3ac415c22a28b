"""Computational domains: the unit disk and the unit square from gmsh, and 2D gmsh files.

Every mesh is a dolfinx P1 triangular mesh with geometric dimension 2. gmsh is opened and
closed inside each function; `dolfinx.io.gmshio.read_from_msh` is broken in dolfinx 0.5.2, so a
`.msh` file is opened with gmsh and converted with `gmshio.model_to_mesh`, which keeps only the
cells of a physical group (a file without 2D physical groups gets one holding every surface).
"""

import contextlib
import os

import numpy as np
from mpi4py import MPI

from .compiled import kernel

_GMSH_TRIANGLE = 2  # gmsh element type of the 3-node triangle


@contextlib.contextmanager
def _gmsh_session():
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        yield gmsh
    finally:
        gmsh.finalize()


def _check_size(h):
    h = float(h)
    if not np.isfinite(h) or h <= 0:
        raise ValueError(f"mesh size h must be a positive finite number, got {h}")
    return h


def _to_dolfinx(gmsh, comm):
    from dolfinx.io import gmshio
    mesh, _, _ = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=2)
    return mesh


def _mesh_shape(shape, h, comm):
    """Mesh the unit disk or the unit square with gmsh, target cell size h."""
    h = _check_size(h)
    with _gmsh_session() as gmsh:
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
        return _to_dolfinx(gmsh, comm)


def unit_disk(h, comm=MPI.COMM_SELF):
    """Unstructured mesh of the unit disk with target cell size h (DESIGN §9)."""
    return _mesh_shape("disk", h, comm)


def unit_square(h, comm=MPI.COMM_SELF):
    """Unstructured mesh of (0, 1)² with target cell size h."""
    return _mesh_shape("square", h, comm)


def structured_square(nx, ny, grading=1.0, comm=MPI.COMM_SELF):
    """(0, 1)² cut into nx × ny rectangles, each split into two right triangles (dolfinx's
    create_unit_square), then mapped by (x, y) -> (x^p, y^p), p = `grading` ≥ 1: cells shrink
    towards the corner (0, 0) (the smallest and largest cell sizes differ by ~ p nx^(p-1)).
    For stiff and extreme cases (DESIGN §11): nx ≠ ny gives anisotropic cells of aspect ratio
    about max(nx, ny)/min(nx, ny), a small nx, ny a mesh of a handful of cells."""
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


def aspect_ratios(mesh):
    """Longest edge over smallest altitude, h_K² / (2 |K|), of every local cell (1.15 for an
    equilateral triangle, a/b for a right triangle with legs a ≥ b)."""
    p = _cell_vertices(mesh)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return cell_diameters(mesh) ** 2 / (2.0 * area)


def read_msh(path, comm=MPI.COMM_SELF):
    """Read a 2D triangular gmsh `.msh` file; ValueError names what is wrong with it."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f"mesh file {path!r} does not exist")
    if not os.path.isfile(path):
        raise ValueError(f"mesh file {path!r} is not a file")
    if not os.access(path, os.R_OK):
        raise ValueError(f"mesh file {path!r} is not readable")
    with _gmsh_session() as gmsh:
        try:
            gmsh.open(path)
        except Exception as e:
            raise ValueError(f"cannot read mesh file {path!r}: {e}") from None
        dim = gmsh.model.getDimension()
        if dim == 3 or gmsh.model.mesh.getElementTypes(3).size:
            raise ValueError(f"mesh file {path!r} is 3D; a 2D triangular mesh is required")
        types = list(gmsh.model.mesh.getElementTypes(2))
        if dim < 2 or not types:
            raise ValueError(f"mesh file {path!r} has no 2D cells")
        if types != [_GMSH_TRIANGLE]:
            names = [gmsh.model.mesh.getElementProperties(t)[0] for t in types]
            raise ValueError(f"mesh file {path!r} is not a linear triangular mesh "
                             f"(cells: {', '.join(names)})")
        _, coords, _ = gmsh.model.mesh.getNodes()
        z = np.abs(coords.reshape(-1, 3)[:, 2])
        if z.size and z.max() > 1e-12 * max(1.0, np.abs(coords).max()):
            raise ValueError(f"mesh file {path!r} is 3D (nodes off the plane z = 0)")
        if not np.all(np.isfinite(coords)):
            raise ValueError(f"mesh file {path!r} has non-finite node coordinates")
        if not gmsh.model.getPhysicalGroups(2):
            gmsh.model.addPhysicalGroup(2, [t for _, t in gmsh.model.getEntities(2)], 1)
        try:
            return _to_dolfinx(gmsh, comm)
        except Exception as e:
            raise ValueError(f"cannot convert mesh file {path!r}: {e}") from None


def p1_cells(V):
    """The dofs of every local cell of a P1 space V, shape (cells, 3), in the cells' vertex
    order."""
    ncells = V.mesh.topology.index_map(2).size_local
    return V.dofmap.list.array.reshape(-1, 3)[:ncells]


def holding_cells(cells, n):
    """For each of n vertices, one of the `cells` (c, 3) that has it (the last one listed)."""
    holder = np.empty(n, dtype=np.int64)
    holder[cells.ravel()] = np.repeat(np.arange(len(cells)), 3)
    return holder


def cells_by_vertex(cells, counts):
    """(ptr, order): the positions in the cells' array (cells (c, 3), flat: position 3 c + k
    is vertex k of cell c) grouped by vertex, ascending within each group, those of vertex a
    at order[ptr[a]:ptr[a + 1]] (counts: the number of cells at each vertex); a stable
    counting sort (`_counting_sort`), for the vertex patches of the flux equilibration and
    the P1 sparsity and boundary of discretisation.p1_assembly."""
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr, _counting_sort(np.ascontiguousarray(cells).reshape(-1), ptr)


@kernel
def _counting_sort(keys, ptr):
    """The positions 0 .. len(keys) - 1 grouped by key, ascending within each group (a stable
    counting sort; ptr (n + 1,) the groups' offsets, from the counts of the keys), as int32
    (3 ncells < 2^31: half the memory of int64)."""
    at = ptr[:-1].copy()
    order = np.empty(len(keys), dtype=np.int32)
    for i in range(len(keys)):
        order[at[keys[i]]] = i
        at[keys[i]] += 1
    return order


def _cell_vertices(mesh):
    """(ncells, 3, 2): the vertex coordinates of every local cell."""
    x = mesh.geometry.x[:, :2]
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)
    return x[cells[:mesh.topology.index_map(2).size_local]]


def cell_diameters(mesh):
    """Diameter of every local cell (the longest edge of the triangle): one compiled pass
    over the cells (`_longest_edges`)."""
    ncells = mesh.topology.index_map(2).size_local
    out = np.empty(ncells)
    _longest_edges(mesh.geometry.x, mesh.geometry.dofmap.array.reshape(-1, 3), out)
    return out


@kernel
def _longest_edges(x, cells, out):
    """out[c] = max over the edges (0, 1), (1, 2), (2, 0) of cell c of the edge length
    sqrt(dx² + dy²) (x: the vertex coordinates, 3 per row)."""
    for c in range(len(out)):
        longest = 0.0
        for i, j in ((0, 1), (1, 2), (2, 0)):
            dx = x[cells[c, i], 0] - x[cells[c, j], 0]
            dy = x[cells[c, i], 1] - x[cells[c, j], 1]
            longest = max(longest, np.sqrt(dx * dx + dy * dy))
        out[c] = longest


def mesh_size(mesh):
    """h: the largest cell diameter over all processes."""
    d = cell_diameters(mesh)
    return mesh.comm.allreduce(float(d.max()) if d.size else 0.0, op=MPI.MAX)
