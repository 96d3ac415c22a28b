"""The multilevel algebraic flux σ_α,alg on the distributed mesh hierarchy (§6, §9, §12).

Given the lifted residual r = r_αh ∈ DG1(T_J) (§4), σ_alg ∈ RT_1(T_J) with ∇·σ_alg = r on every
cell, to round-off, after Papež, Rüde, Vohralík and Wohlmuth: a coarse solve and, for
j = 1..J, mixed RT_1 × DG1 problems on the patches of the vertices of T_{j-1}, meshed by the
cells of T_j, whose fluxes are moved to T_J and added.

**Curved boundaries (§9).** On the disk the new boundary vertices of each level are moved onto
the circle, so a boundary cell of T_j is not inside its parent. Each cell K of T_j is instead
tied to its parent K' by the *combinatorial map* G_K : K → K̂ ⊂ K', the affine map that sends
the vertices of K to where plaza created them (coarse vertices and midpoints of coarse edges,
`Hierarchy.prolongations` applied to the coarse coordinates), K̂ one of the four quarters of K'
(|K̂| = |K'|/4). Composing these maps level by level gives the map of a cell of T_J into its
ancestor in T_j, and everything below is transported along them:

* a field σ ∈ RT_1(T_{j-1}) moves to T_j by the contravariant Piola transform along G_K,
  σ_K(x) = det(DG_K) DG_K⁻¹ σ(G_K(x)). It lies in RT_1(K), its normal traces agree across
  every facet of T_j (two neighbours map their facet onto the same half of a coarse facet, with
  the same parametrisation), and ∇·σ_K = (|K̂|/|K|) (∇·σ)∘G_K. In dof terms it is the usual
  RT interpolation into the *unmoved* quarter K̂: the matrix `rt_prolongation`, computed on the
  reference cell from the child's position in its parent and the dof transformations;
* divergences move with the same law, T q := (|K̂|/|K|) q∘G_K for q ∈ DG1(T_{j-1}), which
  preserves integrals over every coarse cell, and composes like the maps;
* Π̃_j, the "L² projection onto DG1(T_j)" of §6 seen from T_J, is the L² projection on each
  cell K_j of T_j of the function transported there: Π̃_j x ∈ DG1(T_j) with
  (Π̃_j x, q)_{K_j} = Σ_{K ⊂ K_j} (x, q∘G)_K for q ∈ P1(K_j) (its moments are those of x against
  the DG1(T_j) basis prolonged combinatorially, R_jᵀ b(x)). Q_j := T Π̃_j is then a projection
  on DG1(T_J) that preserves integrals over the cells of T_j, with Q_j Q_{j-1} = Q_{j-1},
  Q_{j-1} Q_j = Q_{j-1}, Q_J = I. On a nested mesh (the square) these are the plain L²
  projections and the plain interpolation, and the construction is the paper's.

**The construction.** ψ_{j,a} are the hat functions of T_j prolonged to T_J (combinatorial P1
prolongations, a partition of unity on T_J).

1. ρ_0 ∈ P1(T_0) ∩ H¹_0 with (∇ρ_0, ∇ψ_{0,a})_{T_J} = (r, ψ_{0,a})_{T_J}: the Galerkin coarse
   matrix Pᵀ S_J P (P = P_J ⋯ P_1), factorised once by MUMPS.
2. For j = 1..J and each vertex a of T_{j-1}, with x_a = r ψ_{j-1,a} - ∇ρ_0·∇ψ_{j-1,a} on T_J:
   on the patch of a (the cells of T_j whose parent contains a) the mixed problem of §5 with
   target 0 (minimal ‖σ‖) and divergence e_j^a = Π̃_j x_a - T Π̃_{j-1} x_a ∈ DG1(T_j)
   (Π̃_0 := 0), zero normal flux on the patch boundary off ∂Ω, zero mean if a ∉ ∂Ω.
   Interior patches are compatible: for j = 1, ∫ e_1^a = ∫_{T_J} x_a = 0 by the coarse solve;
   for j ≥ 2 both terms have the integral of x_a over every cell of T_{j-1}.
3. σ_alg = Σ_j (Piola transfer to T_J of Σ_a σ_j^a). Its divergence on T_J is
   Σ_j (Q_j - Q_{j-1}) Σ_a x_a = Σ_j (Q_j - Q_{j-1}) r = Q_J r = r (Σ_a ψ_{j-1,a} = 1,
   Σ_a ∇ψ_{j-1,a} = 0): exact, with or without moved vertices.

**The data by corners.** Everything in step 2 acts within one cell K' of T_{j-1} (the moments
on its descendants, Π̃_j, Π̃_{j-1}), and there ψ_{j-1,a} is the hat function λ_m of one of
K''s vertices m, or zero. So the data of all patches of a level come from three fields: for
m = 0, 1, 2 the moments on T_j of r λ_m - ∇ρ_0·∇λ_m, λ_m the broken function that is, on every
cell, the hat of vertex m of its ancestor in T_{j-1}; a patch of colour c takes, on each cell,
the field of its parent's vertex of colour c. On T_J these moments are B (the data form with a
broken DG1 ψ, cellwise) applied to β (`child_positions`: the parent's hats at a cell's
vertices). Level j - 1's follow from level j's: a hat of a cell's ancestor in T_{j-2} is, on
each cell K' of T_{j-1}, the combination of K''s own parent hats given by β of K', the same on
all of K''s descendants; so restricting level j's moments to T_{j-1} (E_jᵀ, which level j's
T Π̃_{j-1} needs anyway) and mixing them by β of the cells of T_{j-1}, 3 × 3 per cell, gives
them. Per level the work is that of its own mesh.

**Round-off, accounted for.** The patches are solved with dense inverses of their classes'
blocks, and the residual of such a solve grows with the block's condition: the defect
d = ∇·σ_alg - r ∈ DG1(T_J) is at round-off, but on strongly graded meshes it grows like
(aspect ratio)² ε of the right-hand sides (measured 8.9e-8 at aspect ratio 1.5e4), beyond
the check of `divergence`. So the defect is not assumed zero: its DG1 moments b_K, which the
check assembles anyway, give ‖d‖_K² = b_Kᵀ M_K⁻¹ b_K exactly (d ∈ DG1), and ‖d‖² (`defect_sq`)
enters the bound as the remainder ρ_α = -d_α of §6 (theory §6, `Estimators.remainder_of`).
The check then only catches a wrong block (`divergence.ACCOUNTED_TOLERANCE`).

**Distributed set-up (§12).** Plaza refinement without redistribution keeps children on their
parents' process, so all the DG1 moment algebra (restrictions R_jᵀ, the 3×3 cell masses) is
process-local numpy/scipy on the owned cells. The patches of level j are the coloured groups of
a `PatchSystems` on T_j, one group per colour of a vertex colouring of T_{j-1} (no two vertices
of one colour share a cell of T_{j-1}, so no two of their patches share a cell of T_j), set
up once. Their right-hand sides are DG moments and only σ is wanted, so each class of
congruent patches keeps the block Y S⁻¹ of its inverse from the DG rows to the RT unknowns
(`PatchSystems(rhs="divergence", solution="flux")`). The RT transfers are distributed PETSc
matrices.

**Cost.** Level j's patches have about 3 × dim(RT_1 × DG1)(T_j) unknowns in patches of ~24
cells, so all levels together about 4 × dim(T_J) (σ_disc: 3 ×); the coarse system has the size
of P1(T_0). On a uniformly refined hierarchy most coarse patches of level j ≥ 2 are translates
and share their block, and the levels share one store of classes: a scaled copy of an earlier
level's patch reuses that class's inverse (`classes`). Per call: one coarse back-solve, one
assembly of the data matrix on T_J, three matrix-vector products on T_J and one 3 × 3 product
per cell of each level (the data by corners), the patches of each level in one pass (a
matrix product per class of congruent patches), J - 1 RT transfers. (Solving every level's
coarse patches on T_J itself, grouped by ancestry, would be just as exact but costs about
3 × dim(T_J) unknowns *per level*, in patches of up to 6 · 4^J cells.)
"""

