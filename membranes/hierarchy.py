"""Mesh hierarchy T_0 ⊂ T_1 ⊂ … ⊂ T_J by uniform (Plaza) refinement (DESIGN §6).

The computational mesh is the finest, T_J. For every level j ≥ 1 the parent map gives, for
each cell of T_j, the cell of T_{j-1} that contains it (`plaza_refine_data`); the multilevel
algebraic flux of a later stage walks these maps. Nested refinement keeps the polygon of T_0:
on the disk the computational domain does not follow the circle (DESIGN §9).
"""

from dataclasses import dataclass, field

import numpy as np

from .compiled import kernel, part


@dataclass
class Hierarchy:
    meshes: list                                  # [T_0, …, T_J]
    parent_cells: list = field(default_factory=list)  # parent_cells[j-1][c] = parent of c ∈ T_j

    @property
    def levels(self):
        return len(self.meshes) - 1

    @property
    def finest(self):
        return self.meshes[-1]


def refine_uniformly(mesh):
    """One uniform refinement of `mesh`; returns the fine mesh and its parent-cell map."""
    import ufl
    from dolfinx import cpp, mesh as dmesh
    mesh.topology.create_entities(1)
    fine, parent_cell, _ = cpp.refinement.plaza_refine_data(
        mesh._mesh, False, cpp.refinement.RefinementOptions.parent_cell_and_facet)
    domain = ufl.Mesh(mesh.ufl_domain().ufl_coordinate_element())
    fine = dmesh.Mesh(fine, domain)
    # plaza's parent map is in the order cells were created; mesh creation then reorders the
    # cells (for locality), and original_cell_index maps each cell back to that order
    created = np.asarray(fine.topology.original_cell_index, dtype=np.int64)
    return fine, np.asarray(parent_cell, dtype=np.int32)[created]


def build_hierarchy(coarse, levels):
    """T_0 = `coarse` and `levels` uniform refinements of it."""
    levels = int(levels)
    if levels < 0:
        raise ValueError(f"levels must be a non-negative integer, got {levels}")
    h = Hierarchy([coarse])
    for _ in range(levels):
        fine, parents = refine_uniformly(h.meshes[-1])
        h.meshes.append(fine)
        h.parent_cells.append(parents)
    return h


def barycentric(points, corners):
    """Barycentric coordinates of points (c, m, 2) in triangles with corners (c, 3, 2):
    shape (c, m, 3) (in a parent cell: the vertices of its children, multiples of 1/2)."""
    points, corners = np.ascontiguousarray(points, float), np.ascontiguousarray(corners, float)
    out = np.empty(points.shape[:2] + (3,))
    _barycentric(points, corners, out)
    return out


@part
def barycentric_point(x, y, v0x, v0y, v1x, v1y, v2x, v2y):
    """The barycentric coordinates (w0, w1, w2) of the point (x, y) in the triangle v0 v1 v2:
    Cramer's rule on its edges e1 = v1 - v0, e2 = v2 - v0 (the one formula: `barycentric`
    and the prolongation's compiled pass, membranes.nested, call it)."""
    e1x, e1y, e2x, e2y = v1x - v0x, v1y - v0y, v2x - v0x, v2y - v0y
    det = e1x * e2y - e1y * e2x
    dx, dy = x - v0x, y - v0y
    xi1 = (dx * e2y - dy * e2x) / det
    xi2 = (e1x * dy - e1y * dx) / det
    return 1.0 - xi1 - xi2, xi1, xi2


@kernel
def _barycentric(points, corners, out):
    """out[c, i] = barycentric_point of points[c, i] in the triangle corners[c]."""
    for c in range(points.shape[0]):
        v = corners[c]
        for i in range(points.shape[1]):
            out[c, i, 0], out[c, i, 1], out[c, i, 2] = barycentric_point(
                points[c, i, 0], points[c, i, 1], v[0, 0], v[0, 1], v[1, 0], v[1, 1],
                v[2, 0], v[2, 1])
