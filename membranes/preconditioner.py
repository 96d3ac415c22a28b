"""Vertex-block AMG: a mesh-independent preconditioner for the eliminated 2N Newton system
(DESIGN §3; `Krylov` option ``pc_type vertex_amg``).

**The system.** The eliminated system Ã Y = b (newton_system) has unknowns Y = (u1, z), one
pair per vertex l: z_l = u2_l where λ_l was eliminated (|β_l| ≥ |α_l|: "free" vertices),
z_l = λ_l where u2_l was (|β_l| < |α_l|: "contact" vertices). Its rows are the two membrane
rows of every vertex, r1_l = μ1 (S u1)_l - D_l λ_l and r2_l = μ2 (S u2)_l + D_l λ_l, with

    free:     λ_l = c_l (u2 - u1)_l + const,   c_l = α_l/β_l   (0 for min, in [0, 1] for fb)
    contact:  u2_l = u1_l + d_l λ_l + const,   d_l = β_l/α_l   (0 for min, in [0, 1) for fb).

Written in (u1, u2) only, it is the SPD system of two membranes tied by a spring of stiffness
p_l = c_l D_l (free) or D_l/d_l (contact; p = ∞ for min: u1 = u2 there). In the mean
m = (μ1 u1 + μ2 u2)/(μ1 + μ2) and the gap δ = u2 - u1 it falls apart exactly (the cross terms
of μ1|∇u1|² + μ2|∇u2|² cancel): (μ1 + μ2) S m = f1 + f2 and (μ̄ S + diag p) δ = ...,
μ̄ = μ1μ2/(μ1 + μ2). Both are Laplacians plus a nonnegative reaction: AMG's home ground, for any
p from 0 to ∞. ILU(0) on Ã, in contrast, needs O(1/h) GMRES iterations per Newton step (the
paper's GMRES counts, DESIGN §8, grow the same way).

**The preconditioner** gets that structure from Ã alone, without μ_α, c, d or the row scaling:

1. Vertex blocks. B = the 2×2 blocks Ã[(l, N+l), (l, N+l)]; Â = B⁻¹ Ã. Any scaling or mixing of
   the two rows of a vertex (e.g. block α scaled by 1/μ_α) cancels in B⁻¹ Ã: Â, and so the
   preconditioner, does not depend on it. At a contact vertex, B⁻¹ sums the two rows (λ_l
   drops out: the "mean" row of the glued membranes) and keeps one row that gives λ_l.
2. Slaves. A z-column with entries only in its own vertex's rows (λ_l at a min contact vertex:
   d_l = 0) is the identity column in Â: that λ_l appears in no other row, and
   Â = [[K, 0], [X, I]] over (others, slaves). Solve K, then λ_slaves = rhs - X y.
3. Gap scaling. At a contact vertex with d_l > 0 (fb), λ_l enters the neighbours' second rows
   through u2 = u1 + d_l λ_l, and its row of Â has couplings of size 1/d_l (up to 570 times the
   diagonal, measured: disk, 6k vertices, fb step 5): BoomerAMG broke down (GMRES on K alone,
   step 3). With the gap d_l λ_l as unknown (a diagonal similarity K → Ds K Ds⁻¹, Ds = d on
   those columns, 1 elsewhere) the row is the gap's reaction–diffusion row again, diagonally
   dominant, and BoomerAMG converges (6–21 iterations on K alone at every step). d_l is read
   off Ã: in any second-block row N+m of a neighbour m, the u1_l and z_l entries are
   ρ μ2 S_ml and ρ μ2 d_l S_ml (ρ the row's scale), so d_l = their ratio, whatever ρ.
4. One V-cycle of hypre BoomerAMG on Ds K Ds⁻¹ per application (`DEFAULT_INNER`): PETSc's
   defaults (classical interpolation, strong threshold 0.25) except two options.
   * Smoothing: one forward hybrid Gauss–Seidel sweep down and one backward sweep up (a
     symmetric V-cycle) instead of PETSc's symmetric sweep both ways, which costs twice as
     much: the V-cycle takes 35 % less time (1.7e5 rows of K: 20 instead of 33 ms) for at most
     one more GMRES iteration per Newton step (disk, cmp configuration, 1e2 … 4.4e5 vertices:
     7–9 per step instead of 6–9, no growth with the mesh).
   * Coarsening: Ruge–Stüben instead of Falgout (which adds CLJP on processor boundaries: none
     in a serial run): the same hierarchy (grid complexity 1.66, operator 2.65) and the same
     iterations, a 10–15 % cheaper set-up.
   Tried and not kept (set-up + iterations × V-cycle per Newton step at 1.1e5 and 4.4e5
   vertices, and iterations): HMIS or PMIS coarsening with ext+i interpolation, P_max 4 (the
   same total: V-cycles 5–20 % cheaper, set-up 15 % dearer) or P_max 3 (10–20 % less in
   total, but one more iteration per step than the options above, 10 at the worst step: one
   more would cost the adaptive variant an estimator evaluation at ν = 10, DESIGN §8);
   aggressive coarsening (agg_nl 1: 70 % more iterations); l1-Jacobi smoothing (30 % more);
   strong threshold 0.3–0.5, interpolation truncation (no gain).

The preconditioner is M⁻¹ r = block-triangular solve of Â with AMG for K, applied to B⁻¹ r.
The set-up is one sparse product (B⁻¹Ã; the similarity Ds scales K's entries), a few
slicings and one BoomerAMG set-up per Newton step. At 1.1e5 vertices (K: 1.7e5 rows) the scipy
part takes 80 ms, the BoomerAMG set-up 200 ms and a V-cycle 20 ms: the BoomerAMG set-up is
about a third of a Newton step's linear algebra (600 ms with ~8 iterations).

**For min: the exact mean/gap split** (`MeanGapAMG`; `vertex_amg` takes it wherever
`mean_gap_split` recognises the system, else 1.–4.). For min every vertex is free (c_l = 0:
z_l = u2_l, λ_l = const) or in contact (d_l = 0: z_l = λ_l, u2_l = u1_l + const), and with the
rows weighted by W (newton.linear_step) both membrane blocks hold the same S, Dirichlet rows
included. Let a_l = D_l/μ1 and b_l = D_l/μ2 be the λ-entries of a contact vertex's two rows
(-a_l in the first, b_l in the second), θ = a/(a + b) = μ2/(μ1 + μ2). Then Ã Y = r is, exactly,
with the mean m = (1 - θ) u1 + θ u2 = (μ1 u1 + μ2 u2)/(μ1 + μ2), the gap δ = u2 - u1 and f the
free vertices:

    S m = (1 - θ) r1 + θ r2                      (every vertex: λ cancels)
    S_ff δ_f = (r2 - r1)_f,   δ = 0 at contact   (S_ff: S on the free vertices)
    λ_l = (r2 - r1 - S δ)_l / (a_l + b_l)         (contact vertices)

and u1 = m - θ δ, u2 = m + (1 - θ) δ. Two Laplacians, one V-cycle on each per application.
S does not depend on the iterate: its AMG is set up by the first Newton step of a mesh that
needs it and kept (`Krylov`'s cache; reused while Ã[:N, :N] is the same matrix, entry for
entry; with the exact mean of membranes.mean no step needs it), so a step sets up only the
gap's, on the N_f free vertices (~55 % of N on the disk), where 1.–4. set up
K (N + N_f rows; the glued rows of the contact vertices give it operator complexity 2.66, the
hierarchy above). a, b, θ and S are read off Ã, and Ã is compared with the model of the
identity above entry by entry (to 1e-10 of S's largest entry; one compiled pass over Ã's
entries, `mean_gap_split`); where it differs (fb; rows not weighted alike, e.g. Ã unweighted
with μ1 ≠ μ2) 1.–4. apply. A min step of newton.linear_step vouches for its structure (the
vertices where it eliminated u2): the second block is then not compared (its first block
still is, and θ), 0.06 s a step at 9.3e5 vertices instead of 0.15 s (the splits of a J = 6
run: 0.24 s instead of 0.56 s). The gap's matrix S_ff and the two halves of an application (the
right sides of the two V-cycles; u1, u2 and λ from their solutions) are compiled passes too:
at 9.3e5 vertices a numpy application cost 25 ms besides its V-cycles, now 12 ms, and the
split with S_ff 0.35 s a step, now 0.12 s. Measured (disk, min, the adaptive nested
run of issue 6's comparison, ν-flux; GMRES iterations per Newton step and the time of the
Krylov solves, set-ups included): the three steps of the finest level at 1.1e5 vertices
(h0 = 0.2, J = 5), solved to 2e-12 on their own: 9, 8, 7 → 8, 6, 6 iterations, 0.68, 0.59,
0.61 s → 0.36, 0.23, 0.22 s; the whole run at 9.3e5 vertices (h0 = 0.132, J = 6; 21 Newton
steps): 7–9 → 5–8 iterations a step (168 → 142), Krylov 21 s → 9.4 s, the same Newton steps.
Keeping the mean's AMG costs memory: the run's peak was 4.41 GiB, 4.11 GiB when it is set up
anew at every step (Krylov 11.2 s) and 4.23 GiB with 1.–4.; the PETSc matrices of the inner
PCs are built on the scipy arrays (no copy).
Where the mean part of the initial residual is already below half the solve's bound (the
later Newton steps of a level), the solve leaves the mean's V-cycles out (`settle_mean`).
The inner options of 4. were checked again on the gap's S_ff (the same run at 9.3e5 vertices,
serial, one run each, Krylov time with set-ups | set-ups | GMRES iterations, most in a step):
the defaults 5.3 | 2.6 s | 137, 8; HMIS, ext+i, P_max 4: 8.6 | 4.8 s | 144, 8; PMIS, ext+i,
P_max 4: 6.8 | 3.7 s | 163, 10; HMIS, ext+i, P_max 4, agg_nl 1: 8.3 | 2.1 s | 266, 16.

**Measured** (disk, exact Newton, GMRES(30) right-preconditioned, benchmarks/
bench_preconditioner.py; BENCHMARKS.md has the table; with PETSc's BoomerAMG defaults, before
the two options of 4., which add 0.3–0.8 iterations per step on average): GMRES iterations
per Newton step, mean over the steps, min | fb:

    vertices          1.5k       6k         24k        (see BENCHMARKS.md for 1e4 … 6.6e5)
    ILU(0)         51 | 40    103 | 79    255 | 179
    vertex_amg    7.4 | 7.1   8.1 | 8.1   8.5 | 8.9

Inner options: ``vertex_amg_<option>`` goes to the inner PC as ``<option>`` (e.g.
``vertex_amg_pc_type gamg``, ``vertex_amg_pc_hypre_boomeramg_strong_threshold 0.5``); the
default is ``pc_type hypre`` (BoomerAMG). GAMG and ML were tried on K: 2–20 times more
iterations than BoomerAMG on the fb systems.

Only the eliminated system has this pairing of rows and unknowns per vertex; on the full 3N
system the vertex blocks are meaningless, and a singular one is refused (ValueError).
"""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from .compiled import kernel
from .linear_solve import petsc_matrix, scaled_rows
from .newton_system import vertex_pair_rows

