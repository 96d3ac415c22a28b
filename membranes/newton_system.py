"""The semismooth Newton system A X = B in its two forms (DESIGN §2, §3).

Unknowns X = (X1, X2, X3) = (u1, u2, λ) nodal, block layout, X ∈ R^{3N}.

Linear rows (fixed for a mesh):  E X = F,  E = [[μ1 S, 0, -D], [0, μ2 S, D]], with the rows of
boundary vertices replaced by the Dirichlet rows u1 = g, u2 = 0.
Complementarity rows (change with the iterate): α_l (X1 - X2)_l + β_l X3_l = B3_l for interior
vertices l (cfunctions.linearise), λ_l = 0 at boundary vertices.

* full 3N system: A = [E; J], B = [F; B3] with J = [diag α, -diag α, diag β];
* eliminated 2N system: each complementarity row is used to eliminate one unknown per vertex,
  λ_l where |β_l| ≥ |α_l| (boundary vertices included), else u2_l. With X = T Y + t,
  Y = (u1, z), z_l = u2_l or λ_l, the system is (E T) Y = F - E t and R3 = 0 exactly.

R_lin(X) = (F - E X, -C(X)) is the nonlinear residual of DESIGN §8 (with -λ_l in the boundary
rows of the third block).

**Units (DESIGN §11: tolerances relative to the data scale).** The rows of membrane α are
loads, of size μ_α times a displacement; λ is a pressure. Left as they are, a relative
residual ‖R_lin‖/‖(F, 0)‖ is the residual of the stiffer membrane alone when μ1/μ2 is extreme
(measured before this scaling: μ1/μ2 = 1e6, GMRES stopped at ‖R_alg‖/‖B‖ = 2e-12 with the
constraint violated by 2e-7 of the data, and on other data Newton stalled at 1.3e-9), and the
C-function compares a displacement with a pressure, so that its Newton path depends on the
unit of λ. Two fixed, data-independent scalings put every row in units of displacement:

* `weights` W: the rows of membrane α (interior vertices) are divided by μ_α, the Dirichlet
  rows u_α = g, 0 keep weight 1 (μ_α S has entries μ_α times O(1) in 2D);
* `kappa` κ = (1/μ1 + 1/μ2)/2 = 1/μ_H (μ_H the harmonic mean): the C-function acts on
  (u1 - u2, κ λ), κ λ the gap change a pressure λ makes on membranes of unit size. Its rows
  are α (X1 - X2) + β X3 with β = κ ∂C/∂b (cfunctions.linearise).

Newton measures R_lin with the membrane rows weighted, relative to ‖W F‖ (`norm_F`), and the
Krylov solver sees the weighted system W A, W B (`newton.linear_step`), which is the same
linear system: iterates and solutions are unchanged, only the norm that GMRES minimises and
that the tests read changes. For μ1 = μ2 = 1 both scalings are the identity (the paper's
setting, DESIGN §3, §8). Scaling f1, f2, g by s scales X by s and leaves W and κ alone, so
iteration counts do not change; scaling μ1, μ2, f1, f2 by t leaves u and W F, κ λ alone.
Residuals R handed to the estimators are always the unweighted ones (DESIGN §4).
"""

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import cfunctions
from .compiled import kernel
from .kept import KeptArrays
from .linear_solve import row_buffers, scaled_rows, written_csr


@dataclass
class LinearRows:
    """E (2N × 3N, Dirichlet rows included) and F (2N) of a discretisation."""
    E: sp.csr_matrix
    F: np.ndarray
    n: int
    boundary: np.ndarray
    weights: np.ndarray = None     # W: row weights of E (2N), see the module notes
    kappa: float = 1.0             # κ: the C-function acts on (u1 - u2, κ λ)

    def __post_init__(self):
        if self.weights is None:
            self.weights = np.ones(2 * self.n)
        self.norm_F = float(np.linalg.norm(self.weights * self.F))

    @functools.cached_property
    def weighted_E(self):
        """W E, formed once (E itself where W = 1, e.g. μ1 = μ2 = 1; else a second matrix of
        E's size, kept with it)."""
        return self.E if np.all(self.weights == 1.0) else scaled_rows(self.E, self.weights)

    @functools.cached_property
    def product_room(self):
        """What the eliminated systems of these rows are written into (`eliminated_system`):
        their row pointers, column indices and values kept from one Newton step to the next
        (membranes.kept), the compiled pass's dense row accumulator (its flags all False
        between passes), and the number of E's entries in each column (for the room a product
        needs)."""
        n2 = 2 * self.n
        return ((KeptArrays(), KeptArrays(), KeptArrays()),
                (np.empty(n2), np.zeros(n2, dtype=np.bool_), np.empty(n2, dtype=np.int64)),
                np.bincount(self.E.indices, minlength=3 * self.n))

    def weighted(self, R):
        """R (2N or 3N) with its first 2N entries (the rows of E) multiplied by W."""
        R = np.array(R, dtype=float)
        R[:2 * self.n] *= self.weights
        return R

    def unweighted(self, R):
        """The inverse of `weighted`."""
        R = np.array(R, dtype=float)
        R[:2 * self.n] /= self.weights
        return R

    def relative_residual(self, cfun, X):
        """‖W R_lin(X)‖/‖W F‖: the nonlinear residual relative to the data scale."""
        return float(np.linalg.norm(self.weighted(nonlinear_residual(self, cfun, X)))) \
            / self.norm_F


