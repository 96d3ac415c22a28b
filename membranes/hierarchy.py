"""Mesh hierarchy T_0 ⊂ T_1 ⊂ … ⊂ T_J by uniform (Plaza) refinement (DESIGN §6).

The computational mesh is the finest, T_J. For every level j ≥ 1 the parent map gives, for
each cell of T_j, the cell of T_{j-1} that contains it (`plaza_refine_data`); the multilevel
algebraic flux of a later stage walks these maps. Nested refinement keeps the polygon of T_0:
on the disk the computational domain does not follow the circle (DESIGN §9).
"""

from dataclasses import dataclass, field

import numpy as np


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
    v0 = corners[:, 0]
    e1, e2 = corners[:, 1] - v0, corners[:, 2] - v0                          # (c, 2)
    det = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])[:, None]
    d = points - v0[:, None]                                                 # (c, m, 2)
    xi1 = (d[..., 0] * e2[:, None, 1] - d[..., 1] * e2[:, None, 0]) / det   # Cramer's rule
    xi2 = (e1[:, None, 0] * d[..., 1] - e1[:, None, 1] * d[..., 0]) / det
    return np.stack([1.0 - xi1 - xi2, xi1, xi2], axis=2)