import numpy as np
import scipy.sparse as sp
import ufl
from mpi4py import MPI
from petsc4py import PETSc

from ..fem.discretisation import boundary_dofs, ghosted_vector, p1_space
from ..fem.hierarchy import barycentric
from ..fem.meshes import cell_vertices, offsets, owned_cells, triangle_areas
from ..forms import equilibration as equilibration_forms
from ..forms.membrane import membrane_linear
from .classes import ClassStore
from .congruence import dof_transformation, piola_reference_block
from .lifting import mass_inverse
from .patches import PatchSystems, colour_vertices

ROUND_OFF = 1e-8      # tolerance on the barycentric coordinates 0, 1/2, 1 of plaza's vertices
# the round-off of a barycentric coordinate computed from coordinates |x| with cells of altitude
# a is a few ε |x| / a; the tolerance allows 1e3 times that (`child_positions`)
COORDINATE_ROUND_OFF = 1e3 * np.finfo(float).eps
# entries of the RT transfer's blocks below this times the largest are round-off of exact
# zeros (the others are at least 1e-2 of it; `rt_prolongation`)
EXACT_ZERO = 1e-12


def _check(comm, ok, message):
    """Raise RuntimeError(message) on every process if `ok` is False on one of them."""
    from mpi4py import MPI
    if not comm.allreduce(bool(ok), op=MPI.LAND):
        raise RuntimeError(message)


