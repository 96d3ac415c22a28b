"""The semismooth Newton systems as distributed PETSc matrices (§2, §3, §11, §12).

Unknowns X = (u1, u2, λ) in the iterate layout [u1 owned | u2 owned | λ owned] of every process
(`Discretisation.vector3`). The 2N linear rows (fixed for a mesh) are

    E X = F,   E = [[μ1 S, 0, -D], [0, μ2 S, D]],

with the rows of boundary vertices replaced by the Dirichlet rows u1 = g, u2 = 0 (§2). The N
complementarity rows change with the iterate: α_l (X1 - X2)_l + β_l X3_l = B3_l at interior
vertices (`cfunctions.linearise`) and κ λ_l = 0 at boundary vertices.

**Units (§11).** The rows of membrane α are loads, μ_α times a displacement; λ is a pressure.
Two fixed, data-independent scalings put every row in units of a displacement:

* the row weights W: the rows of membrane α at interior vertices are divided by μ_α (the
  Dirichlet rows u_α = g, 0 keep weight 1, the complementarity rows too);
* the scale κ = ℓ² (1/μ1 + 1/μ2)/2 of the pressure: the C-function acts on (u1 - u2, κ λ), so
  that its Newton path does not depend on the unit of λ (`cfunctions.linearise`). ℓ is the
  domain's unit of length (`length_unit`): a pressure λ bends a membrane of modulus μ by about
  ℓ² λ / μ on a domain of size ℓ, so κ λ is a displacement whatever the domain's size. It is
  π C_PF h_Ω rounded to a power of ten: 1 on the unit disk and square (κ as the design notes
  write it), and a change of the length unit by 10^k (a mesh in mm instead of m) scales κ by
  10^(2k), so the run is the same, counts included. With ℓ = 1 on a square of side 1e-6
  every method diverged at its second Newton step (relative residual 1.2e13: the
  complementarity rows, κ λ ≈ λ, were 1e12 times the membrane rows), and on a side of 1e6 the
  paper preset did not converge in 100 Newton steps.

Without them, for μ1/μ2 = 1e6, a relative residual is that of the stiffer membrane alone and
the constraint of the softer one is left violated far above round-off. Every matrix and
right-hand side here is the *weighted* one, W A and W B: the same linear system, so the same
iterates and solutions; only the norm a Krylov method minimises, and the norm of the stopping
tests, change. The weighted linear rows are exact copies of S: the first block row is
[S_D, 0, -D/μ1], the second [0, S_D, D/μ2], S_D the stiffness matrix with identity rows at the
boundary vertices. Residuals handed to the estimators are always unweighted (§4):
R = W⁻¹ (W B - W A X). For μ1 = μ2 = 1 both scalings are the identity (the paper's setting).

The nonlinear residual of §8 is R_lin(X) = (F - E X, -C(X1 - X2, κ X3)) (with -κ λ_l in the
boundary rows of the third block), and its size relative to the data ‖W R_lin‖/‖W F‖, F with
its Dirichlet values (`relative_residual`). §8 leaves open whether (F, 0) holds them;
with them the test is invariant under scaling the data, but where g dwarfs the loads (far
beyond §11's g ≤ 1e3 for loads of order 1) the Dirichlet rows dominate ‖W F‖ and the exact
and inexact tests can hold before the interior is solved (the adaptive test, on the
estimators, is unaffected; BENCHMARKS.md, "Robustness: what the probes found").

**The full 3N system** (`full_step`): A = [W E; J_C], one distributed AIJ matrix made once per
mesh from a MatNest of the blocks (S_D, the diagonal D blocks, three diagonal J_C blocks) by
PETSc's conversion, which keeps the iterate layout. Each Newton step only overwrites the N
complementarity rows (three entries each, all in the owning process's diagonal block); their
entries stay stored where they are zero, which natural-order ILU(0) needs (the λ-block diagonal
β_l is 0 at a min contact vertex: its pivot is then D_l (1/(μ1 p1_l) + 1/(μ2 p2_l)) > 0, p_α
the ILU pivots of the weighted stiffness rows, whose λ entries are ∓D_l/μ_α).

**The eliminated 2N system** (`eliminated_step`): every complementarity row eliminates one
unknown of its vertex, λ_l where |β_l| ≥ κ |α_l| (the C-function's own derivatives compared:
|∂C/∂b| = |β|/κ against |∂C/∂a| = |α|; boundary vertices, where α = 0, always), else u2_l.
With Y = (u1, z), z_l = u2_l where λ_l goes and z_l = λ_l where u2_l goes,

    X = T Y + t,   T = [[I, 0], [diag U, diag H], [diag G, diag Q]],

    λ eliminated:  u2 = z,                   λ = B3/β - (α/β) u1 + (α/β) z
    u2 eliminated: u2 = u1 + (β/α) z - B3/α,  λ = z,

and the system is (W E T) Y = W F - W E t: T is a sparse PETSc matrix whose pattern (five
entries per vertex, zero factors kept) is the same at every step. Every iterate X = T Y + t
satisfies the complementarity rows exactly, so R3 = 0 and the residual is W⁻¹ (b - A Y) in the
two membrane blocks.

**W E is never assembled for a product with a vector.** W E is a MatNest of S_D and the two
diagonals (`E_op`: no copy of S_D), whose products with vectors in the iterate layout are
those of the assembled matrix. The eliminated matrix A = W E T is needed as a matrix only by
a PETSc preconditioner that reads its entries (a user's ``pc_type``, `eliminated_step`
``assembled=True``): then W E is converted to one AIJ matrix once and A is one numeric
MatMatMult per step on the symbolic product of the first. The mean/gap preconditioner
(membranes.linalg.preconditioners) reads S_D only, so for it A is the operator Y ↦ W E (T Y)
(a PETSc shell matrix): the same products (A has about the nonzeros of E and T together) and
no product to form at every step, nor its memory.
"""