def linear_rows(disc):
    """Assemble E and F with the Dirichlet rows u1 = g, u2 = 0 on boundary vertices.

    E is built from the CSR arrays of S1 and S2 in one compiled pass (`_membrane_entries`;
    scipy's bmat of the blocks, which converts them all to COO and back, took 7 times as long
    as numpy passes at 9.3e5 vertices, and those 5 times as long as compiled ones): the 2N
    rows of S1 and of S2 (its columns shifted by N), ∓D_l (column 2N + l) at the end of each;
    a boundary row holds its diagonal entry 1 alone (a stiffness matrix stores the diagonal).
    Without stiffness matrices (discretise with stiffness=False) E is None: F and the weights
    alone."""
    n = disc.n
    interior = disc.interior
    E = None if disc.S1 is None else _membrane_rows(disc)
    F1, F2 = disc.F1.copy(), disc.F2.copy()
    F1[disc.boundary] = disc.problem.g
    F2[disc.boundary] = 0.0
    mu1, mu2 = disc.problem.mu1, disc.problem.mu2
    weights = np.concatenate([np.where(interior, 1.0 / mu1, 1.0),
                              np.where(interior, 1.0 / mu2, 1.0)])
    return LinearRows(E, np.concatenate([F1, F2]), n, disc.boundary, weights,
                      0.5 * (1.0 / mu1 + 1.0 / mu2))


def _membrane_rows(disc):
    """E of `linear_rows`, from the CSR arrays of S1 and S2 (`_membrane_entries`)."""
    n = disc.n
    S1, S2 = (sp.csr_matrix(S) for S in (disc.S1, disc.S2))
    S1, S2 = (S if S.has_sorted_indices else S.sorted_indices() for S in (S1, S2))
    interior = disc.interior
    slot = np.where(interior, disc.D, 0.0)
    indptr = np.zeros(2 * n + 1, dtype=np.int64)
    indices, data = row_buffers(S1.nnz + S2.nnz + 2 * n)
    if not _membrane_entries(S1.indptr, S1.indices, S1.data, S2.indptr, S2.indices, S2.data,
                             interior, slot, indptr, indices, data):
        raise ValueError("a stiffness matrix without its diagonal entry in a boundary row")
    return written_csr(indptr, indices, data, (2 * n, 3 * n))


@kernel
def _membrane_entries(indptr1, indices1, data1, indptr2, indices2, data2, interior, slot,
                      out_indptr, out_indices, out_data):
    """The CSR arrays of E (`linear_rows`), zeros not stored: row l of block α is row l of
    S_α (columns shifted by (α - 1) N) and ∓slot_l in column 2N + l at an interior vertex,
    the single entry 1 on the diagonal at a boundary vertex; rows written one after the
    other, out_indptr[i + 1] where row i ends. False if a boundary row of S_α stores no
    diagonal entry."""
    n = interior.size
    stored = 0
    for block in range(2):
        indptr, indices, data = (indptr2, indices2, data2) if block else \
            (indptr1, indices1, data1)
        sign = 1.0 if block else -1.0
        for i in range(n):
            row = block * n + i
            if interior[i]:
                for k in range(indptr[i], indptr[i + 1]):
                    if data[k] != 0.0:
                        out_indices[stored] = indices[k] + block * n
                        out_data[stored] = data[k]
                        stored += 1
                if slot[i] != 0.0:
                    out_indices[stored], out_data[stored] = 2 * n + i, sign * slot[i]
                    stored += 1
            else:
                found = False
                for k in range(indptr[i], indptr[i + 1]):
                    found = found or indices[k] == i
                if not found:
                    return False
                out_indices[stored], out_data[stored] = row, 1.0
                stored += 1
            out_indptr[row + 1] = stored
    return True