# ## The combinatorial maps
#
# The fine vertex l of a cell K of T_j sits, before any boundary vertex moved, at
# x̂_l = (P_j X_{j-1})_l: a coarse vertex or the midpoint of a coarse edge. Its barycentric
# coordinates in the parent K' are then exactly 0, 1/2 or 1; β[K, l, m] is the one of x̂_l
# with respect to vertex m of K'. β is the DG1 prolongation (nodal values of a parent's affine
# function at the child's vertices) and defines G_K.

def child_positions(Vc, Vf, P, parents):
    """β (owned cells of T_j, 3, 3): barycentric coordinates of each fine cell's vertices in
    their parent, in the vertex (= P1 dof) order of both cells."""
    from dolfinx import fem
    Xc = Vc.tabulate_dof_coordinates()[:, :2]
    nco, nfo = Vc.dofmap.index_map.size_local, Vf.dofmap.index_map.size_local
    xc, xf = P.createVecRight(), P.createVecLeft()
    f = fem.Function(Vf)
    xhat = np.empty((f.x.array.size, 2))
    for d in range(2):
        xc.array[:] = Xc[:nco, d]
        P.mult(xc, xf)
        f.x.array[:nfo] = xf.array_r
        f.x.scatter_forward()
        xhat[:, d] = f.x.array
    xc.destroy()
    xf.destroy()
    nc = len(parents)
    corners = Xc[Vc.dofmap.list.array.reshape(-1, 3)[parents]]           # (c, 3, 2)
    pts = xhat[Vf.dofmap.list.array.reshape(-1, 3)[:nc]]                  # (c, 3, 2)
    beta = barycentric(corners, pts)
    rounded = np.round(2.0 * beta) / 2.0
    # β errs by the coordinates' round-off ε |x| over the parent's smallest altitude: on a
    # mesh far from the origin more than ROUND_OFF (cells of 1/64 at 1e9: about 3e-5)
    noise = COORDINATE_ROUND_OFF * offsets(corners)
    # β's candidates 0, 1/2, 1 lie 1/2 apart: a noise of 1/4 cannot tell them apart (a unit
    # square of cells 0.0625 moved by 1e14, refined twice: a singular child map further on)
    worst = Vf.mesh.comm.allreduce(float(noise.max(initial=0.0)), op=MPI.MAX)
    if not worst < 0.25:
        raise ValueError(f"the mesh lies too far from the origin for the size of its cells "
                         f"for the multilevel flux in double precision: the tolerance of a "
                         f"vertex's place in its parent cell (1e3 eps |x| / altitude) is "
                         f"{worst:.1e} of the cell, above the 1/4 that tells a corner from an "
                         f"edge's midpoint; translate the mesh "
                         f"towards the origin, or use the flux of extra iterations "
                         f"(alg_flux 'nu')")
    error = np.abs(beta - rounded).max(axis=(1, 2))
    _check(Vf.mesh.comm, np.all(error <= np.maximum(ROUND_OFF, noise)),
           "a fine vertex is neither a coarse vertex nor a coarse edge's midpoint: the "
           "hierarchy's P1 numbering does not match")
    return rounded


