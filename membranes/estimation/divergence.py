"""The divergence identities the guaranteed bound rests on, checked on every flux made (§5,
§6, §7).

The bound of §7 holds for any σ_α in H(div, Ω) whose divergence is exactly the load it
equilibrates: ∇·σ_α,disc = Π f_α ± λ_h - r_αh (§5), ∇·σ_α,alg = r_αh (§6). H(div)
conformity holds by construction (σ is a global RT_1 Function; each patch keeps only the
dofs of its interior facets, and of its facets on ∂Ω if it touches ∂Ω). The divergence is
what the patch solves decide: each patch is solved with the inverse of its class's block
(`congruence`), whose divergence rows must be the patch's own. So every flux is checked:
the DG1 moments of its divergence defect, one assembly of a form of
`forms.equilibration`, must vanish to round-off against the moments of the patch
right-hand sides. A flux that fails raises; the bound is never computed with it.

A wrong divergence row gives a defect of the size of the right-hand sides on the patch's
cells (measured 0.43 of their largest entry, tests/core/test_equilibration.py); round-off
gives about (block condition) · ε of the scale, the largest right-hand side entry or the
round-off unit of the moments that cancel in the sum (for σ_disc μ max|u|: the moments
(μ ∇u·∇ψ_a, q) of a u far from 0). TOLERANCE sits between the two (measured round-off: up to
6e-13 on the disk at 9.3e5 vertices, the stability matrix's cases in BENCHMARKS.md).

The block condition grows like the square of the cells' aspect ratio A (longest edge over
smallest altitude), so on a mesh stretched enough that A² ε reaches the defect, round-off
explains a failed check: the graded squares of `fem.meshes.structured_square(16, 16, p)`
passed at p = 4 (A = 1.5e4), and σ_disc failed with a relative defect of 1.2e-7 at p = 8
(A = 1.7e9, A² ε ≈ 6e2) on T_0. Likewise a mesh far from the origin for the size of its
cells: its positions are rounded to ε |x|, a fraction ε |x| / a_K of a cell's altitude a_K, and
the blocks' round-off grows to about A² ε |x| / h_K (a unit square of cells 0.0625 moved by
1e14: the σ_disc check failed at 5.0e-2 of the right-hand sides, A² ε |x| / h ≈ 1; by 1e15 the
defect was NaN). Such a failure, where ε A² reaches the defect, or ε max_K A_K² max(1, |x|_K /
h_K) (or 1, for a defect that is not finite), is said as a mesh too stretched or too far from
the origin for a bound in double precision (ValueError, bad input); any other as the bug it
is (RuntimeError).
"""

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from ..fem.meshes import cell_vertices, offsets, stretches

EPS = np.finfo(float).eps
TOLERANCE = 1e-8
# σ_alg of the multilevel flux: its defect, whatever its size, is measured and enters the
# bound as the remainder (multilevel notes), so the check only catches a wrong block (a defect
# of the size of the right-hand sides) and lets the round-off of strongly graded meshes pass
ACCOUNTED_TOLERANCE = 1e-4


def assemble(form, mesh, into):
    """The UFL `form` of a defect's DG1 moments (`forms.equilibration`) assembled into
    `into`, zeroed first, a chunk of cells at a time (dolfinx packs the coefficients of all a
    form's cells before it assembles). `into`: a PETSc Vec (ghost contributions are then
    added to their owners) or a numpy array of the local dofs (the caller sees to the
    ghosts). Collective."""
    from dolfinx import fem

    from .cell_forms import chunks, compiled
    if isinstance(into, PETSc.Vec):
        with into.localForm() as local:
            assemble(form, mesh, local.array)
        into.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return into
    into[:] = 0.0
    for part in compiled(chunks(form, mesh), mesh):
        fem.assemble_vector(into, part)
    return into


