"""A posteriori estimators and the guaranteed bound (DESIGN §7).

For an iterate X = (u1h, u2h, λh) with algebraic residual R (DESIGN §4), per cell K and
membrane α:

    η_F,K,α   = ‖μ_α^{1/2} ∇u_αh + μ_α^{-1/2} σ_α‖_K,   σ_α = σ_α,disc + σ_α,alg
    η_osc,K,α = (h_K/π) μ_α^{-1/2} ‖f_α - Π_P1 f_α‖_K
    η_C,K     = 2 (u1h - u2h, λ^pos)_K
    η_lin1,K  = |||s_h - u_h|||_K
    η_lin2,K  = 2 C_PF h_Ω (1/μ1 + 1/μ2)^{1/2} ‖λ^pos‖_Ω |||s_h - u_h|||_K
    η_lin3,K  = C_PF h_Ω (1/μ1 + 1/μ2)^{1/2} ‖λ^neg‖_K
    η_alg,K,α = ‖μ_α^{-1/2} σ_α,alg‖_K

with s_h the nodal projection onto the constraint (s = u_h where u1h ≥ u2h, else both
components (u1h + u2h)/2) and λ^pos, λ^neg the nodal positive and negative parts. Globally
η_· = (Σ_K η_·,K²)^{1/2}, Σ_C = Σ_K η_C,K, η_1 = (Σ_K Σ_α (η_F,K,α + η_osc,K,α)²)^{1/2} and

    |||u - u_h||| ≤ η = {(η_1 + η_lin1 + η_lin3)² + η_lin2 + max(0, Σ_C)}^{1/2}

(the paper's Theorem 5.1), with the components η_disc, η_lin, η_alg of Corollary 5.6.

The algebraic flux σ_alg (DESIGN §6) is passed in by the caller (`evaluate(sigma_alg=...)`,
the multilevel construction of `algebraic_flux`, or `nu_flux`). Without it:

* where the algebraic residual vanishes to round-off (`R` None, or ‖R‖/‖B‖ ≤ ALG_ROUNDOFF:
  exact solves), σ_alg = 0 and the unbalanced lifted residual r_h, however tiny, is bounded by
  Poincaré–Friedrichs, |(r_α, φ_α)| ≤ C_PF h_Ω μ_α^{-1/2} ‖r_α‖ μ_α^{1/2} ‖∇φ_α‖; so
  η_rem = C_PF h_Ω (Σ_α μ_α^{-1} ‖r_αh‖²)^{1/2} joins η_1 (as the remainder of the
  ν-construction does, DESIGN §6) and is reported as η_alg: the bound is guaranteed;
* elsewhere (inexact iterates) η_alg, η_F and η are reported as missing (None), never as 0,
  and no bound is claimed; η_disc and η_lin are still computed.

A remainder η_rem left by σ_alg (the ν-construction) joins η_1 in the bound and η_alg.

Integrals of P1 products (η_C, η_lin1, η_lin3, ‖λ^pos‖) are exact cell formulas; so are η_F
and η_alg (`CellFluxNorms`: σ_α is a quadratic vector polynomial on each cell, integrated by
an exact rule); so is ‖r_αh‖ of the remainder. Each kind is one compiled pass over the
cells for both membranes (membranes.compiled: `_constraint_parts` for the four P1 parts,
`_flux_squares` for η_F, η_alg, `_lifted_squares` for the remainder) that reads the nodal
values, RT coefficients and the Geometry's cell data where they are, with no per-cell copies.
η_osc is computed once per mesh from ‖f_α - Π_P1 f_α‖_K², which the flux set-up's pass over
the quadrature points of the scene's data measures gives with the load moments
(equilibration.load_moments).

σ_disc is computed once per iterate: the driver (membranes.driver, IterateEstimates) asks
for the σ_disc of an iterate in `nu_flux`, in `evaluate`, and in the next `nu_flux` when it
is the later iterate of the one before; `sigma_disc` keeps the last two (none where
`evaluate` has no ν flux: that σ is not asked for again, and it is written into the arrays of
the ones let go, so that such a run holds one σ's arrays). The ν flux is kept
as the pair of fluxes it is the difference of (`FluxDifference`): `_flux_squares` forms
σ_alg = σ_disc(X_later) - σ_disc(X) at each cell's dofs as it reads them, where an array of it
took 142 MiB of fresh memory per evaluation at 9.3e5 vertices (both membranes).
"""

