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
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from . import cfunctions


@dataclass
class LinearRows:
    """E (2N × 3N, Dirichlet rows included) and F (2N) of a discretisation."""
    E: sp.csr_matrix
    F: np.ndarray
    n: int
    boundary: np.ndarray

    @property
    def norm_F(self):
        """‖(F, 0)‖, the scale of the relative nonlinear residual."""
        return float(np.linalg.norm(self.F))


def linear_rows(disc):
    """Assemble E and F with the Dirichlet rows u1 = g, u2 = 0 on boundary vertices."""
    n = disc.n
    Dm = sp.diags(disc.D)
    E = sp.bmat([[disc.S1, None, -Dm], [None, disc.S2, Dm]], format="csr")
    bmask = np.zeros(n)
    bmask[disc.boundary] = 1.0
    keep = sp.diags(np.concatenate([1.0 - bmask, 1.0 - bmask]))
    dirichlet = sp.hstack([sp.diags(np.concatenate([bmask, bmask])),
                           sp.csr_matrix((2 * n, n))])
    E = (keep @ E + dirichlet).tocsr()
    E.eliminate_zeros()
    F1, F2 = disc.F1.copy(), disc.F2.copy()
    F1[disc.boundary] = disc.problem.g
    F2[disc.boundary] = 0.0
    return LinearRows(E, np.concatenate([F1, F2]), n, disc.boundary)


def initial_guess(rows, g):
    """X^0 = (g, 0, 0) of the paper: u1 = g everywhere, u2 = 0, λ = 0 (DESIGN §3)."""
    X = np.zeros(3 * rows.n)
    X[:rows.n] = g
    return X


def split(X, n):
    return X[:n], X[n:2 * n], X[2 * n:]


def complementarity_rows(rows, cfun, X):
    """α, β, B3 at X; boundary vertices get the Dirichlet row λ_l = 0 (α = 0, β = 1)."""
    u1, u2, lam = split(X, rows.n)
    alpha, beta, B3 = cfunctions.linearise(cfun, u1 - u2, lam)
    alpha[rows.boundary], beta[rows.boundary], B3[rows.boundary] = 0.0, 1.0, 0.0
    return alpha, beta, B3


def nonlinear_residual(rows, cfun, X):
    """R_lin = (F - E X, -C(X)) (DESIGN §8)."""
    u1, u2, lam = split(X, rows.n)
    C = cfunctions.get(cfun)[0](u1 - u2, lam)
    C[rows.boundary] = lam[rows.boundary]
    return np.concatenate([rows.F - rows.E @ X, -C])


def full_system(rows, alpha, beta, B3):
    """A = [E; J_C], B = [F; B3] (3N × 3N)."""
    J = sp.hstack([sp.diags(alpha), sp.diags(-alpha), sp.diags(beta)])
    return sp.vstack([rows.E, J], format="csr"), np.concatenate([rows.F, B3])


@dataclass
class Elimination:
    """X = T Y + t; `eliminate_lambda[l]` tells which unknown vertex l lost."""
    T: sp.csr_matrix
    t: np.ndarray
    eliminate_lambda: np.ndarray

    def expand(self, Y):
        return self.T @ Y + self.t


def eliminate(n, alpha, beta, B3):
    """The substitution X = T Y + t that satisfies every complementarity row exactly."""
    lam_out = np.abs(beta) >= np.abs(alpha)
    u2_out = ~lam_out
    a_safe = np.where(u2_out, alpha, 1.0)
    b_safe = np.where(lam_out, beta, 1.0)
    L, U = lam_out.astype(float), u2_out.astype(float)
    I = sp.identity(n, format="csr")
    Z = sp.csr_matrix((n, n))
    T = sp.bmat([
        [I, Z],
        [sp.diags(U), sp.diags(L + U * beta / a_safe)],
        [sp.diags(-L * alpha / b_safe), sp.diags(L * alpha / b_safe + U)],
    ], format="csr")
    t = np.concatenate([np.zeros(n), -U * B3 / a_safe, L * B3 / b_safe])
    return Elimination(T, t, lam_out)


def eliminated_system(rows, alpha, beta, B3):
    """Ã = E T, B̃ = F - E t (2N × 2N) and the elimination that maps Y back to X."""
    elim = eliminate(rows.n, alpha, beta, B3)
    A = (rows.E @ elim.T).tocsr()
    A.eliminate_zeros()
    return A, rows.F - rows.E @ elim.t, elim