def dg_prolongation(beta, parents, ncoarse):
    """The process-local DG1 prolongation E_j (scipy CSR, 3 n_j × 3 n_{j-1}; rows and columns
    (cell, vertex)): the nodal values of the parent's affine function at the child's
    combinatorial vertices. E_jᵀ restricts moments (x, q) from T_j to T_{j-1}."""
    nc = beta.shape[0]
    rows = np.repeat(np.arange(3 * nc), 3)
    cols = 3 * np.repeat(parents, 9) + np.tile(np.arange(3), 3 * nc)
    values = beta.ravel()
    keep = values != 0.0
    return sp.csr_matrix((values[keep], (rows[keep], cols[keep])), shape=(3 * nc, 3 * ncoarse))


def _block_diagonal(blocks):
    """The block-diagonal CSR matrix of (n, 3, 3) blocks."""
    n = blocks.shape[0]
    return sp.bsr_matrix((blocks, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()


# ## Raviart–Thomas transfer along the combinatorial maps
#
# For a fine cell K with reference map F_K, and its parent K' with F_K', the composite
# A = F_K'⁻¹ ∘ G_K ∘ F_K maps the reference cell onto the child's quarter of the reference
# cell (vertices at the β's), whatever the geometry. dolfinx's basis on K' is the Piola image of
# T_K' φ̂ (T the dof transformation of the cell, from its permutation info), and the
# interpolation of a field into K gives the coefficients T_K⁻ᵀ Π̂ (pulled-back values at the
# reference points), Π̂ basix's interpolation matrix. Pulling the Piola-transferred coarse
# basis back to the fine reference cell gives det(DA) DA⁻¹ φ̂(A X). So the block of K is
#
#     M_K = T_K⁻ᵀ Π̂ V(A) T_K'ᵀ,   V(A)[(i, p), m] = (det(DA) DA⁻¹ φ̂_m(A X_p))_i,
#
# depending on the child's position and the two cells' permutation infos only.

def rt_prolongation(Rc, Rf, parents, beta):
    """The Piola transfer RT_1(T_{j-1}) → RT_1(T_j) along the combinatorial maps, as a
    distributed PETSc matrix (rows: fine dofs, columns: coarse dofs). Exact: the transferred
    field of an RT_1 field is in RT_1(T_j)."""
    element = Rf.element.basix_element
    n = element.dim
    coarse, fine = Rc.mesh, Rf.mesh
    for mesh in (coarse, fine):
        mesh.topology.create_entity_permutations()
    info_c = np.asarray(coarse.topology.get_cell_permutation_info())
    info_f = np.asarray(fine.topology.get_cell_permutation_info())
    nc = len(parents)
    ref = beta[:, :, 1:]                                             # (c, 3, 2)
    # a cell's kind: its six doubled reference coordinates (0, 1 or 2) and the two
    # permutation infos (3 bits each on a triangle), one integer below 3⁶ · 2⁶; the kinds
    # present, and a cell of each, by a table over all kinds (a sort of the cells costs more)
    if max(info_f.max(initial=0), info_c.max(initial=0)) >= 8:
        raise RuntimeError("unexpected cell permutation info (not a triangle mesh?)")
    kind = ((np.round(2.0 * ref).astype(np.int64).reshape(nc, 6) * 3 ** np.arange(6)).sum(axis=1)
            * 64 + info_f[:nc].astype(np.int64) * 8 + info_c[parents])
    cell_of = np.full(3 ** 6 * 64, nc, dtype=np.int64)
    cell_of[kind] = np.arange(nc)
    present = np.flatnonzero(cell_of < nc)
    number = np.zeros(cell_of.size, dtype=np.int64)
    number[present] = np.arange(present.size)
    inverse = number[kind]
    blocks = np.empty((present.size, n, n))
    for k, i in enumerate(cell_of[present].tolist()):                # a cell of each kind
        blocks[k] = (dof_transformation(element, info_f[i], inverse_transpose=True)
                     @ piola_reference_block(element, ref[i])
                     @ dof_transformation(element, info_c[parents[i]]).T)
    # the entries that vanish exactly (a fine dof on a coarse facet sees that facet's dofs
    # only) come out of the products as round-off: made zero and left out of the matrix
    blocks[np.abs(blocks) <= EXACT_ZERO * np.abs(blocks).max(initial=0.0)] = 0.0
    # each owned fine dof takes its row from the first owned cell that has it
    imf, imc = Rf.dofmap.index_map, Rc.dofmap.index_map
    fdofs = Rf.dofmap.list.array.reshape(-1, n)[:nc].ravel()
    cdofs = Rc.dofmap.list.array.reshape(-1, n)[parents]                # (c, n)
    owned = np.flatnonzero(fdofs < imf.size_local)
    row, at = np.unique(fdofs[owned], return_index=True)
    _check(fine.comm, row.size == imf.size_local,
           "an owned RT dof of the fine mesh lies on no owned cell")
    cell, local = np.divmod(owned[at], n)
    values = blocks[inverse[cell], local]                       # (rows, n)
    keep = values != 0.0
    cols = np.asarray(imc.local_to_global(cdofs[cell][keep].astype(np.int32)), dtype=np.int64)
    indptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))]).astype(PETSc.IntType)
    M = PETSc.Mat().createAIJ(((imf.size_local, imf.size_global),
                               (imc.size_local, imc.size_global)),
                              csr=(indptr, cols.astype(PETSc.IntType), values[keep]),
                              comm=fine.comm)
    M.assemble()
    return M