INNER_PREFIX = "vertex_amg_"
DEFAULT_INNER = {"pc_type": "hypre", "pc_hypre_type": "boomeramg",
                 "pc_hypre_boomeramg_coarsen_type": "Ruge-Stueben",
                 "pc_hypre_boomeramg_relax_type_down": "SOR/Jacobi",
                 "pc_hypre_boomeramg_relax_type_up": "backward-SOR/Jacobi"}

_prefixes = iter(range(1 << 62))


def check_shape(A):
    """ValueError unless A is 2N × 2N."""
    if A.shape[0] != A.shape[1] or A.shape[0] % 2:
        raise ValueError(f"vertex_amg needs the eliminated 2N x 2N system, got {A.shape}")


def vertex_blocks_inverse(A):
    """B⁻¹ as a sparse 2N × 2N matrix, B the 2×2 blocks of the vertices (rows and columns l and
    N + l), two entries a row (`vertex_pair_rows`); ValueError if one is singular or A is not
    2N × 2N."""
    check_shape(A)
    n = A.shape[0] // 2
    a, d = A.diagonal()[:n], A.diagonal()[n:]
    b, c = A.diagonal(n), A.diagonal(-n)
    det = a * d - b * c
    scale = np.maximum(np.abs(a * d), np.abs(b * c))
    if not np.all(np.abs(det) > 1e-12 * scale) or not np.all(np.isfinite(det)):
        raise ValueError("vertex_amg: a singular 2x2 vertex block (it needs the eliminated "
                         "system, system='eliminated')")
    return vertex_pair_rows((d / det, -b / det), (-c / det, a / det))


