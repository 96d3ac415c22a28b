"""Nested iteration on the mesh hierarchy T_0 ⊂ T_1 ⊂ … ⊂ T_J (issue 6, item 1).

Solve on T_0, prolong the solution (u1, u2, λ) to T_1 as the initial guess there, solve, and so
on up to T_J, every level with the variant's own stopping test (exact, inexact: the relative
residual ≤ tol; adaptive: η_lin ≤ γ_lin η_disc, DESIGN §8). The initial guess of level j is
then within O(h_j) of its solution (the discretisation error of T_{j-1}), and the semismooth
Newton steps per level stay bounded as h → 0, where from the paper's X^0 = (g, 0, 0) they grow
(DESIGN §8's table: 8 to 28 steps).

**Prolongation.** P1 interpolation T_{j-1} → T_j. Plaza's uniform refinement keeps the
vertices of T_{j-1} and adds the edge midpoints, and every cell of T_j lies in its parent
cell of T_{j-1} (`Hierarchy.parent_cells`), so each fine vertex is found in the parent of any
fine cell that contains it, and its value is the P1 interpolant there: the barycentric
weights of the vertex in the parent, 1 at an old vertex and (1/2, 1/2) at an edge midpoint.
The weights are computed from the geometry and snapped to these exact values (ValueError if a
mesh is not such a refinement), so that the prolongation reproduces linear functions, and the
boundary values u1 = g, u2 = λ = 0, exactly. λ is nodal (DESIGN §2) and is prolonged the same
way. One sparse matrix per level (scipy CSR, n_j × n_{j-1}, in the P1 dof order of the levels'
spaces); the three fields are prolonged by it in turn. Serial, as the driver is.

The prolonged pair is not complementary where a coarse edge crosses the free boundary: at its
midpoint both w = u1 - u2 and λ are positive. Setting λ = 0 there (the membranes are apart) was
tried and not kept: on the disk (h0 = 0.2, J = 3, Newton steps on T_0..T_3) it saved a step
per level for exact Newton-min (4, 3, 3, 4 against 4, 4, 4, 5) and for Fischer–Burmeister on
T_3 (14 against 21), but cost steps where it counts more: adaptive 3, 3, 4, 6 against
3, 2, 3, 3, inexact 6, 8, 17, 42 against 6, 7, 16, 33. Projecting every prolonged pair onto
the complementarity set (λ = 0 where w ≥ κ λ, else u1 = u2 = their mean) did not help
Fischer–Burmeister either (exact, MUMPS, full steps: 10, 7, 8, 8 against 10, 7, 7, 7 on
T_0..T_3): the first step from it is the active set step, and FB's own steps then take
as long as before. FB meets the bound by its active-set steps instead (newton).

**Levels.** The problem of level j is the problem itself with its hierarchy truncated to
T_0..T_j (`level_problem`): same data, same scene declarations (exact solution, interface,
Poincaré constant of the domain).
"""

import dataclasses

import numpy as np

from .compiled import kernel
from .hierarchy import Hierarchy, barycentric_point
from .linear_solve import row_buffers, written_csr
from .meshes import p1_cells

SNAP = 1e-8      # barycentric weights farther than this from {0, 1/2, 1}: not a Plaza refinement


def level_problem(problem, j):
    """The problem on T_j: the same data with the hierarchy T_0..T_j (the problem itself for
    j = J)."""
    h = problem.hierarchy
    if not 0 <= j <= h.levels:
        raise ValueError(f"level {j} is not in 0..{h.levels}")
    if j == h.levels:
        return problem
    return dataclasses.replace(problem, hierarchy=Hierarchy(list(h.meshes[:j + 1]),
                                                            list(h.parent_cells[:j])))