import math
import weakref
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from ..model.checks import UNDERFLOW_SCALE
from . import cfunctions

# Every test of §8 compares a norm with a tolerance times ‖W (F, 0)‖, and the norms are roots
# of sums of squares (PETSc's VecNorm too). Below UNDERFLOW_SCALE (model.checks) of ‖W (F, 0)‖
# the square of a residual at round-off, (ε ‖W (F, 0)‖)², is no longer a normal double: the
# residuals read 0, and the tests pass on noise. With data scaled by 1e-160 (g = 1e-161 on the
# square) the adaptive variant stopped after one step with λ = 0 and η = 0; exact Newton
# reported a relative residual of 0 from 1e-150 on and stopped early from 1e-154 (theory §11:
# the problem is positively homogeneous, the data can be rescaled). The symmetric limit,
# ‖W (F, 0)‖² overflowing, is the overflow check of NewtonSystem.


def _ints(a):
    return np.ascontiguousarray(a, dtype=PETSc.IntType)


def diagonal_matrix(values, offset, size, comm):
    """The AIJ matrix diag(values) (`values` the owned entries, rows from `offset`, global
    `size`), every diagonal entry stored, zeros included."""
    n = len(values)
    indptr = _ints(np.arange(n + 1))
    indices = _ints(offset + np.arange(n))
    M = PETSc.Mat().createAIJ(((n, size), (n, size)),
                              csr=(indptr, indices, np.asarray(values, dtype=float)), comm=comm)
    M.assemble()
    return M


def initial_guess(disc, X0=None):
    """X⁰ for Newton on `disc` (a new Vec): the paper's (g, 0, 0) (§3) for X0 None, else a copy
    of X0 with the Dirichlet values of §2 (u1 = g, u2 = 0, λ = 0) at the boundary vertices.
    The Dirichlet rows are identities in every Newton system, so an exact step sets them
    anyway; from a guess that has them every Krylov iterate keeps them, and its residual
    vanishes at the Dirichlet vertices, as the lifting of §4 and the bound of §7 assume."""
    X = disc.vector3()
    n = disc.n
    if X0 is None:
        X.array[:n] = disc.g
        return X
    X0.copy(X)
    b = disc.boundary_owned
    X.array[b] = disc.g
    X.array[n + b] = 0.0
    X.array[2 * n + b] = 0.0
    return X


def final_residual(disc, X, cfun):
    """The algebraic residual R = B - A X of an iterate X that ends a solve, for its
    certificate (§4, §7): its membrane blocks are those of the nonlinear residual, F - E X,
    whatever the linearisation (the third block, unused by the estimators, is set to zero).
    Newton does not keep it, and a peer's iterate has none, so it is formed here once."""
    sys_ = NewtonSystem(disc)
    try:
        R, _ = sys_.nonlinear_residual(X, cfun)
    finally:
        sys_.destroy()
    R.array[2 * disc.n:] = 0.0
    return R