import numpy as np

from .compiled import kernel, part
from .equilibration import (FluxEquilibration, _rt_element, cell_gradient, cell_reflections,
                            p1_mass_solve, rt_signs)
from .kept import KeptArrays
from .meshes import cell_diameters
from .newton_system import split
from .parallel import in_two

ALG_ROUNDOFF = 1e-11   # ‖R_alg‖/‖B‖ below which σ_alg = 0 and η_rem carries the bound

COLUMNS = ("eta", "eta_disc", "eta_lin", "eta_alg", "eta_F", "eta_osc", "eta_C",
           "eta_lin1", "eta_lin2", "eta_lin3")


@part
def _p1_product(area, p0, p1, p2, q0, q1, q2):
    """(p, q)_K = |K|/12 (Σ_k p_k q_k + Σ_k p_k Σ_k q_k) for p, q ∈ P1(K) with the values
    p_k, q_k at the cell's vertices (exact)."""
    return area / 12.0 * ((p0 * q0 + p1 * q1 + p2 * q2) + (p0 + p1 + p2) * (q0 + q1 + q2))


@kernel
def _constraint_parts(area, cells, grad, u1, u2, lam, mu1, mu2, out, first, last):
    """Per cell K of first … last-1 (into out (4, ncells)): (u1h - u2h, λ^pos)_K,
    |||s_h - u_h|||_K² = |K| (μ_1 |∇e_1h|² + μ_2 |∇e_2h|²) with e_αh = s_αh - u_αh (s_h of
    the module notes, vertex by vertex: e_h = 0 where u1h ≥ u2h, else s_αh = (u1h + u2h)/2),
    ‖λ^pos‖_K² and ‖λ^neg‖_K² (λ^pos, λ^neg the nodal max(λ, 0), min(λ, 0)): exact P1
    integrals from the nodal values at the cell's vertices, one pass for the four."""
    d = np.empty(3)
    lp = np.empty(3)
    ln = np.empty(3)
    e1 = np.empty(3)
    e2 = np.empty(3)
    for K in range(first, last):
        for k in range(3):
            v = cells[K, k]
            x, y, z = u1[v], u2[v], lam[v]
            d[k] = x - y
            lp[k] = z if z >= 0.0 else 0.0
            ln[k] = z if z <= 0.0 else 0.0
            e1[k] = e2[k] = 0.0
            if x < y:
                m = 0.5 * (x + y)
                e1[k], e2[k] = m - x, m - y
        a0, a1 = cell_gradient(grad, K, e1[0], e1[1], e1[2])
        b0, b1 = cell_gradient(grad, K, e2[0], e2[1], e2[2])
        out[0, K] = _p1_product(area[K], d[0], d[1], d[2], lp[0], lp[1], lp[2])
        out[1, K] = area[K] * (mu1 * (a0 * a0 + a1 * a1) + mu2 * (b0 * b0 + b1 * b1))
        out[2, K] = _p1_product(area[K], lp[0], lp[1], lp[2], lp[0], lp[1], lp[2])
        out[3, K] = _p1_product(area[K], ln[0], ln[1], ln[2], ln[0], ln[1], ln[2])