def slaves(A):
    """z-unknowns (as a mask over the N vertices) whose column of A has entries only in the
    two rows of their own vertex."""
    n = A.shape[0] // 2
    C = A.tocoo(copy=False)
    z = C.col >= n
    row, col = C.row[z], C.col[z] - n
    foreign = (row != col) & (row != col + n) & (C.data[z] != 0)
    touched = np.zeros(n, dtype=bool)
    touched[col[foreign]] = True
    return ~touched


def gap_scales(A):
    """d_l where u2_l = u1_l + d_l z_l + const (z_l = λ_l), read off the second block's rows of
    the neighbours (module notes, 3.); 1 where u2_l does not depend on u1_l (z_l = u2_l)."""
    n = A.shape[0] // 2
    B = A[n:].tocoo(copy=False)
    z = B.col >= n
    vertex = np.where(z, B.col - n, B.col)
    foreign = B.row != vertex
    u1, z = foreign & ~z, foreign & z
    on_u1 = np.bincount(vertex[u1], B.data[u1], minlength=n)
    on_z = np.bincount(vertex[z], B.data[z], minlength=n)
    gap = on_u1 != 0
    return np.where(gap, on_z / np.where(gap, on_u1, 1.0), 1.0)


@kernel
def _split_entries(indptr, indices, data, n, rtol, ref_indptr, ref_indices, ref_data,
                   check_model):
    """The mean/gap model of `mean_gap_split` read off the CSR arrays of A (2N × 2N) in one
    pass over the entries, and checked entry by entry in a second (where `check_model`): (ok,
    same, S's indptr, indices and data (A[:N, :N], in A's order), a, b). ok is False where a
    first-block row has an entry outside its own columns S and N + l, where S has a zero
    diagonal entry, or where a second-block row differs from the model by more than
    rtol max |S| in some column.
    `same`: A[:N, :N] is the reference matrix (its CSR arrays ref_*; empty arrays: none),
    entry for entry and in the same order; S's arrays are then the reference's, not copies."""
    a, b, diagonal = np.zeros(n), np.zeros(n), np.zeros(n)
    S_indptr = np.zeros(n + 1, dtype=np.int64)
    ok = True
    same = ref_indptr.size == n + 1
    for i in range(n):
        m = ref_indptr[i] if same else 0
        for k in range(indptr[i], indptr[i + 1]):
            c = indices[k]
            if c < n:
                S_indptr[i + 1] += 1
                if c == i:
                    diagonal[i] += data[k]
                if same:
                    same = m < ref_indptr[i + 1] and ref_indices[m] == c and \
                        ref_data[m] == data[k]
                    m += 1
            elif c == n + i:
                a[i] -= data[k]
            elif data[k] != 0.0:
                ok = False
        same = same and m == ref_indptr[i + 1]
        for k in range(indptr[n + i], indptr[n + i + 1]):
            if indices[k] == n + i:
                b[i] += data[k]
        if diagonal[i] == 0.0:
            ok = False
        S_indptr[i + 1] += S_indptr[i]
    largest = 0.0
    if same:
        S_indptr, S_indices, S_data = ref_indptr.astype(np.int64), ref_indices, ref_data
        for k in range(S_data.size if check_model else 0):
            largest = max(largest, abs(S_data[k]))
    else:
        S_indices = np.empty(S_indptr[n], dtype=indices.dtype)
        S_data = np.empty(S_indptr[n])
        for i in range(n):
            m = S_indptr[i]
            for k in range(indptr[i], indptr[i + 1]):
                if indices[k] < n:
                    S_indices[m], S_data[m] = indices[k], data[k]
                    largest = max(largest, abs(data[k]))
                    m += 1
    # second block: row N + l of A minus the model (S_lj in column j at contact vertices j,
    # N + j at free ones; b_l in column N + l at a contact vertex l), scattered into `work`
    tol = rtol * largest
    work = np.zeros(2 * n if check_model else 0)
    for i in range(n if check_model else 0):
        if not ok:
            break
        for k in range(indptr[n + i], indptr[n + i + 1]):
            work[indices[k]] += data[k]
        for k in range(S_indptr[i], S_indptr[i + 1]):
            j = S_indices[k]
            work[j if a[j] != 0.0 else n + j] -= S_data[k]
        if a[i] != 0.0:
            work[n + i] -= b[i]
        for k in range(indptr[n + i], indptr[n + i + 1]):
            ok = ok and abs(work[indices[k]]) <= tol
            work[indices[k]] = 0.0
        for k in range(S_indptr[i], S_indptr[i + 1]):
            j = S_indices[k]
            c = j if a[j] != 0.0 else n + j
            ok = ok and abs(work[c]) <= tol
            work[c] = 0.0
        ok = ok and abs(work[n + i]) <= tol
        work[n + i] = 0.0
    return ok, same, S_indptr, S_indices, S_data, a, b