def _converted(blocks, comm):
    """The MatNest of `blocks` converted to one AIJ matrix (the iterate layout)."""
    nest = PETSc.Mat().createNest(blocks, comm=comm)
    return nest.convert("aij")                  # in place (petsc4py's convert without `out`)


@dataclass
class Linearisation:
    """The complementarity rows α (X1 - X2) + β X3 = B3 at an iterate (owned entries) and
    ‖W B‖ of its 3N right-hand side."""
    alpha: np.ndarray
    beta: np.ndarray
    B3: np.ndarray
    norm_B: float


def length_unit(poincare):
    """ℓ of κ (module notes): the power of ten nearest to π C_PF h_Ω, `poincare` = C_PF h_Ω
    (§7; for a box a × b, π C_PF h_Ω = (1/a² + 1/b²)^(-1/2), the shorter side for a strip)."""
    return 10.0 ** round(math.log10(math.pi * poincare))


class NewtonSystem:
    """The linear rows of §2 on one discretisation, weighted by W (module notes), and the
    Newton systems of its iterates."""

    def __init__(self, disc):
        self.disc, self.comm = disc, disc.comm
        self.n, self.N = disc.n, disc.n_global
        mu1, mu2 = float(disc.mu1), float(disc.mu2)
        self.mu = (mu1, mu2)
        self.length = length_unit(disc.poincare)                   # ℓ of κ (module notes)
        self.kappa = 0.5 * (1.0 / mu1 + 1.0 / mu2) * self.length ** 2     # κ of §3, §11
        self.theta = mu2 / (mu1 + mu2)                      # z = μ1 u1 + μ2 u2 ∝ (1-θ) u1 + θ u2
        self.offset = disc.S.getOwnershipRange()[0]          # first owned P1 dof (global)
        self.boundary = disc.boundary_owned
        inner = disc.interior
        n, N, r0, comm = self.n, self.N, self.offset, self.comm
        # S_D: the stiffness matrix with identity rows at the boundary vertices
        self.S_D = disc.S.copy()
        self.S_D.zeroRows(_ints(self.boundary + r0), 1.0)
        # D_l = (ψ_l, 1) from the lumped (vertex-rule) contact form, 0 in Dirichlet rows
        d = np.where(inner, disc.D.array_r[:n], 0.0)
        self.D = d
        self._D1 = diagonal_matrix(-d / mu1, r0, N, comm)
        self._D2 = diagonal_matrix(d / mu2, r0, N, comm)
        # the blocks of W E; as an operator (a MatNest: the blocks are referenced, not copied),
        # and as one AIJ matrix only where an assembled eliminated matrix is asked for (`E`)
        self._E_blocks = [[self.S_D, None, self._D1], [None, self.S_D, self._D2]]
        self.E_op = PETSc.Mat().createNest(self._E_blocks, comm=comm)
        self._E = None
        self._operator = None                                # A = W E T as a shell (`_product`)
        self._A = None                                       # the full matrix, when asked for
        self._T = self._AT = self._T_pattern = None          # T and A = E T of the eliminated
        # the weights W (3N; 1 in the third block) and the weighted right side W (F, 0)
        self.W = disc.vector3()
        self.W.array[:n] = np.where(inner, 1.0 / mu1, 1.0)
        self.W.array[n:2 * n] = np.where(inner, 1.0 / mu2, 1.0)
        self.W.array[2 * n:] = 1.0
        self.WF = disc.vector3()
        self.WF.array[:n] = np.where(inner, disc.F1.array_r[:n] / mu1, disc.g)
        self.WF.array[n:2 * n] = np.where(inner, disc.F2.array_r[:n] / mu2, 0.0)
        self.norm_F = self.WF.norm()                         # ‖W (F, 0)‖
        if np.isnan(self.norm_F):    # not an overflow: data undefined where they are integrated
            raise ValueError("the loads are not a number (NaN) at some quadrature points: f1 "
                             "or f2 is undefined somewhere on the mesh (e.g. sqrt or a "
                             "fractional power of a negative number)")
        infinite = not np.all(np.isfinite(self.WF.array_r))
        if comm.allreduce(infinite, op=MPI.LOR):
            # an entry ∫ f φ itself infinite: not a scale that rescaling cures (1/(x - 0.5)
            # met a quadrature point on x = 0.5, where the data's sample points missed it)
            raise ValueError("the loads are infinite at some quadrature points: f1 or f2 "
                             "has a singularity on the mesh (e.g. 1/(x - 0.5) on a line of "
                             "its points) or exceeds double precision there")
        if not (np.isfinite(self.norm_F) and np.isfinite(self.kappa)):
            raise ValueError(f"the data overflow double precision: ||W (F, 0)|| = "
                             f"{self.norm_F:g}, kappa = {self.kappa:g} (mu1 = {mu1:g}, "
                             f"mu2 = {mu2:g}, g = {float(disc.g):g}); rescale them: the "
                             f"solution scales with f / mu and g (theory §11)")
        if not self.kappa > 0.0:
            raise ValueError(f"the pressure scale kappa = l^2 (1/mu1 + 1/mu2)/2 underflows "
                             f"double precision (l = {self.length:g}, mu1 = "
                             f"{mu1:g}, mu2 = {mu2:g}); rescale the lengths or the moduli "
                             f"(theory §3, §11)")
        if self.norm_F < UNDERFLOW_SCALE:
            raise ValueError(f"the data underflow double precision: ||W (F, 0)|| = "
                             f"{self.norm_F:g} < {UNDERFLOW_SCALE:.1e} (mu1 = {mu1:g}, "
                             f"mu2 = {mu2:g}, g = {float(disc.g):g}); rescale them: the "
                             f"solution scales with f / mu and g (theory §11)")
        self.WF2 = PETSc.Vec().createMPI((2 * n, 2 * N), comm=comm)    # W F, 2N layout
        self.WF2.array[:] = self.WF.array_r[:2 * n]
        self._r2 = self.WF2.duplicate()

    # ## Iterates

    def split(self, X):
        return self.disc.split(X)

    def _sum(self, local):
        from mpi4py import MPI
        return self.comm.allreduce(float(local), op=MPI.SUM)

    # ## The nonlinear residual (§8)

    def constraint(self, X, cfun):
        """C(u1 - u2, κ λ) on the owned vertices, κ λ at the boundary vertices."""
        u1, u2, lam = self.split(X)
        C = cfunctions.value(cfun, u1 - u2, lam, self.kappa)
        C[self.boundary] = self.kappa * lam[self.boundary]
        return C

    def relative_residual(self, X, cfun, out=None):
        """‖W R_lin(X)‖/‖W F‖ (§8, §11); with `out` (a 3N Vec) also R_lin = (F - E X, -C)
        itself, unweighted, written there (`nonlinear_residual`)."""
        r = self._r2
        self.E_op.mult(X, r)
        r.aypx(-1.0, self.WF2)                               # W (F - E X)
        C = self.constraint(X, cfun)
        if out is not None:
            n = self.n
            out.array[:2 * n] = r.array_r / self.W.array_r[:2 * n]
            out.array[2 * n:] = -C
        return np.sqrt(r.norm() ** 2 + self._sum(C @ C)) / self.norm_F

    def nonlinear_residual(self, X, cfun, out=None):
        """(R_lin, ‖W R_lin‖/‖W F‖): R_lin = (F - E X, -C) unweighted (a 3N Vec, `out` if
        given), and its weighted size relative to the data (module notes)."""
        if out is None:
            out = self.disc.vector3()
        return out, self.relative_residual(X, cfun, out)

    # ## The linearisation (§3)

    def linearise(self, X, cfun):
        """α, β, B3 of the Newton rows at X; boundary vertices get κ λ_l = 0 (α = 0, β = κ)."""
        u1, u2, lam = self.split(X)
        alpha, beta, B3 = cfunctions.linearise(cfun, u1 - u2, lam, self.kappa)
        b = self.boundary
        alpha[b], beta[b], B3[b] = 0.0, self.kappa, 0.0
        return Linearisation(alpha, beta, B3, np.sqrt(self.norm_F ** 2 + self._sum(B3 @ B3)))

    def full_matrix(self):
        """W A with placeholder complementarity rows (made once; `full_step` fills them)."""
        if self._A is None:
            one = diagonal_matrix(np.ones(self.n), self.offset, self.N, self.comm)
            self._A = _converted(self._E_blocks + [[one, one, one]], self.comm)
            one.destroy()
        return self._A

    def full_step(self, lin):
        """The full 3N system of §3 at the linearisation `lin` (`FullStep`)."""
        A = self.full_matrix()
        n, r3 = self.n, 3 * self.offset
        l = np.arange(n)  # noqa: E741  (the vertex index l of §3)
        cols = np.stack([r3 + l, r3 + n + l, r3 + 2 * n + l], axis=1).ravel()
        vals = np.stack([lin.alpha, -lin.alpha, lin.beta], axis=1).ravel()
        A.setValuesIJV(_ints(np.arange(0, 3 * n + 1, 3)), _ints(cols), vals,
                       rowmap=_ints(r3 + 2 * n + l))
        A.assemble()
        b = self.WF.copy()
        b.array[2 * n:] = lin.B3
        return FullStep(self, A, b, lin.norm_B)

    def _elimination(self, values, assembled):
        """T of `EliminatedStep` with the CSR `values` (5 per vertex: row u1 (1), rows u2 and
        λ (2 each)), and A = W E T: assembled (then the product reuses its symbolic part) or
        as the shell operator (module notes). The pattern of T is the same at every step
        (zeros kept), so T is made once and refilled. One step at a time: the matrices of the
        step before are overwritten."""
        if self._T is None:
            n, N, r0 = self.n, self.N, self.offset
            y0 = 2 * r0 + np.arange(n)
            pair = np.stack([y0, y0 + n], axis=1).ravel()
            self._T_pattern = (_ints(np.concatenate([np.arange(n + 1), n + 2 * np.arange(
                1, 2 * n + 1)])), _ints(np.concatenate([y0, pair, pair])))
            self._T = PETSc.Mat().createAIJ(((3 * n, 3 * N), (2 * n, 2 * N)),
                                            csr=(*self._T_pattern, values), comm=self.comm)
        else:
            self._T.setValuesCSR(*self._T_pattern, values)
        self._T.assemble()
        if not assembled:
            return self._T, self._product()
        if self._AT is None:
            self._AT = self.E.matMult(self._T)
        else:
            self.E.matMult(self._T, result=self._AT)
        return self._T, self._AT

    def _product(self):
        """A = W E T as a PETSc shell matrix: Y ↦ E_op (T Y) (module notes)."""
        if self._operator is None:
            n, N = self.n, self.N
            self._operator = PETSc.Mat().createPython(((2 * n, 2 * N), (2 * n, 2 * N)),
                                                      _Product(self), comm=self.comm)
            self._operator.setUp()
        return self._operator

    @property
    def E(self):
        """W E, the weighted linear rows (2N × 3N), as one AIJ matrix: for the assembled
        eliminated matrix only (products with vectors use `E_op`)."""
        if self._E is None:
            self._E = _converted(self._E_blocks, self.comm)
        return self._E

    def release(self):
        """Free the eliminated steps' T and A (and the AIJ W E; made anew when next
        needed): less alive under an estimate that may be full."""
        for obj in (self._T, self._AT, self._E, self._operator):
            if obj is not None:
                obj.destroy()
        self._T = self._AT = self._E = self._T_pattern = self._operator = None

    def eliminated_step(self, lin, assembled=True):
        """The eliminated 2N system of the module notes at `lin` (`EliminatedStep`); its
        matrix assembled, or the shell operator W E T (`assembled=False`: for a
        preconditioner that reads no entries of it)."""
        return EliminatedStep(self, lin, assembled)

    def step(self, lin, system, assembled=True):
        """The Newton system at `lin`: system 'full' or 'eliminated' (`eliminated_step`)."""
        if system == "full":
            return self.full_step(lin)
        if system == "eliminated":
            return self.eliminated_step(lin, assembled)
        raise ValueError(f"unknown Newton system {system!r} (choose from: full, eliminated)")

    def destroy(self):
        self.release()
        for obj in (self.E_op, self.S_D, self._D1, self._D2, self._A, self.W, self.WF,
                    self.WF2, self._r2):
            if obj is not None:
                obj.destroy()