@kernel
def _lifted_squares(area, cells, cpv, R1, R2, shift, out, first, last):
    """‖ρ_α‖_K² for α = 1, 2 on the cells K of first … last-1 (into out (2, ncells)): ρ_α =
    r_αh the lifting of R_α (equilibration.Lifting: r_K = (3/|K|) [[3,-1,-1],[-1,3,-1],
    [-1,-1,3]] (R_l / N_l)_l, `equilibration.p1_mass_solve`), minus λ'_h - λ_h for α = 1 and
    plus it for α = 2 where `shift` (nodal) has entries; exact P1 products."""
    r = np.empty(3)
    v = np.empty(3)
    for K in range(first, last):
        for alpha in range(2):
            R = R1 if alpha == 0 else R2
            for k in range(3):
                v[k] = R[cells[K, k]] / cpv[cells[K, k]]
            r[0], r[1], r[2] = p1_mass_solve(area[K], v[0], v[1], v[2])
            if len(shift):
                for i in range(3):
                    if alpha == 0:
                        r[i] -= shift[cells[K, i]]
                    else:
                        r[i] += shift[cells[K, i]]
            out[alpha, K] = _p1_product(area[K], r[0], r[1], r[2], r[0], r[1], r[2])


class CellFluxNorms:
    """‖a + c σ‖_K² on every cell K at once, for a = b ∇u_h (u_h ∈ P1 by its nodal values, b a
    factor), a factor c and σ ∈ RT_1 given by its global coefficients (dolfinx's ("RT", 2) on
    `space`, a PatchSpace), without assembly (DESIGN §7: η_F and η_alg, with b = μ^{1/2} and
    c = μ^{-1/2}). On K, σ = (1/det J) J Σ_j s_j c_j ψ̂_j ∘ F_K⁻¹: the contravariant Piola map
    of basix's reference basis ψ̂ (RT_1, Legendre variant) with the cell's dof signs s (its
    edge reflections), as in PatchSpace.element_blocks. Its components are polynomials of
    degree 2 (RT_1 = P_1² + x P̃_1), so |a + σ|² has degree 4 and basix's degree-4 rule
    (weights w_q, points x̂_q) integrates it exactly: ‖a + σ‖_K² = |det J| Σ_q w_q
    |a + σ(F_K(x̂_q))|², with a added to the values of σ before squaring, as an assembly does
    (no cancellation between the terms of an expanded square).

    The signs take eight patterns (one per set of reflected edges ρ), folded into eight
    tables of reference values s_j ψ̂_j(x̂_q) (exact: a sign); one compiled pass over the cells
    (`_flux_squares`) forms each cell's ∇u_h and gathers its coefficients, forms the values
    at the points from the table of its ρ and the Piola entries J / det J, and sums the
    weighted squares: no array of values at the points is formed."""

    def __init__(self, space):
        import basix
        self.geo = geo = space.geo
        nc = geo.ncells
        self.reflections = cell_reflections(space.RT.mesh, nc).astype(np.int8)
        X, self.w = basix.make_quadrature(basix.CellType.triangle, 4)
        psi = _rt_element().tabulate(0, X)[0]                             # (q, 8, 2)
        psi = psi.transpose(2, 0, 1).reshape(-1, 8)                       # (2 q, 8)
        self.psi = np.ascontiguousarray(psi[None] * rt_signs(np.arange(8))[:, None, :])  # ρ
        self.rt_cells = np.ascontiguousarray(space.RT.dofmap.list.array.reshape(-1, 8)[:nc],
                                             dtype=np.int32)       # dolfinx's, no copy

    def squared(self, u, sigma, tau=None, b=1.0, c=1.0, out=None):
        """∫_K |b ∇u_h + c σ|² for every cell K; with τ ∈ RT_1 also ∫_K |b ∇u_h + c σ + c τ|²
        and ∫_K |c τ|²: shape (ncells,), or (3, ncells) with τ (into `out`, of shape (1 or
        3, ncells), if given). `squares` for one field."""
        given = out is not None
        full = self.squares([(u, sigma, tau, b, c)], None if out is None else out[:, None])
        if given:
            return out
        return full[:, 0] if tau is not None else full[0, 0]

    def squares(self, fields, out=None, pool=None):
        """`squared` for one or two fields (u, σ, τ, b, c) (the two membranes) in one pass over
        the cells, τ None in all or none: out (1 or 3, fields, ncells), each field's values
        the same to the bit as alone (and with `pool`, a thread to spare, in two halves:
        parallel.in_two). τ may be a pair (τ⁺, τ⁻) of coefficient arrays, for τ = τ⁺ - τ⁻
        formed at each dof as the pass reads it (the same numbers as with the array τ⁺ - τ⁻:
        `FluxDifference`), in all fields or none."""
        geo = self.geo
        k = len(fields)
        rows = 1 if fields[0][2] is None else 3
        if out is None:
            out = np.empty((rows, k, geo.ncells))
        u, sigma, tau, b, c = zip(*fields)
        difference = isinstance(tau[0], tuple)
        plus = tuple(s if t is None else t[0] if difference else t for s, t in zip(sigma, tau))
        minus = tuple(t[1] for t in tau) if difference else plus
        second = 1 if k == 2 else 0
        b, c = np.array(b, dtype=float), np.array(c, dtype=float)
        in_two(pool, geo.ncells, lambda first, last: _flux_squares(
            self.psi, self.reflections, self.rt_cells, geo.cells, geo.grad, geo.area, self.w,
            u[0], u[second], b, sigma[0], sigma[second], plus[0], plus[second], minus[0],
            minus[second], difference, c, out, first, last))
        return out