def mean_gap_split(A, rtol=1e-10, reference=None, contact=None):
    """(S, a, b) if A is a min system with equally weighted rows (module notes, the mean/gap
    split): A = [[S, -diag a], [S (u2 → u1 where a ≠ 0), diag b]], i.e. for Y = (p, q)

        (A Y)[:N] = S p - a q,   (A Y)[N:] = S u2 + b λ,
        (u2, λ) = (p, q) where a ≠ 0 (contact vertices), (q, 0) elsewhere (free vertices),

    with a/(a + b) the same at every contact vertex and S = A[:N, :N] with a nonzero diagonal;
    else None. The second block is compared with this model entry by entry, to rtol of the
    largest entry of S (`_split_entries`: two passes over A's entries, where a product with a
    random vector, the check this replaces, took three sparse products, the diagonals and a
    slicing, 0.26 s at 9.3e5 vertices against 0.10 s): any other matrix fails it.
    `reference`: a sorted CSR matrix (the S of an earlier step, whose AMG `MeanGapAMG` keeps);
    where A[:N, :N] holds the same entries, S is `reference` itself, not a copy (the same
    numbers; at 9.3e5 vertices a copy is 6.5e6 entries of new memory every Newton step).

    `contact` (a boolean mask over the vertices): the caller vouches that A is a min system
    (newton.linear_step: a min step on the eliminated system, u2 eliminated at `contact`),
    whose second block follows the model by construction. Where a ≠ 0 exactly at `contact`
    the second block is then not compared with the model (the second pass: 0.08 s of the
    0.13 s at 9.3e5 vertices); the first pass reads S, a and b and checks the first block,
    against `reference` too, and θ is checked as always. Elsewhere A is checked as any
    other."""
    A = sp.csr_matrix(A)
    n = A.shape[0] // 2
    ref = reference if reference is not None and reference.shape == (n, n) else None
    ref_arrays = (ref.indptr.astype(np.int64), ref.indices, ref.data) if ref is not None \
        else (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=A.indices.dtype), np.zeros(0))
    vouched = contact is not None
    ok, same, indptr, indices, data, a, b = _split_entries(A.indptr, A.indices, A.data, n,
                                                           rtol, *ref_arrays, not vouched)
    if vouched and ok and not np.array_equal(a != 0, contact):   # not as vouched: check
        ok, same, indptr, indices, data, a, b = _split_entries(
            A.indptr, A.indices, A.data, n, rtol, *ref_arrays, True)
    if not ok:
        return None
    if same:
        return _with_theta(ref, a, b, rtol)
    S = sp.csr_matrix((data, indices, indptr), shape=(n, n))
    S.sort_indices()
    return _with_theta(S, a, b, rtol)


