"""The mesh hierarchy T_0, …, T_J by uniform refinement, and its P1 prolongations (§6, §9, §12).

Each level is dolfinx's plaza refinement of the one below, on the same communicator and without
redistribution: every process refines its own cells, so the parent of a local fine cell is a
local coarse cell (`plaza_refine_data(..., parent_cell_and_facet)`).

**Curved boundaries (§9).** Plaza puts a new vertex at the midpoint of every edge. On a domain
with a curved boundary the scene gives a projection onto the boundary curve (the disk:
x ↦ x/|x|), and every new boundary vertex is moved onto it, so that the polygon of T_J converges
to the domain instead of keeping the polygon of T_0. The boundary cells of T_j are then no longer
inside their parents; nothing below relies on geometric nesting:

* the prolongation P_j : P1(T_{j-1}) → P1(T_j) is *combinatorial*: the value at a fine vertex
  is the coarse value at the same vertex or the mean of the two ends of the coarse edge it
  halves (computed from the positions plaza gave, kept for the moved vertices). It reproduces
  constants, so the prolonged hat functions of T_{j-1} still form a partition of unity on T_j;
  it is made at its first use (`Hierarchy.prolongation`);
* the multilevel algebraic flux groups the cells of each mesh by their parents
  (`parent_cells`), which is a statement about cells, not about geometry.

Without a projection (polygons, gmsh files) the hierarchy is geometrically nested and P_j is the
usual interpolation.
"""

import time
from dataclasses import dataclass, field

import numpy as np
from mpi4py import MPI

from ..model.progress import reporter
from .discretisation import p1_space
from .meshes import cell_vertices, degenerate, offsets, on_boundary, without_ghosts


@dataclass
class Hierarchy:
    meshes: list                                      # [T_0, …, T_J]
    parent_cells: list = field(default_factory=list)  # parent_cells[j-1][c]: parent of c ∈ T_j
    projection: object = None                         # boundary projection, or None
    # the domain's name where a scene made T_0 ("disk", "square"), else None: two hierarchies
    # with the same name mesh the same domain (`Problem`'s exact solution and C_PF h_Ω)
    domain: object = None
    # unmoved[j-1]: the geometry nodes of T_j the projection moved and their positions
    # before (plaza's edge midpoints), or None: what `prolongation` reads instead
    unmoved: list = field(default_factory=list)
    # the P_j made so far, shared with the hierarchies of `up_to`
    made: list = field(default_factory=list, repr=False)

    @property
    def levels(self):
        return len(self.meshes) - 1

    @property
    def finest(self):
        return self.meshes[-1]

    def prolongation(self, j):
        """P_j, the PETSc Mat P1(T_{j-1}) → P1(T_j) (`prolongation`), made at its first use
        (with those before it): only nested iteration and the multilevel flux read them, so a
        run on T_J alone never makes them. Collective at that use (every process reaches it
        on the same code path)."""
        if not 1 <= j <= self.levels:
            raise ValueError(f"no prolongation P_{j} in a hierarchy of {self.levels} levels")
        for k in range(len(self.made) + 1, j + 1):
            self.made.append(prolongation(self.meshes[k - 1], self.meshes[k],
                                          self.parent_cells[k - 1], self.unmoved[k - 1]))
        return self.made[j - 1]

    @property
    def prolongations(self):
        """[P_1, …, P_J] (`prolongation`: each made at its first use)."""
        return [self.prolongation(j) for j in range(1, self.levels + 1)]

    def up_to(self, j):
        """The hierarchy T_0, …, T_j (shares the meshes, maps and prolongations)."""
        if j == self.levels:
            return self
        return Hierarchy(self.meshes[:j + 1], self.parent_cells[:j], self.projection,
                         self.domain, self.unmoved[:j], self.made)