def norm_squared(moments, area, comm):
    """‖d‖² of a DG1 function d from its moments b_K = ((d, φ_m)_K)_m on the owned cells
    (`moments` (cells, 3), `area` their |K|): Σ_K b_Kᵀ M_K⁻¹ b_K, exact for d in DG1 (the
    defects of every flux are), reduced over the processes. The defect's norm enters the
    bound as a remainder (§6, `Estimators.remainder_of`)."""
    from .lifting import mass_inverse
    local = float(np.einsum("ij,ij->", mass_inverse(area, moments), moments))
    return comm.allreduce(local, op=MPI.SUM)


def largest(values):
    """The largest |entry| of a PETSc Vec's owned entries (or of a numpy array) on this
    process (no temporary, no communication: `check` reduces over the processes once)."""
    a = values.array_r if isinstance(values, PETSc.Vec) else values
    return float(max(a.max(initial=0.0), -a.min(initial=0.0)))


def geometric_round_off(mesh):
    """(A, U, O) over all processes: the largest aspect ratio A_K (longest edge h_K over
    smallest altitude, `fem.meshes.stretches`), the largest A_K² max(1, O_K), O_K =
    |x|_K / h_K the ratio of a cell's largest coordinate to its size, and that O_K (module
    notes: ε A² is the patch solves' round-off, ε A² O that of a mesh whose positions are
    rounded to ε |x|). Collective."""
    p = cell_vertices(mesh)
    with np.errstate(divide="ignore", invalid="ignore"):
        stretch = stretches(p)
        offset = offsets(p) / stretch                                   # |x|_K / h_K
        unit = stretch ** 2 * np.maximum(1.0, offset)
    k = int(np.argmax(np.nan_to_num(unit, nan=np.inf))) if len(unit) else None
    local = (0.0, 0.0, 0.0) if k is None else (float(unit[k]), float(offset[k]),
                                                float(stretch.max()))
    comm = mesh.comm
    unit, offset = max(comm.allgather(local[:2]))
    return comm.allreduce(local[2], op=MPI.MAX), unit, offset


def check(defect, scale, comm, what, tolerance=None, mesh=None):
    """`defect` (the largest |moment| of the defect on this process) against `tolerance`
    (TOLERANCE if None) · `scale` (the size of the right-hand sides, see the module notes),
    over all processes; if it fails, raises ValueError where the cells of `mesh` are so
    stretched, or lie so far from the origin for their size, that round-off explains the
    defect (module notes), else RuntimeError, naming `what`. Returns the relative defect."""
    tolerance = TOLERANCE if tolerance is None else tolerance
    defect = comm.allreduce(float(defect), op=MPI.MAX)
    scale = comm.allreduce(float(scale), op=MPI.MAX)
    relative = defect / scale if scale > 0.0 else defect
    if not relative <= tolerance:                     # (also for NaN)
        if mesh is not None:
            stretch, unit, offset = geometric_round_off(mesh)
            round_off = (f"the round-off of {what}'s patch solves leaves a divergence defect "
                         f"of {relative:.1e} of the right-hand sides (above {tolerance:g})")
            if relative <= stretch ** 2 * EPS:
                raise ValueError(f"the mesh's cells are too stretched for a guaranteed bound "
                                 f"in double precision: largest aspect ratio {stretch:.1e}, "
                                 f"and {round_off}; mesh with less stretched cells (theory "
                                 f"§11)")
            if relative <= unit * EPS or (unit * EPS >= 1.0 and not np.isfinite(relative)):
                raise ValueError(f"the mesh lies too far from the origin for the size of its "
                                 f"cells for a guaranteed bound in double precision: "
                                 f"coordinates up to {offset:.1e} times a cell's size, and "
                                 f"{round_off}; translate the mesh towards the origin (theory "
                                 f"§11)")
        raise RuntimeError(f"{what} violates its divergence identity, so no bound can rest on "
                           f"it: largest DG1 moment of the defect {defect:.3e}, {relative:.1e} "
                           f"of the right-hand sides' (a patch solved with a block not its "
                           f"own, or data whose interior patches are not compatible, §4)")
    return relative