class FullStep:
    """A y = b with y = X (3N), the weighted full system; `norm_B` = ‖W B‖."""
    system = "full"

    def __init__(self, sys, A, b, norm_B):
        self.sys, self.A, self.b, self.norm_B = sys, A, b, norm_B

    def guess(self, X):
        """The solver's unknowns y for the iterate X (the Newton iterate X^{k-1}, §8)."""
        return X.copy()

    def expand(self, y, X):
        """X = the iterate of the solver's unknowns y."""
        y.copy(X)
        return X

    def residual(self, y, R, rw=None):
        """R = W⁻¹ (b - A y) (3N, unweighted, §4); returns ‖b - A y‖ (weighted). rw: the
        weighted residual if already known."""
        if rw is None:
            rw = self.b.duplicate()
            self.A.mult(y, rw)
            rw.aypx(-1.0, self.b)
            norm = rw.norm()
            R.pointwiseDivide(rw, self.sys.W)
            rw.destroy()
            return norm
        R.pointwiseDivide(rw, self.sys.W)
        return rw.norm()

    def destroy(self):
        self.b.destroy()                       # A is the system's, kept for the next step


class _Product:
    """The context of the shell matrix A = W E T (`NewtonSystem._product`): A y = E_op (T y),
    through one 3N work vector; T is looked up at every product (it is made anew after a
    `release`). The system is held by a weak reference: PETSc holds the context, so a strong
    one would be a cycle Python cannot collect."""

    def __init__(self, sys):
        self.sys, self.work = weakref.ref(sys), None

    def mult(self, mat, y, out):
        sys = self.sys()
        T = sys._T
        if self.work is None:
            self.work = T.createVecLeft()
        T.mult(y, self.work)
        sys.E_op.mult(self.work, out)

    def destroy(self, mat):
        if self.work is not None:
            self.work.destroy()
            self.work = None