def _refine(mesh):
    """Plaza refinement of `mesh` and its parent-cell map (local fine cell → local coarse)."""
    import ufl
    from dolfinx import cpp
    from dolfinx import mesh as dmesh
    mesh.topology.create_entities(1)
    fine, parent_cell, _ = cpp.refinement.plaza_refine_data(
        mesh._mesh, False, cpp.refinement.RefinementOptions.parent_cell_and_facet)
    fine = dmesh.Mesh(fine, ufl.Mesh(mesh.ufl_domain().ufl_coordinate_element()))
    # plaza's parent map is in the order this process created its cells; mesh creation then
    # reorders the cells (and may add ghost cells), and original_cell_index maps each cell back
    # to its place in the created cells of all processes, numbered process by process
    parent_cell = np.asarray(parent_cell, dtype=np.int32)
    offset = mesh.comm.exscan(len(parent_cell)) or 0
    owned = fine.topology.index_map(2).size_local
    created = np.asarray(fine.topology.original_cell_index, dtype=np.int64)[:owned] - offset
    # (decided on every process: raised on one alone, it left the others waiting)
    moved = bool(owned and (created.min() < 0 or created.max() >= len(parent_cell)))
    if mesh.comm.allreduce(moved, op=MPI.LOR):
        raise RuntimeError("plaza refinement moved cells between processes")
    return fine, parent_cell[created]


def _cell_dofs(V):
    return V.dofmap.list.array.reshape(-1, 3)


def barycentric(corners, points):
    """Barycentric coordinates (n, k, 3) of the points (n, k, 2) in the triangles (n, 3, 2)
    `corners`, in the corners' order. A vertex plaza made has the coordinates 0, 1/2 or 1 in
    its parent (a coarse vertex or an edge's midpoint): the callers round to those."""
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    d = points - corners[:, None, 0]
    det = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])[:, None]
    l1 = (d[..., 0] * e2[:, None, 1] - d[..., 1] * e2[:, None, 0]) / det
    l2 = (e1[:, None, 0] * d[..., 1] - e1[:, None, 1] * d[..., 0]) / det
    return np.stack([1.0 - l1 - l2, l1, l2], axis=-1)


def prolongation(coarse, fine, parents, unmoved=None):
    """P1 prolongation P : P1(coarse) → P1(fine) as a distributed PETSc matrix (rows: fine
    dofs, columns: coarse dofs), from the barycentric coordinates of each fine vertex in the
    parent of a cell holding it. Plaza's vertices are coarse vertices or edge midpoints, so the
    coordinates are 0, 1/2 or 1 and are rounded to those values (they are exact at the
    positions plaza gave: `unmoved` = (nodes, positions) restores those of the boundary
    vertices a projection moved); every cell holding a vertex gives the same row, so one cell
    per vertex is read. A row has one entry (1) or two (1/2, 1/2)."""
    from petsc4py import PETSc
    Vc, Vf = p1_space(coarse), p1_space(fine)
    ncf = fine.topology.index_map(2).size_local
    imf, imc = Vf.dofmap.index_map, Vc.dofmap.index_map
    # one (owned cell, local vertex k) per fine dof of the owned cells
    rows_local = _cell_dofs(Vf)[:ncf]
    at = np.full(imf.size_local + imf.num_ghosts, -1, dtype=np.int64)
    at[rows_local.ravel()] = np.arange(rows_local.size)
    dofs = np.flatnonzero(at >= 0).astype(np.int32)
    cell, k = np.divmod(at[dofs], 3)
    del at
    # its barycentric coordinates in the parent (geometry nodes and P1 dofs are both
    # vertex-based but numbered apart: the cell-local order k is shared)
    xc, xf = coarse.geometry.x[:, :2], fine.geometry.x[:, :2]
    if unmoved is not None:
        xf = xf.copy()
        xf[unmoved[0]] = unmoved[1]
    gc = coarse.geometry.dofmap.array.reshape(-1, 3)
    gf = fine.geometry.dofmap.array.reshape(-1, 3)
    bary = barycentric(xc[gc[parents[cell]]], xf[gf[cell, k]][:, None])[:, 0]   # (n, 3)
    bary = np.round(2.0 * bary) / 2.0
    keep = bary != 0.0
    cols = imc.local_to_global(_cell_dofs(Vc)[parents[cell]][keep])   # row by row
    ptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))]).astype(PETSc.IntType)
    P = PETSc.Mat().createAIJ(((imf.size_local, imf.size_global),
                               (imc.size_local, imc.size_global)), comm=fine.comm)
    P.setPreallocationNNZ((2, 2))
    P.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
    # a vertex on a process boundary is written by each process holding a cell of it, with
    # the same values
    P.setValuesIJV(ptr, np.asarray(cols, dtype=PETSc.IntType), bary[keep],
                   rowmap=np.asarray(imf.local_to_global(dofs), dtype=PETSc.IntType),
                   addv=PETSc.InsertMode.INSERT_VALUES)
    P.assemble()
    return P