class FluxDifference:
    """The fluxes τ_α = τ⁺_α - τ⁻_α (α = 1, 2; RT_1 coefficients) kept as the two pairs
    (`Estimators.nu_flux`: σ_alg = σ_disc(X_later) - σ_disc(X)), which `evaluate` hands to
    `_flux_squares` as they are; τ[α] (or iterating) gives the difference as an array."""

    def __init__(self, plus, minus):
        self.plus, self.minus = tuple(plus), tuple(minus)

    def __len__(self):
        return len(self.plus)

    def __getitem__(self, alpha):
        if not 0 <= alpha < len(self.plus):
            raise IndexError(alpha)
        return self.plus[alpha] - self.minus[alpha]

    def pair(self, alpha):
        """(τ⁺_α, τ⁻_α), for `CellFluxNorms.squares`."""
        return self.plus[alpha], self.minus[alpha]


@kernel
def _flux_squares(psi, refl, rt_cells, cells, grad, area, w, u1, u2, b, sigma1, sigma2, tau1,
                  tau2, minus1, minus2, difference, c, out, first, last):
    """CellFluxNorms.squares on the cells first … last-1, out (1 or 3, k, ncells) for k = 1 or
    2 fields (u_f, σ_f, τ_f, b[f], c[f]): out[0, f, K] = |det J_K| Σ_q w_q |a_K + c σ(x_q)|²
    with a_K = b ∇u_h|_K, and where out has three rows out[2, f, K] for c τ and out[1, f, K]
    for a_K + c σ + c τ (τ_f = tau_f - minus_f at each dof where `difference`, else tau_f);
    σ at the points from the table psi[ρ_K] (2 nq, 8) of signed reference
    values and the Piola entries J / det J, which the gradients of the cell's hat functions
    hold (Geometry: ∇φ_1 = (J_11, -J_01) / det J, ∇φ_2 = (-J_10, J_00) / det J;
    |det J| = 2 |K|); the cell's table, Piola entries and dofs read once for the fields."""
    nq = len(w)
    both = out.shape[0] == 3
    k = out.shape[1]
    s = np.empty(8)
    t = np.empty(8)
    for K in range(first, last):
        tab = psi[refl[K]]
        F0, F1, F2, F3 = grad[K, 2, 1], -grad[K, 1, 1], -grad[K, 2, 0], grad[K, 1, 0]
        abs_det = 2.0 * area[K]
        for f in range(k):
            u, sigma, tau, minus = (u1, sigma1, tau1, minus1) if f == 0 else \
                (u2, sigma2, tau2, minus2)
            for j in range(8):
                d = rt_cells[K, j]
                s[j] = c[f] * sigma[d]
                t[j] = c[f] * (tau[d] - minus[d]) if difference else c[f] * tau[d]
            a0, a1 = cell_gradient(grad, K, u[cells[K, 0]], u[cells[K, 1]], u[cells[K, 2]])
            a0 *= b[f]
            a1 *= b[f]
            e_sum = 0.0
            f_sum = 0.0
            t_sum = 0.0
            for q in range(nq):
                v0 = 0.0
                v1 = 0.0
                for j in range(8):
                    v0 += tab[q, j] * s[j]
                    v1 += tab[nq + q, j] * s[j]
                e0 = F0 * v0 + F1 * v1 + a0
                e1 = F2 * v0 + F3 * v1 + a1
                e_sum += w[q] * (e0 * e0 + e1 * e1)
                if both:
                    v0 = 0.0
                    v1 = 0.0
                    for j in range(8):
                        v0 += tab[q, j] * t[j]
                        v1 += tab[nq + q, j] * t[j]
                    t0 = F0 * v0 + F1 * v1
                    t1 = F2 * v0 + F3 * v1
                    t_sum += w[q] * (t0 * t0 + t1 * t1)
                    e0 += t0
                    e1 += t1
                    f_sum += w[q] * (e0 * e0 + e1 * e1)
            out[0, f, K] = e_sum * abs_det
            if both:
                out[1, f, K] = f_sum * abs_det
                out[2, f, K] = t_sum * abs_det