# ## One level of coarse patches

class _Level:
    """Level j ≥ 1: the patches of the vertices of T_{j-1} meshed by T_j."""

    def __init__(self, j, hierarchy, Vc, Vf, store):
        from dolfinx import fem
        self.j = j
        self.mesh = hierarchy.meshes[j]
        comm = self.mesh.comm
        self.parents = parents = np.asarray(hierarchy.parent_cells[j - 1], dtype=np.int64)
        nc, ncc = len(parents), owned_cells(hierarchy.meshes[j - 1])
        _check(comm, nc == owned_cells(self.mesh) and parents.max(initial=-1) < ncc,
               "the parent of an owned cell is not an owned cell")
        P = hierarchy.prolongation(j)
        self.beta = child_positions(Vc, Vf, P, parents)

        # moments: E_j (prolongation, so E_jᵀ restricts moments from T_j to T_{j-1}) and
        # G_j = M̂_j E_j M_{j-1}⁻¹, which maps the moments of x on T_{j-1} to those of
        # T Π̃_{j-1} x on T_j (M̂_j: DG1 masses of the unmoved quarters, |K'|/48 (I + 1 1ᵀ))
        E = dg_prolongation(self.beta, parents, ncc)
        self.ET = E.T.tocsr()
        cells_c = Vc.dofmap.list.array.reshape(-1, 3)[:ncc]
        area_c = triangle_areas(Vc.tabulate_dof_coordinates()[:, :2][cells_c])
        minv = mass_inverse(area_c, np.broadcast_to(np.eye(3), (ncc, 3, 3)))     # M_{j-1}⁻¹
        mhat = (area_c[parents] / 48.0)[:, None, None] * (np.eye(3) + 1.0)
        self.G = _block_diagonal(mhat) @ E @ _block_diagonal(minv)

        # the patches: colour the vertices of T_{j-1}; group c holds the patches of colour c
        imap = Vc.dofmap.index_map
        colour, self.ncolours, _ = colour_vertices(cells_c, imap, comm)
        on_boundary = boundary_dofs(Vc)
        gdofs = np.asarray(imap.local_to_global(np.arange(colour.size, dtype=np.int32)),
                           dtype=np.int64)
        corners = cells_c[parents]                                        # (c, 3)
        patches, interior = [], []
        # cells[c][m]: the cells whose parent has its vertex m of colour c
        self.cells = []
        for c in range(self.ncolours):
            hit = colour[corners] == c                                    # ≤ 1 per cell
            at = np.argmax(hit, axis=1)
            vertex = corners[np.arange(nc), at]
            has = hit.any(axis=1)
            self.cells.append([np.flatnonzero(has & (at == m)).astype(np.int32)
                               for m in range(3)])
            patches.append(np.where(has, gdofs[vertex], -1))
            interior.append(has & ~on_boundary[vertex])
        self.patches, self.interior = patches, interior
        # the data are DG moments and only σ is wanted; the classes of the levels before,
        # scaled copies of this level's, are kept in `store` with their inverses
        self.systems = PatchSystems(self.mesh, patches, interior, rhs="divergence",
                                    solution="flux", store=store)
        self.rt_space = self.systems.rt_space
        W = self.systems.W
        self.dg = W.sub(1).dofmap.list.array.reshape(-1, 3)[:nc].ravel()
        # the W vectors of the solve (owned entries) and σ_j's owned entries as a Vec: made by
        # petsc4py (dolfinx 0.5 frees a Function's `.vector` only at an explicit destroy)
        nw = W.dofmap.index_map.size_local * W.dofmap.index_map_bs
        self.b = PETSc.Vec().createMPI((nw, PETSc.DECIDE), comm=comm)
        self.x = self.b.duplicate()
        self.sigma = fem.Function(self.rt_space)
        rmap = self.rt_space.dofmap.index_map
        self.sigma_vec = PETSc.Vec().createWithArray(
            self.sigma.x.array[:rmap.size_local], size=(rmap.size_local, rmap.size_global),
            comm=comm)

        self.transfer = None            # RT_1(T_{j-1}) → RT_1(T_j), for j ≥ 2

    def solve(self, data):
        """σ_j = Σ_a σ_j^a on T_j for the DG1 moments of the corners `data` ((3 n_j, 3):
        column m the moments -(e, q) for ψ the hat function of vertex m of each cell's
        parent). On a cell, the data of colour c's patch are those of the parent's vertex of
        colour c (none if it has none)."""
        b, x = self.b, self.x
        home = self.systems.home_vector()                 # one colour at a time
        x.array[:] = 0.0
        by_cell = data.reshape(-1, 3, 3)
        dg = self.dg.reshape(-1, 3)
        for c in range(self.ncolours):
            b.array[:] = 0.0
            for m, cells in enumerate(self.cells[c]):
                b.array[dg[cells]] = by_cell[cells, :, m]
            self.systems.gather(c, b, home)
            self.systems.scatter(c, self.systems.solve_home(c, home), x, add=True)
        self.sigma.x.array[:] = 0.0
        self.systems.add_flux(x, self.sigma)

    def destroy(self):
        self.systems.destroy()
        for v in (self.b, self.x, self.sigma_vec):
            v.destroy()
        if self.transfer is not None:
            self.transfer.destroy()