def boundary_vertices(mesh):
    """Local geometry nodes on the boundary ∂Ω of `mesh` (owned and ghost; `meshes.on_boundary`,
    so that a ghost copy held only by ghost cells is found, and moved, too)."""
    g = mesh.geometry.dofmap.array.reshape(-1, 3)
    return np.flatnonzero(on_boundary(mesh, g, mesh.geometry.index_map()))


def refine(mesh, projection=None):
    """One uniform refinement: (fine mesh, parent cells, unmoved); new boundary vertices are
    moved by `projection` (points (m, 2) ↦ points (m, 2)) when it is given, and `unmoved` is
    (their geometry nodes, their positions before), else None (`prolongation`)."""
    fine, parents = _refine(mesh)
    unmoved = None
    if projection is not None:
        nodes = boundary_vertices(fine)
        unmoved = (nodes, fine.geometry.x[nodes, :2].copy())
        fine.geometry.x[nodes, :2] = projection(unmoved[1])
    return fine, parents, unmoved


def _rounded_offsets(mesh):
    """ε max_K |x|_K / a_K over the owned cells of `mesh` and all processes: the rounding of
    the positions as a fraction of a cell's altitude a_K. Each uniform refinement halves
    the altitudes and so doubles it. Collective."""
    local = float(offsets(cell_vertices(mesh)).max(initial=0.0))
    return np.finfo(float).eps * mesh.comm.allreduce(local, op=MPI.MAX)


def _check_resolved(fine, j):
    """Refuse a refinement whose new vertices, rounded to the double nearest the midpoint of
    an edge, made degenerate triangles (`meshes.degenerate`, the test of a mesh file's
    cells): a mesh far from the origin for the size of its cells (a unit square of cells
    0.0625 moved by 1e14, refined twice: the multilevel flux's set-up met a singular
    Jacobian). Collective."""
    p = cell_vertices(fine)
    flat = fine.comm.allreduce(np.count_nonzero(degenerate(p)), op=MPI.SUM)
    if flat:
        size = fine.comm.allreduce(float(np.abs(p).max(initial=0.0)), op=MPI.MAX)
        raise ValueError(f"refinement {j} of the mesh made {flat} degenerate triangle(s): "
                         f"its coordinates, up to {size:.3g}, are too far from the origin "
                         f"for the size of its cells in double precision; translate the "
                         f"mesh towards the origin")


def build_hierarchy(coarse, levels, projection=None, domain=None, progress=None):
    """T_0 = `coarse` and `levels` uniform refinements of it (§6), new boundary vertices moved
    onto the curve by `projection` (§9); `domain` names the domain T_0 meshes (scenes only).
    A coarse mesh with ghost cells is refined as `meshes.without_ghosts` makes it anew.
    `progress`: one line per refinement, as `solve`'s (`model.progress.reporter`: True for
    stderr, or a callable; process 0 writes), since refining is a long silent phase on fine
    meshes (dolfinx's mesh creation costs more than linear time, BENCHMARKS.md)."""
    levels = int(levels)
    if levels < 0:
        raise ValueError(f"levels must be a non-negative integer, got {levels}")
    say = reporter(progress, coarse.comm)
    if levels:                                  # (plaza refinement needs it, `meshes`)
        coarse = without_ghosts(coarse)
    h = Hierarchy([coarse], projection=projection, domain=domain)
    # (only where the rounding is not negligible: a vertex moved by well under its cells'
    # altitudes leaves no triangle degenerate, and most meshes are checked at no cost)
    rounding = _rounded_offsets(coarse) if levels else 0.0
    for j in range(1, levels + 1):
        t = time.perf_counter()
        fine, parents, unmoved = refine(h.meshes[-1], projection)
        if rounding * 2 ** j > 1e-6:
            _check_resolved(fine, j)
        h.meshes.append(fine)
        h.parent_cells.append(parents)
        h.unmoved.append(unmoved)
        if say is not None:
            say(f"refinement {j} of {levels}: {fine.topology.index_map(0).size_global:,} "
                     f"vertices in {time.perf_counter() - t:.2f} s")
    return h


def onto_unit_circle(points):
    """The projection of the unit disk's boundary vertices onto the circle (§9)."""
    r = np.sqrt((points ** 2).sum(axis=1))
    return points / r[:, None]