def _with_theta(S, a, b, rtol):
    """(S, a, b) where a/(a + b) is the same (to rtol) at every contact vertex (a ≠ 0), else
    None."""
    contact = a != 0
    ab = (a + b)[contact]
    theta = a[contact] / np.where(ab != 0, ab, 1.0)
    if np.any(ab == 0) or (theta.size and np.ptp(theta) > rtol * np.abs(theta).max()):
        return None
    return S, a, b


@kernel
def _principal_entries(indptr, indices, data, keep):
    """The CSR arrays of M[keep][:, keep] (`keep` increasing indices), the entries of each row
    in M's order."""
    number = np.full(indptr.size - 1, -1, dtype=np.int64)
    for i in range(keep.size):
        number[keep[i]] = i
    out_indptr = np.zeros(keep.size + 1, dtype=np.int64)
    for i in range(keep.size):
        count = 0
        for k in range(indptr[keep[i]], indptr[keep[i] + 1]):
            if number[indices[k]] >= 0:
                count += 1
        out_indptr[i + 1] = out_indptr[i] + count
    out_indices = np.empty(out_indptr[-1], dtype=indices.dtype)
    out_data = np.empty(out_indptr[-1])
    m = 0
    for i in range(keep.size):
        for k in range(indptr[keep[i]], indptr[keep[i] + 1]):
            c = number[indices[k]]
            if c >= 0:
                out_indices[m], out_data[m] = c, data[k]
                m += 1
    return out_indptr, out_indices, out_data