class EliminatedStep:
    """The eliminated 2N system (module notes): A = W E T, b = W F - W E t, X = T Y + t.

    `lam_out[l]`: λ_l was eliminated (z_l = u2_l), else u2_l (z_l = λ_l). The vertex
    couplings the mean/gap preconditioner needs: c_l = α_l/β_l where λ_l was eliminated
    (λ_l = c_l (u2 - u1)_l + const), d_l = β_l/α_l where u2_l was (u2_l - u1_l = d_l λ_l +
    const)."""
    system = "eliminated"

    def __init__(self, sys, lin, assembled=True):
        self.sys, self.norm_B = sys, lin.norm_B
        n = sys.n
        alpha, beta, B3 = lin.alpha, lin.beta, lin.B3
        lam_out = np.abs(beta) >= sys.kappa * np.abs(alpha)
        u2_out = ~lam_out
        a_safe = np.where(u2_out, alpha, 1.0)
        b_safe = np.where(lam_out, beta, 1.0)
        L, U = lam_out.astype(float), u2_out.astype(float)
        H = L + U * beta / a_safe
        G = -L * alpha / b_safe
        Q = L * alpha / b_safe + U
        self.lam_out = lam_out
        self.c = np.where(lam_out, alpha / b_safe, 0.0)
        self.d = np.where(u2_out, beta / a_safe, 0.0)
        # T (3N × 2N): row l of u1 holds 1 in column l (Y's u1); rows of u2 and λ hold (U, H)
        # and (G, Q) in columns l and n + l (Y's u1 and z); A = E T, assembled or an operator.
        # Both are the system's, refilled at every step (`NewtonSystem._elimination`)
        values = np.empty(5 * n)
        values[:n] = 1.0
        values[n:3 * n:2], values[n + 1:3 * n:2] = U, H
        values[3 * n::2], values[3 * n + 1::2] = G, Q
        self.T, self.A = sys._elimination(values, assembled)
        self.t = sys.disc.vector3()
        self.t.array[n:2 * n] = -U * B3 / a_safe
        self.t.array[2 * n:] = L * B3 / b_safe
        self.b = sys.WF2.duplicate()
        sys.E_op.mult(self.t, self.b)
        self.b.aypx(-1.0, sys.WF2)                            # W F - W E t

    def guess(self, X):
        """Y = (u1, z) of the iterate X: z = u2 where λ was eliminated, else λ."""
        n = self.sys.n
        u1, u2, lam = self.sys.split(X)
        y = self.b.duplicate()
        y.array[:n] = u1
        y.array[n:] = np.where(self.lam_out, u2, lam)
        return y

    def expand(self, y, X):
        """X = T y + t."""
        self.T.multAdd(y, self.t, X)
        return X

    def residual(self, y, R, rw=None):
        """R = (W⁻¹ (b - A y), 0) (3N, unweighted, §4; R3 = 0 exactly); returns ‖b - A y‖."""
        n = self.sys.n
        own = rw is None
        if own:
            rw = self.b.duplicate()
            self.A.mult(y, rw)
            rw.aypx(-1.0, self.b)
        R.array[:2 * n] = rw.array_r / self.sys.W.array_r[:2 * n]
        R.array[2 * n:] = 0.0
        norm = rw.norm()
        if own:
            rw.destroy()
        return norm

    def destroy(self):
        for obj in (self.t, self.b):           # T and A are the system's
            obj.destroy()