def initial_residual(rows, X):
    """R = (F - E X, 0) (3N): the residual DESIGN §4 reads at an iterate that no linear solve
    produced (X^0), whose linear rows are out of balance."""
    return np.concatenate([rows.F - rows.E @ X, np.zeros(rows.n)])


def initial_guess(rows, g):
    """X^0 = (g, 0, 0) of the paper: u1 = g everywhere, u2 = 0, λ = 0 (DESIGN §3)."""
    X = np.zeros(3 * rows.n)
    X[:rows.n] = g
    return X


def split(X, n):
    return X[:n], X[n:2 * n], X[2 * n:]


def complementarity_rows(rows, cfun, X, at_projection=False):
    """α, β, B3 of C(u1 - u2, κ λ) at X (or, for Fischer–Burmeister, at_projection: at the
    projection of (u1 - u2, κ λ) onto the complementarity set, cfunctions.linearise);
    boundary vertices get the Dirichlet row κ λ_l = 0 (α = 0, β = κ)."""
    u1, u2, lam = split(X, rows.n)
    alpha, beta, B3 = cfunctions.linearise(cfun, u1 - u2, lam, rows.kappa, at_projection)
    alpha[rows.boundary], beta[rows.boundary], B3[rows.boundary] = 0.0, rows.kappa, 0.0
    return alpha, beta, B3


def nonlinear_residual(rows, cfun, X):
    """R_lin = (F - E X, -C(u1 - u2, κ λ)) (DESIGN §8; κ of the module notes)."""
    u1, u2, lam = split(X, rows.n)
    C = cfunctions.get(cfun)[0](u1 - u2, rows.kappa * lam)
    C[rows.boundary] = rows.kappa * lam[rows.boundary]
    return np.concatenate([rows.F - rows.E @ X, -C])


def full_system(rows, alpha, beta, B3):
    """A = [E; J_C], B = [F; B3] (3N × 3N)."""
    J = sp.hstack([sp.diags(alpha), sp.diags(-alpha), sp.diags(beta)])
    return sp.vstack([rows.E, J], format="csr"), np.concatenate([rows.F, B3])


@dataclass
class Elimination:
    """X = T Y + t, T = [[I, 0], [diag U, diag H], [diag G, diag Q]] (`coefficients` = (U, H,
    G, Q)); `eliminate_lambda[l]` tells which unknown vertex l lost."""
    coefficients: tuple
    t: np.ndarray
    eliminate_lambda: np.ndarray

    def expand(self, Y):
        """T Y + t, without T: (u1, U u1 + H z, G u1 + Q z) + t (the same sums as T @ Y)."""
        U, H, G, Q = self.coefficients
        n = len(U)
        u1, z = Y[:n], Y[n:]
        return np.concatenate([u1, U * u1 + H * z, G * u1 + Q * z]) + self.t


def vertex_pair_rows(*pairs):
    """The CSR matrix (k n × 2n, k = len(pairs)) whose row i n + l holds pairs[i][0][l] in
    column l and pairs[i][1][l] in column n + l (zeros stored): rows that couple the two
    unknowns of each vertex l of the 2N systems (u1_l and z_l, or the 2×2 vertex blocks)."""
    n = len(pairs[0][0])
    pair = np.stack([np.arange(n), np.arange(n, 2 * n)], axis=1).ravel()
    data = np.concatenate([np.stack([a, b], axis=1).ravel() for a, b in pairs])
    return sp.csr_matrix((data, np.tile(pair, len(pairs)), 2 * np.arange(len(pairs) * n + 1)),
                         shape=(len(pairs) * n, 2 * n))


def eliminate(n, alpha, beta, B3, kappa=1.0):
    """The substitution X = T Y + t that satisfies every complementarity row exactly; the
    choice compares the C-function's own derivatives, |∂C/∂b| = |β|/κ against |α|."""
    lam_out = np.abs(beta) >= kappa * np.abs(alpha)
    u2_out = ~lam_out
    a_safe = np.where(u2_out, alpha, 1.0)
    b_safe = np.where(lam_out, beta, 1.0)
    L, U = lam_out.astype(float), u2_out.astype(float)
    H, G, Q = L + U * beta / a_safe, -L * alpha / b_safe, L * alpha / b_safe + U
    t = np.concatenate([np.zeros(n), -U * B3 / a_safe, L * B3 / b_safe])
    return Elimination((U, H, G, Q), t, lam_out)