def principal_submatrix(M, keep):
    """M[keep][:, keep] for a CSR matrix M and increasing indices `keep` (one compiled pass:
    scipy's two fancy slicings took 0.25 s for 5e5 of 9.3e5 vertices)."""
    indptr, indices, data = _principal_entries(M.indptr, M.indices, M.data,
                                               np.asarray(keep, dtype=np.int64))
    return sp.csr_matrix((data, indices, indptr), shape=(len(keep), len(keep)))


@kernel
def _mean_gap_right_sides(r, theta, free, mean, gap):
    """mean = (1 - θ) r1 + θ r2, gap = (r2 - r1)[free] (`MeanGapAMG.apply`)."""
    n = mean.size
    for i in range(n):
        mean[i] = (1.0 - theta) * r[i] + theta * r[n + i]
    for k in range(free.size):
        gap[k] = r[n + free[k]] - r[free[k]]


@kernel
def _mean_gap_combine(r, m, gap, theta, free, contact, ab, indptr, indices, data, delta, out):
    """out = (m - θ δ, m + (1 - θ) δ), with λ = (r2 - r1 - S δ)/(a + b) at contact vertices;
    δ = `gap` on the free vertices, 0 elsewhere (`delta`: zeros of size N, left zero)."""
    n = m.size
    for k in range(free.size):
        delta[free[k]] = gap[k]
    for i in range(n):
        out[i] = m[i] - theta * delta[i]
        out[n + i] = m[i] + (1.0 - theta) * delta[i]
    for k in range(contact.size):
        c = contact[k]
        s = 0.0
        for e in range(indptr[c], indptr[c + 1]):
            s += data[e] * delta[indices[e]]
        out[n + c] = ((r[n + c] - r[c]) - s) / ab[k]
    for k in range(free.size):
        delta[free[k]] = 0.0


class InnerAMG:
    """The inner PC (BoomerAMG by default, `DEFAULT_INNER`; `inner` the user's options) set up
    on the scipy matrix M, applied to arrays (`solve`, or `b` → `apply` → `x`). The PETSc
    matrix is built on M's own arrays (M, the caller's matrix, is kept as `M` and must not
    change), one copy of it less in memory; the right side and the solution are PETSc vectors
    on the arrays `b` and `x`."""

    def __init__(self, M, inner=None):
        self.M = M
        self.mat = petsc_matrix(M, copy=False)
        self.pc = PETSc.PC().create(PETSc.COMM_SELF)
        self.pc.setOperators(self.mat)
        options = dict(DEFAULT_INNER if inner is None or "pc_type" not in inner else {})
        options.update(inner or {})
        prefix = f"membranes_vamg_{next(_prefixes)}_"
        database = PETSc.Options()
        for name, value in options.items():
            database[prefix + name] = value
        self.pc.setOptionsPrefix(prefix)
        try:
            self.pc.setFromOptions()
        finally:
            for name in options:
                database.delValue(prefix + name)
        self.pc.setUp()
        self.b, self.x = np.zeros(M.shape[0]), np.zeros(M.shape[0])
        self.rhs, self.sol = (PETSc.Vec().createWithArray(v, comm=PETSc.COMM_SELF)
                              for v in (self.b, self.x))

    def apply(self):
        """One application (a V-cycle) to the array `b`, into the array `x`."""
        self.pc.apply(self.rhs, self.sol)

    def solve(self, r):
        """One application to the array r; a view of the result, valid until the next call."""
        self.b[:] = r
        self.apply()
        return self.x

    def destroy(self):
        """Free the PETSc objects."""
        for obj in (self.pc, self.mat, self.rhs, self.sol):
            obj.destroy()