def prolongation(V_coarse, V_fine, parent_cells):
    """The P1 interpolation matrix T_{j-1} → T_j (scipy CSR, n_fine × n_coarse) of the P1
    spaces V_coarse on T_{j-1} and V_fine on T_j; parent_cells[c] is the cell of T_{j-1} that
    holds the cell c of T_j (Hierarchy.parent_cells[j-1])."""
    n_f = V_fine.dofmap.index_map.size_local
    fine_cells, coarse_cells = p1_cells(V_fine), p1_cells(V_coarse)
    n_c = V_coarse.dofmap.index_map.size_local
    parent_cells = np.asarray(parent_cells)
    if parent_cells.shape != (len(fine_cells),):
        raise ValueError(f"{len(parent_cells)} parent cells for {len(fine_cells)} fine cells")
    fine, coarse = V_fine.mesh, V_coarse.mesh
    indptr = np.zeros(n_f + 1, dtype=np.int64)
    indices, data = row_buffers(2 * n_f)
    if not _interpolation_rows(
            fine_cells, fine.geometry.dofmap.array.reshape(-1, 3), fine.geometry.x,
            coarse_cells, coarse.geometry.dofmap.array.reshape(-1, 3), coarse.geometry.x,
            parent_cells, SNAP, indptr, indices, data):
        raise ValueError("the fine mesh is not a uniform refinement of the coarse one (a fine "
                         "vertex is neither a coarse vertex nor an edge midpoint)")
    return written_csr(indptr, indices, data, (n_f, n_c))


@kernel
def _interpolation_rows(fine_cells, fine_nodes, fine_x, coarse_cells, coarse_nodes, coarse_x,
                        parent_cells, snap, out_indptr, out_indices, out_data):
    """The CSR rows of the prolongation, one per fine vertex (the P1 dofs `fine_cells`, the
    geometry nodes `fine_nodes` of the same cells and local order, coordinates `fine_x`): in
    the parent of one fine cell that holds the vertex (the last listed, as `holding_cells`),
    its barycentric weights (`hierarchy.barycentric_point`: Cramer's rule on the parent's
    edges) snapped to {0, 1/2, 1} (the nearest multiple of 1/2), the nonzero ones stored with
    their coarse dofs in increasing order, rows written one after the other (out_indptr[v + 1]
    where row v ends). False if a weight is farther than `snap` from its snapped value, or the
    snapped weights are negative or do not sum to 1 (one compiled pass, where numpy passes
    over the weights and scipy's sorting took 0.13 s at 9.3e5 vertices)."""
    n_f = out_indptr.size - 1
    holder = np.empty(n_f, dtype=np.int64)
    local = np.empty(n_f, dtype=np.int64)
    for c in range(fine_cells.shape[0]):
        for a in range(3):
            if fine_cells[c, a] < n_f:
                holder[fine_cells[c, a]], local[fine_cells[c, a]] = c, a
    w = np.empty(3)
    stored = 0
    for v in range(n_f):
        c = holder[v]
        p = parent_cells[c]
        x = fine_x[fine_nodes[c, local[v]]]
        v0, v1, v2 = (coarse_x[coarse_nodes[p, 0]], coarse_x[coarse_nodes[p, 1]],
                      coarse_x[coarse_nodes[p, 2]])
        w[0], w[1], w[2] = barycentric_point(x[0], x[1], v0[0], v0[1], v1[0], v1[1], v2[0],
                                             v2[1])
        total = 0.0
        start = stored
        for a in range(3):
            snapped = np.round(2.0 * w[a]) / 2.0
            if not abs(w[a] - snapped) <= snap or snapped < 0.0:
                return False
            total += snapped
            if snapped != 0.0:
                if stored - start >= 2:
                    return False
                dof = coarse_cells[p, a]
                q = stored                  # insertion: the row's dofs in increasing order
                while q > start and out_indices[q - 1] > dof:
                    out_indices[q], out_data[q] = out_indices[q - 1], out_data[q - 1]
                    q -= 1
                out_indices[q], out_data[q] = dof, snapped
                stored += 1
        if total != 1.0:
            return False
        out_indptr[v + 1] = stored
    return True


def prolong(P, X):
    """(u1, u2, λ) of X ∈ R^{3 n_coarse} prolonged to R^{3 n_fine} by P."""
    n = P.shape[1]
    X = np.asarray(X, dtype=float)
    if X.shape != (3 * n,):
        raise ValueError(f"expected {3 * n} values (u1, u2, lam), got shape {X.shape}")
    return np.concatenate([P @ X[k * n:(k + 1) * n] for k in range(3)])