class MultilevelFlux:
    """σ_alg of §6 on the hierarchy of `disc`'s mesh (set up once per hierarchy).

    `MultilevelFlux(disc, hierarchy, lifting=None)`: disc a `Discretisation` on
    hierarchy.finest (its P1 space V and stiffness S are used), hierarchy with J ≥ 1 levels;
    `lifting` the estimators' `membranes.estimation.lifting.Lifting` on that mesh, whose DG1
    space and cell areas are taken instead of making them again. `sigma(r, out=None)`
    returns σ_alg ∈ RT_1(T_J) with ∇·σ_alg = r for the lifted residual r (a DG1 Function on
    T_J), as a new Function of `rt_space` or written into `out` (any RT_1 Function on T_J).
    σ_alg does not depend on μ_α: call it once per membrane.
    """

    def __init__(self, disc, hierarchy, lifting=None):
        from dolfinx import fem
        from dolfinx.fem.petsc import create_matrix
        if hierarchy.levels < 1:
            raise ValueError("the multilevel algebraic flux needs a hierarchy with at least "
                             "one refinement (J >= 1); use the flux of extra iterations")
        if disc.mesh is not hierarchy.finest:
            raise ValueError("the discretisation must live on the hierarchy's finest mesh")
        self.disc, self.hierarchy = disc, hierarchy
        self.comm = disc.comm
        J = hierarchy.levels
        spaces = [p1_space(m) for m in hierarchy.meshes[:-1]] + [disc.V]
        store = ClassStore("divergence", "flux")       # one for all levels (`classes`)
        self.levels = [_Level(j, hierarchy, spaces[j - 1], spaces[j], store)
                       for j in range(1, J + 1)]
        for coarse, fine in zip(self.levels[:-1], self.levels[1:]):
            fine.transfer = rt_prolongation(coarse.rt_space, fine.rt_space, fine.parents,
                                            fine.beta)
        self.rt_space = self.levels[-1].rt_space

        # the residual, the prolonged coarse solution, the data matrix on T_J
        mesh = disc.mesh
        self.Q = lifting.Q if lifting is not None else fem.FunctionSpace(mesh, ("DG", 1))
        self.r, self.rho = fem.Function(self.Q), fem.Function(disc.V)
        # ψ broken (DG1): B acts on each cell's vertex values of ψ (module notes)
        psi, q = ufl.TrialFunction(self.Q), ufl.TestFunction(self.Q)
        self.data_form = fem.form(equilibration_forms.multilevel_data(psi, self.r, self.rho, q))
        self.B = create_matrix(self.data_form)
        self.psi, self.y = self.B.createVecs()
        ncJ = owned_cells(mesh)
        self.dgJ = self.Q.dofmap.list.array.reshape(-1, 3)[:ncJ].ravel()
        # |K| of the owned cells of T_J (the defect's norm, `_check`)
        self.areaJ = lifting.area if lifting is not None \
            else triangle_areas(cell_vertices(mesh))
        self.rhs_form = fem.form(membrane_linear(self.r, ufl.TestFunction(disc.V)))
        self.rhs = ghosted_vector(disc.V)          # (not dolfinx's: `ghosted_vector`)
        self._coarse_setup(spaces[0])
        self._same_layout = {}
        self.defect = None           # the relative divergence defect of the last σ made
        self.defect_sq = None        # ‖∇·σ_alg - r‖² of the last σ made (global)

    def _coarse_setup(self, V0):
        """P = P_J ⋯ P_1 and the MUMPS factorisation of Pᵀ S_J P with the Dirichlet rows of
        T_0's boundary vertices (§6, step 1)."""
        P = self.hierarchy.prolongations[-1].copy()
        for Pk in reversed(self.hierarchy.prolongations[:-1]):
            P = P.matMult(Pk)
        self.P = P
        K0 = self.disc.S.PtAP(P)
        n0 = V0.dofmap.index_map.size_local
        on_boundary = np.flatnonzero(boundary_dofs(V0)[:n0])
        self.boundary0 = on_boundary
        rows = np.asarray(V0.dofmap.index_map.local_to_global(on_boundary.astype(np.int32)),
                          dtype=PETSc.IntType)
        K0.zeroRowsColumns(rows, diag=1.0)
        ksp = PETSc.KSP().create(self.comm)
        ksp.setOptionsPrefix("multilevel_coarse_")
        ksp.setOperators(K0)
        ksp.setType("preonly")
        ksp.getPC().setType("lu")
        ksp.getPC().setFactorSolverType("mumps")
        ksp.setFromOptions()
        ksp.setUp()
        self.coarse_ksp, self.K0 = ksp, K0
        self.b0, self.rho0 = K0.createVecs()
        self.rhoJ = P.createVecLeft()

    def _coarse_solve(self):
        """ρ_0 for the current r, prolonged to T_J (into self.rho)."""
        from dolfinx.fem.petsc import assemble_vector
        with self.rhs.localForm() as local:
            local.set(0.0)
        assemble_vector(self.rhs, self.rhs_form)
        self.rhs.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        self.P.multTranspose(self.rhs, self.b0)
        self.b0.array[self.boundary0] = 0.0
        self.coarse_ksp.solve(self.b0, self.rho0)
        self.P.mult(self.rho0, self.rhoJ)
        n = self.disc.n
        self.rho.x.array[:n] = self.rhoJ.array_r
        self.rho.x.scatter_forward()

    def _set(self, target, source):
        """target ← source (two Functions of the same element on T_J), by the dof arrays when
        the spaces number the dofs alike (checked once per pair of spaces, on all processes),
        else by interpolation (exact between spaces of one element)."""
        from mpi4py import MPI
        V, W = source.function_space, target.function_space
        key = (id(V), id(W))
        if key not in self._same_layout:
            a, b = V.dofmap.list.array, W.dofmap.list.array
            alike = (V.element.signature() == W.element.signature()
                     and a.shape == b.shape and np.array_equal(a, b))
            # the spaces are kept with the verdict, so that their ids stay theirs
            self._same_layout[key] = (V, W, self.comm.allreduce(alike, op=MPI.LAND))
        if self._same_layout[key][2]:
            target.x.array[:] = source.x.array
        else:
            target.interpolate(source)

    def sigma(self, r, out=None):
        """σ_alg with ∇·σ_alg = r (§6), r a DG1 Function on T_J."""
        from dolfinx import fem
        from dolfinx.fem.petsc import assemble_matrix
        self._set(self.r, r)
        self._coarse_solve()
        self.B.zeroEntries()
        assemble_matrix(self.B, self.data_form)
        self.B.assemble()
        # per level j = J..1 the moments against DG1(T_j) of x for ψ the hat function of
        # vertex m of each cell's parent in T_{j-1} (module notes): on T_J by B on T_J's β;
        # then down the levels, restricted to T_{j-1} by E_jᵀ and mixed by the β of T_{j-1}'s
        # cells in their parents (3 × 3 per cell). The data of the corners m:
        # -Π̃_j x + T Π̃_{j-1} x (Π̃_0 := 0)
        ncJ = self.areaJ.size
        moments = np.empty((ncJ, 3, 3))
        beta = self.levels[-1].beta
        self.psi.set(0.0)
        for m in range(3):
            self.psi.array[self.dgJ] = beta[:, :, m].ravel()
            self.B.mult(self.psi, self.y)
            moments[:, :, m] = self.y.array_r[self.dgJ].reshape(ncJ, 3)
        moments = moments.reshape(3 * ncJ, 3)
        corners = [None] * len(self.levels)
        scale = 0.0                       # the largest data entry (`divergence`)
        for i in reversed(range(len(self.levels))):
            level = self.levels[i]
            data = -moments
            if i > 0:
                coarse = level.ET @ moments                  # on T_{j-1}
                data += level.G @ coarse
                beta = self.levels[i - 1].beta
                moments = np.matmul(coarse.reshape(-1, 3, 3), beta).reshape(-1, 3)
            scale = max(scale, float(np.abs(data).max(initial=0.0)))
            corners[i] = data
        previous = None
        for level, data in zip(self.levels, corners):
            level.solve(data)
            if previous is not None:
                s = level.sigma_vec
                level.transfer.multAdd(previous.sigma_vec, s, s)
            previous = level
        result = previous.sigma
        result.x.scatter_forward()
        if out is None:
            out = fem.Function(self.rt_space)
        self._set(out, result)
        self.defect = self._check(out, scale)
        return out

    def _check(self, sigma, scale):
        """The divergence identity ∇·σ_alg = r_αh (`divergence`): the largest DG1 moment of
        its defect against `scale` (ACCOUNTED_TOLERANCE), and the defect's squared L² norm
        into `defect_sq` (module notes). Returns the relative defect; raises if it fails."""
        from dolfinx import la

        from .divergence import ACCOUNTED_TOLERANCE, assemble, check, largest, norm_squared
        defect = la.create_petsc_vector(self.Q.dofmap.index_map, self.Q.dofmap.index_map_bs)
        assemble(equilibration_forms.flux_divergence(sigma, self.r, ufl.TestFunction(self.Q)),
                 self.disc.mesh, defect)
        worst = largest(defect)
        # b_K: the moments of the owned cells (their DG1 dofs are owned)
        self.defect_sq = norm_squared(defect.array_r[self.dgJ].reshape(-1, 3), self.areaJ,
                                      self.comm)
        defect.destroy()
        return check(worst, scale, self.comm, "σ_alg (§6)", ACCOUNTED_TOLERANCE,
                     self.disc.mesh)

    def summary(self):
        """Global facts of the set-up: per level j = 1..J the colours of T_{j-1} and the
        unknowns of the patch systems; the coarse unknowns."""
        return dict(levels=len(self.levels),
                    colours=[level.ncolours for level in self.levels],
                    unknowns=[sum(level.systems.sizes()) for level in self.levels],
                    coarse=self.K0.getSize()[0],
                    vertices=self.disc.n_global, processes=self.comm.size)

    def destroy(self):
        for level in self.levels:
            level.destroy()
        for obj in (self.coarse_ksp, self.K0, self.b0, self.rho0, self.rhoJ, self.P, self.B,
                    self.psi, self.y, self.rhs):
            obj.destroy()
        self.levels = []