@kernel
def _product_entries(indptr, indices, data, n, U, H, G, Q, out_indptr, out_indices, out_data,
                     acc, seen, touched):
    """The CSR arrays of E T (E: 2N × 3N, T of `Elimination`) without forming T: an entry v of
    E in column l, N + l or 2N + l goes to columns l and N + l of the product with the factors
    (1, 0), (U_l, H_l) or (G_l, Q_l). Row by row, as scipy's csr_matmat: the products summed
    in E's order in a dense accumulator, zero sums not stored (at most two terms meet in one
    entry, so the sums are those of E @ T, bit for bit); each row's columns sorted (by
    insertion: a row has a dozen). Rows written one after the other, out_indptr[i + 1] where
    row i ends (an entry of E gives one entry of the product for each of its two factors that
    is not 0, at most). `acc`, `seen`, `touched`: 2N each, the accumulator, its flags (all
    False on entry, and so left) and the row's columns."""
    stored = 0
    for i in range(indptr.size - 1):
        m = 0
        for k in range(indptr[i], indptr[i + 1]):
            c, v = np.int64(indices[k]), data[k]
            if c < n:
                j1, w1, j2, w2 = c, v, n + c, 0.0
            elif c < 2 * n:
                j1, w1, j2, w2 = c - n, v * U[c - n], c, v * H[c - n]
            else:
                j1, w1, j2, w2 = c - 2 * n, v * G[c - 2 * n], c - n, v * Q[c - 2 * n]
            for second in range(2):
                j, w = (j2, w2) if second else (j1, w1)
                if not seen[j]:
                    if w == 0.0:
                        continue
                    seen[j] = True
                    acc[j] = w
                    p = m                   # insertion into the sorted columns of the row
                    while p > 0 and touched[p - 1] > j:
                        touched[p] = touched[p - 1]
                        p -= 1
                    touched[p] = j
                    m += 1
                else:
                    acc[j] += w
        for p in range(m):
            j = touched[p]
            if acc[j] != 0.0:
                out_indices[stored], out_data[stored] = j, acc[j]
                stored += 1
            seen[j] = False
        out_indptr[i + 1] = stored


def eliminated_system(rows, alpha, beta, B3, weighted=False):
    """Ã = E T, B̃ = F - E t (2N × 2N) and the elimination that maps Y back to X; weighted:
    W Ã = (W E) T and W B̃ (the system the solvers see, module notes). Ã by
    `_product_entries` (one compiled pass over E's entries; scipy's product, its zero entries
    dropped and its columns sorted for PETSc, took 6 times as long as two such passes at 9.3e5
    vertices, counting and writing; one pass 0.19 s a step, where two took 0.26 s), column
    indices sorted. Written into arrays kept from one step to the next (`rows.product_room`,
    membranes.kept: no fresh pages for them once the step before has let go of its system),
    with room for the entries the factors of T allow (each nonzero factor of an entry of E
    gives at most one entry of Ã: for min, E's entries in the u1 and u2 columns and in the λ
    columns of the vertices where u2 is eliminated, so that the matrix holds more than half
    of its buffers, and scipy takes their prefixes as they are)."""
    elim = eliminate(rows.n, alpha, beta, B3, rows.kappa)
    E, F = (rows.weighted_E, rows.weights * rows.F) if weighted else (rows.E, rows.F)
    n = rows.n
    kept, scratch, count = rows.product_room
    U, H, G, Q = elim.coefficients
    room = int(count[:n].sum() + count[n:2 * n] @ ((U != 0).astype(np.int64) + (H != 0)) +
               count[2 * n:] @ ((G != 0).astype(np.int64) + (Q != 0)))
    index = np.int32 if room <= np.iinfo(np.int32).max else np.int64   # as scipy would take
    indptr = kept[0].empty(2 * n + 1, index)
    indptr[0] = 0
    indices, data = kept[1].empty(room, index), kept[2].empty(room)
    _product_entries(E.indptr, E.indices, E.data, n, U, H, G, Q, indptr, indices, data,
                     *scratch)
    nnz = int(indptr[-1])
    A = sp.csr_matrix((data[:nnz], indices[:nnz], indptr), shape=(2 * n, 2 * n))
    A.has_sorted_indices = True
    return A, F - E @ elim.t, elim