class VertexAMG:
    """The preconditioner of the module notes for the 2N × 2N scipy matrix A, as a petsc4py
    Python PC context (`apply`); `inner` are the options of the PC on K."""

    def __init__(self, A, inner=None):
        A = sp.csr_matrix(A)
        n = A.shape[0] // 2
        self.B_inv = vertex_blocks_inverse(A)
        A_hat = self.B_inv @ A
        slave = np.zeros(2 * n, dtype=bool)
        slave[n:] = slaves(A)
        self.keep, self.slave = np.flatnonzero(~slave), np.flatnonzero(slave)
        d = gap_scales(A)
        scale = np.ones(2 * n)
        scale[n:] = np.where(slave[n:] | (d == 0), 1.0, np.abs(d))
        self.scale = scale[self.keep]
        K = scaled_rows(A_hat[self.keep][:, self.keep], self.scale)
        K.data /= self.scale[K.indices]
        self.X = A_hat[self.slave][:, self.keep]
        self.amg = InnerAMG(K, inner)

    def apply(self, pc, x, y):
        """y = M⁻¹ x."""
        s = self.B_inv @ x.array_r
        kept = self.amg.solve(s[self.keep] * self.scale) / self.scale
        out = np.empty_like(s)
        out[self.keep] = kept
        out[self.slave] = s[self.slave] - self.X @ kept
        y.array[:] = out

    def destroy(self, pc=None):
        """Free the PETSc objects (petsc4py calls this when the outer PC is destroyed)."""
        self.amg.destroy()


MEAN_SETTLED = 0.5     # `MeanGapAMG.settle_mean`: the mean's residual floor, as a fraction of
                       # the solve's bound, below which its V-cycles are left out