def oscillation(disc, squares):
    """η_osc,K,α = (h_K/π) μ_α^{-1/2} ‖f_α - Π_P1 f_α‖_K (iterate-independent), from the
    squares ‖f_α - Π_P1 f_α‖_K² (2, ncells) that the flux set-up's load pass gives
    (FluxEquilibration.projection_squares: equilibration.load_moments, with the scene's data
    measures and Π_P1 f_α from the load moments)."""
    problem = disc.problem
    hK = cell_diameters(problem.mesh)
    return np.array([hK / np.pi / np.sqrt(mu) * np.sqrt(np.maximum(sq, 0.0))
                     for sq, mu in zip(squares, (problem.mu1, problem.mu2))])


class Estimators:
    """Set-up once per discretisation; `evaluate(X, R)` at any iterate.

    With `owned` (a boolean mask over the vertices) only the patches of the owned vertices
    are set up (FluxEquilibration): σ_disc is then this process's part, and `sum_parts` (a
    callable, e.g. parallel.Summation) takes the pair (σ_1, σ_2) of parts and returns their
    sums over all processes before anything uses them; the rest of the evaluation is the
    same on every process.

    `helper` (None, or a callable asked before each pass of an evaluation) may give an
    executor with a thread to spare: the passes then run in two halves or as a pipeline of
    two (parallel.in_two, algebraic_flux._apply_buckets), with the same numbers. The
    estimator process of a run on two processes gets one while process 0 waits for its
    estimates (membranes.pipeline: process 0's core is lent)."""

    def __init__(self, disc, owned=None, sum_parts=None):
        self.disc = disc
        problem = disc.problem
        self.flux = FluxEquilibration(disc, owned)
        self.sum_parts = sum_parts
        self.geo = self.flux.geo
        self.mu = (problem.mu1, problem.mu2)
        self.cpf = problem.poincare_constant()
        self.kappa = self.cpf * np.sqrt(1.0 / self.mu[0] + 1.0 / self.mu[1])
        self.norms = CellFluxNorms(self.flux.space)
        self.osc = oscillation(disc, self.flux.projection_squares)     # (2, ncells)
        self.flux.projection_squares = None                   # only the oscillation uses it
        self._recent = []                                     # sigma_disc's last two
        self._parts = KeptArrays()                            # evaluate's (membranes.kept)
        self.helper = None

    def _pool(self):
        return None if self.helper is None else self.helper()

    def remainder(self, R, lam_shift=None):
        """η_rem = C_PF h_Ω (Σ_α μ_α^{-1} ‖ρ_α‖²)^{1/2} with ρ_α = r_αh (DESIGN §4), or with
        lam_shift = λ' - λ (nodal): ρ_α = r_αh ∓ (λ'_h - λ_h) (- for α = 1: the flux
        σ_disc(X') balances Π_P1 f_1 + λ'_h - r'_1h = Π_P1 f_1 + λ_h - (r'_1h - (λ'_h - λ_h))).
        It bounds the part of the residual that the flux leaves out of balance, by
        Poincaré–Friedrichs. The cells' ‖ρ_α‖_K² in one compiled pass (`_lifted_squares`)."""
        n = self.disc.n
        geo = self.geo
        sq = np.empty((2, geo.ncells))
        shift = np.zeros(0) if lam_shift is None else lam_shift
        in_two(self._pool(), geo.ncells, lambda first, last: _lifted_squares(
            geo.area, geo.cells, geo.cells_per_vertex, R[:n], R[n:2 * n], shift, sq, first,
            last))
        total = 0.0
        for alpha in range(2):      # ‖ρ_α‖ first, then squared: the sums of the code before
            total += np.sqrt(np.sum(sq[alpha])) ** 2 / self.mu[alpha]
        return float(self.cpf * np.sqrt(total))

    def sigma_disc(self, X, R=None, keep=True):
        """(σ_1,disc, σ_2,disc) at X with algebraic residual R (RT_1 coefficients, read-only;
        FluxEquilibration.sigmas, both membranes in one pass). The last two are kept and given
        again for the same X and R (equal entries; every process of a run has the same
        iterates, so all of them compute or none). keep=False (`evaluate` without the ν
        flux): a σ that no later call asks for again; where it is not kept already, the kept
        ones are let go first and it is computed into their arrays, not kept (one σ's arrays
        in a run without the ν flux instead of two: 142 MiB at 9.3e5 vertices; a later call
        for one of them computes it again, the same numbers)."""
        # (a generator's names, unlike a loop's, do not outlive it: they would hold the older)
        kept = next((sigma for (Xk, Rk), sigma in self._recent
                     if np.array_equal(Xk, X) and (Rk is None if R is None else
                                                   Rk is not None and np.array_equal(Rk, R))),
                    None)
        if kept is not None:
            return kept
        n = self.disc.n
        u1, u2, lam = split(X, n)
        Rs = (None, None) if R is None else (R[:n], R[n:2 * n])
        # the older goes first (all of them where this one is not kept): their arrays may serve
        self._recent = self._recent[:1] if keep else []
        sigma = self.flux.sigmas([(1, u1, Rs[0]), (2, u2, Rs[1])], lam, self._pool())
        if self.sum_parts is not None:
            sigma = self.sum_parts(sigma)
        for s in sigma:
            s.flags.writeable = False
        if keep:
            key = (X.copy(), None if R is None else R.copy())
            self._recent = [(key, sigma)] + self._recent
        return sigma

    def nu_flux(self, X, R, X_later, R_later):
        """The algebraic flux of ν extra iterations (DESIGN §6) at the iterate X (residual R),
        from the iterate X_later = X^{k,i+ν} of the same linear solve: σ_alg = σ_disc(X_later)
        - σ_disc(X), so that σ_disc + σ_alg = σ_disc(X_later), whose divergence is
        Π_P1 f ± λ'_h - r'_h. The unbalanced part with respect to X is r'_h ∓ (λ'_h - λ_h):
        DESIGN §6 writes r^{k,i} - r^{k,i+ν} for the divergence of σ_alg, which holds where λ
        does not change between the two iterates; here λ changes, so its shift joins the
        remainder. Returns (σ_alg, η_rem), σ_alg a `FluxDifference` of the two σ_disc
        (σ_alg[α] gives the array)."""
        n = self.disc.n
        now, later = self.sigma_disc(X, R), self.sigma_disc(X_later, R_later)
        shift = X_later[2 * n:] - X[2 * n:]
        return FluxDifference(later, now), self.remainder(R_later, shift)

    def evaluate(self, X, R=None, alg_residual=None, sigma_alg=None, eta_rem=0.0):
        """All estimators at X (DESIGN §7). R: the algebraic residual (3N), None where the
        linear rows hold exactly; alg_residual = ‖R‖/‖B‖; sigma_alg: (σ_1,alg, σ_2,alg) RT
        coefficients (or a FluxDifference) where an algebraic flux was built, with eta_rem
        the remainder it leaves (0 for the multilevel flux, whose divergence is r_h exactly;
        `nu_flux` gives both).

        Returns a dict with the global values of COLUMNS (None where missing), `bound`
        (whether η is a guaranteed bound) and `eta_K` (the local distribution)."""
        disc, geo = self.disc, self.geo
        n = disc.n
        u1, u2, lam = split(X, n)
        roundoff = R is None or (alg_residual is not None and alg_residual <= ALG_ROUNDOFF)
        have_alg = sigma_alg is not None or roundoff
        # η_F,K,α = ‖μ^{1/2} ∇u_h + μ^{-1/2} σ‖_K, η_alg,K,α = ‖μ^{-1/2} σ_alg‖_K
        # cells[:, α]: η_disc,K,α (σ_disc alone), η_F,K,α and η_alg,K,α (with σ_alg)
        roots = [np.sqrt(mu) for mu in self.mu]
        difference = isinstance(sigma_alg, FluxDifference)
        fields = [(u, s_disc, None if sigma_alg is None else sigma_alg.pair(alpha) if difference
                   else sigma_alg[alpha], roots[alpha], 1.0 / roots[alpha])
                  for alpha, (u, s_disc) in enumerate(zip((u1, u2), self.sigma_disc(
                      X, R, keep=difference)))]
        cells = self.norms.squares(fields, pool=self._pool())
        np.sqrt(cells, out=cells)
        disc_cells = cells[0]
        flux_cells = disc_cells if sigma_alg is None else cells[1]
        # constraint and linearisation parts (exact P1 integrals)
        parts = self._parts.empty((4, geo.ncells))
        in_two(self._pool(), geo.ncells, lambda first, last: _constraint_parts(
            geo.area, geo.cells, geo.grad, u1, u2, lam, *self.mu, parts, first, last))
        eta_C_K = 2.0 * parts[0]
        lin1_K = np.sqrt(parts[1])
        lam_pos_norm = np.sqrt(max(parts[2].sum(), 0.0))
        lin2_K = 2.0 * self.kappa * lam_pos_norm * lin1_K
        lin3_K = self.kappa * np.sqrt(np.maximum(parts[3], 0.0))
        sum_C = float(eta_C_K.sum())
        eta_lin1, eta_lin2, eta_lin3 = (float(np.sqrt((v * v).sum()))
                                        for v in (lin1_K, lin2_K, lin3_K))
        osc = self.osc
        out = {
            "eta_osc": float(np.sqrt((osc * osc).sum())),
            "eta_C": sum_C,
            "eta_lin1": eta_lin1, "eta_lin2": eta_lin2, "eta_lin3": eta_lin3,
            "eta_disc": float(np.sqrt(((disc_cells + osc) ** 2).sum()) + np.sqrt(abs(sum_C))),
            "eta_lin": eta_lin1 + eta_lin3 + float(np.sqrt(eta_lin2)),
        }
        if not have_alg:
            out.update(eta=None, eta_alg=None, eta_F=None, bound=False)
            out["eta_K"] = None
            return out
        if sigma_alg is not None:
            alg_cells = cells[2]
            eta_rem = float(eta_rem)
            eta_alg = float(np.sqrt((alg_cells * alg_cells).sum())) + eta_rem
        else:
            eta_rem = 0.0 if R is None else self.remainder(R)
            eta_alg = eta_rem
        eta_1 = float(np.sqrt(((flux_cells + osc) ** 2).sum()))
        eta = np.sqrt((eta_1 + eta_rem + eta_lin1 + eta_lin3) ** 2 + eta_lin2 + max(0.0, sum_C))
        out.update(eta=float(eta), eta_alg=eta_alg,
                   eta_F=float(np.sqrt((flux_cells * flux_cells).sum())), bound=True)
        out["eta_K"] = np.sqrt(((flux_cells + osc) ** 2).sum(axis=0) + lin1_K ** 2
                               + lin3_K ** 2 + np.abs(eta_C_K))
        return out