class MeanGapAMG:
    """The exact mean/gap split of a min system (module notes) as a petsc4py Python PC context:
    (S, a, b) from `mean_gap_split`, one inner PC on S (the mean) and one on S restricted to
    the free vertices (the gap). The mean's PC is set up only where a solve needs it (not
    where `settle_mean` finds the mean settled: every step of a run whose iterates hold the
    exact mean, membranes.mean); it is taken from cache["mean"] when that was set up on the
    same S, and left there for the next step. Where the mean is settled, Krylov.solve solves
    the gap's system S_ff δ = `gap_rhs` alone with the gap's PC and makes the step's
    correction from δ (`gap_correction`; membranes.krylov, "The gap's own solve").
    cache["S"] keeps S itself (`mean_gap_split`'s reference: the next step's S is then this
    matrix, not a copy)."""

    def __init__(self, S, a, b, inner=None, cache=None):
        contact = a != 0
        self.free, self.contact = np.flatnonzero(~contact), np.flatnonzero(contact)
        # without contact the membranes are uncoupled, and any θ splits them exactly
        self.theta = a[contact][0] / (a + b)[contact][0] if self.contact.size else 0.5
        self.ab = (a + b)[contact]
        self.S, self.inner, self.cache = S, inner, cache
        if cache is not None and cache.get("S") is not S:
            mean = cache.pop("mean", None)
            if mean is not None:
                mean.destroy()
            cache["S"] = S
        self.mean, self.owns_mean = None, cache is None
        self.gap = InnerAMG(principal_submatrix(S, self.free), inner) if self.free.size \
            else None
        self.delta = np.zeros(S.shape[0])
        self.mean_rhs, self.no_mean = np.zeros(S.shape[0]), np.zeros(S.shape[0])
        self.mean_settled, self.rho = False, None     # `settle_mean`'s verdict and its ρ

    def _mean_amg(self):
        """The mean's inner PC: the cache's, else set up now (and kept there)."""
        if self.mean is None:
            self.mean = (self.cache or {}).get("mean")
            if self.mean is None:
                self.mean = InnerAMG(self.S, self.inner)
                if self.cache is not None:
                    self.cache["mean"] = self.mean
        return self.mean

    def settle_mean(self, r, bound, theta=None):
        """Before a solve from the residual r = b - A x0 to ‖b - A x‖ ≤ bound: leave the mean's
        V-cycles out of it (m = 0 in every application) where the mean part of r is already
        settled. The mean's equation is S m = ρ, ρ = (1 - θ) r1 + θ r2, and a correction with
        m = 0 (δ and λ only) leaves ρ unchanged (its residual is (-θ g, (1 - θ) g): the λ
        terms cancel as in the module notes). So no such correction brings ‖b - A x‖ below
        ‖ρ‖ / √(θ² + (1 - θ)²), and GMRES can reach that floor as the gap converges. Where the
        floor is at most MEAN_SETTLED · bound, the gap alone has to reach √(1 - 0.25) of the
        bound, and V-cycles on the mean would only move its residual within round-off. That is
        the case at every step of a run whose iterates hold the level's exact mean
        (membranes.mean: the step is solved with ρ taken out of its right side), and
        otherwise from the second Newton step of a level on, whose guess keeps the mean of the
        iterate before (newton.mean_keeping_shift): ρ is then what the last solve left (disk,
        J = 5: 0.15 … 0.74 of the bound; settled at 9 of the 11 later steps), not at the
        first (the prolonged guess does not solve the fine mean's equation: 1e9 … 1e11 of the
        bound). The same Newton steps; at 9.3e5 vertices (h0 = 0.132, J = 6) the finest level
        took 15.0 s instead of 15.9 s, with 137 GMRES iterations instead of 142 in the run
        (the shifted guess). A settled mean's inner PC is not set up. `theta`: the caller's
        θ, taken where no vertex is in contact (the membranes are uncoupled then, and any θ
        splits them exactly). ρ is kept (`rho`) for the test of the gap's own solve
        (membranes.krylov)."""
        n = self.S.shape[0]
        if theta is not None and not self.contact.size:
            self.theta = theta
        theta = self.theta
        self.rho = rho = (1.0 - theta) * r[:n] + theta * r[n:]
        floor = np.linalg.norm(rho) / np.hypot(theta, 1.0 - theta)
        self.mean_settled = bool(floor <= MEAN_SETTLED * bound)

    def apply(self, pc, x, y):
        """y = M⁻¹ x: m = S⁻¹((1 - θ) r1 + θ r2), δ_free = S_ff⁻¹ (r2 - r1)_free (δ = 0 at
        contact), u1 = m - θ δ, u2 = m + (1 - θ) δ, λ_contact = (r2 - r1 - S δ)/(a + b)
        (`_mean_gap_right_sides`, `_mean_gap_combine`: one compiled pass each side of the
        V-cycles, where numpy made a dozen temporaries of size N); m = 0 where the mean is
        settled."""
        r = x.array_r
        gap = self.gap.b if self.gap is not None else self.delta[:0]
        mean = None if self.mean_settled else self._mean_amg()
        _mean_gap_right_sides(r, self.theta, self.free,
                              self.mean_rhs if mean is None else mean.b, gap)
        if mean is not None:
            mean.apply()
        if self.gap is not None:
            self.gap.apply()
            gap = self.gap.x
        S = self.S
        _mean_gap_combine(r, self.no_mean if mean is None else mean.x, gap, self.theta,
                          self.free, self.contact, self.ab, S.indptr, S.indices, S.data,
                          self.delta, y.array)

    def gap_rhs(self, r):
        """The gap's right side (r2 - r1) on the free vertices, for the residual r (2N)."""
        n = self.S.shape[0]
        return r[n + self.free] - r[self.free]

    def gap_correction(self, r, gap):
        """The correction Y (2N) with the mean 0 and δ = `gap` on the free vertices (0 at
        contact), λ at the contact vertices from the residual r (`apply`'s second half): with
        gap = S_ff⁻¹ `gap_rhs(r)` it solves A Y = r exactly where the mean part of r is 0."""
        S = self.S
        out = np.empty(2 * S.shape[0])
        _mean_gap_combine(r, self.no_mean, np.ascontiguousarray(gap, dtype=float), self.theta,
                          self.free, self.contact, self.ab, S.indptr, S.indices, S.data,
                          self.delta, out)
        return out

    def destroy(self, pc=None):
        """Free the PETSc objects, except the mean's inner PC when the cache keeps it."""
        for amg in ([self.gap] + ([self.mean] if self.owns_mean else [])):
            if amg is not None:
                amg.destroy()


def vertex_amg(A, inner=None, cache=None, contact=None):
    """The Python PC context for the eliminated system A: `MeanGapAMG` where `mean_gap_split`
    finds a min system, else `VertexAMG`; `cache`: a dict kept from one Newton step to the next
    (the mean's inner PC); `contact`: see `mean_gap_split` (a min step's caller vouches for
    its structure)."""
    A = sp.csr_matrix(A)
    check_shape(A)
    split = mean_gap_split(A, reference=(cache or {}).get("S"), contact=contact)
    if split is not None:
        return MeanGapAMG(*split, inner=inner, cache=cache)
    return VertexAMG(A, inner)
