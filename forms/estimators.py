# # UFL forms of the a posteriori estimators (§6, §7)
#
# UFL only: no dolfinx, no assembly. Every form is *tested with a piecewise-constant function*
# w: with w the test function of DG0 (one basis function per cell, equal to 1 on its cell),
# one assembly of `q * w * dx` gives ∫_K q on every cell K at once. A test function of vector
# DG0 with k components, passed component by component (w[i]), gives k such quantities per cell
# in one assembly: `membranes.estimation.estimators` sums the forms below that way.
#
# Quadrature. The iterate's fields are polynomials on each (affine) cell: u_h, λ_h, s_h ∈ P1,
# r_h ∈ discontinuous P1, σ ∈ RT_1 (basix "RT" of degree 2: P1² + x P̃1, components of degree
# 2; the contravariant Piola map of an affine cell keeps the degree). The integrands are
# therefore polynomials and the rules below integrate them exactly:
#
#   P1 × P1 products (η_C, ‖λ^±‖², ‖r_h ∓ δλ‖², |||v|||² of P1)    degree 2  (`P1_RULE`)
#   |μ^{1/2} ∇u_h + μ^{-1/2} σ|² with σ ∈ RT_1 (η_F, η_disc, η_alg)  degree 4  (`FLUX_RULE`)
#
# Data (f_α, the exact solution) are not polynomials and may jump across a curve that cuts
# cells: their integrals use the data measures of `membranes.fem.quadrature` (a degree-6 Gauss
# rule, a composite rule on cut cells), which the caller passes as dx.

import ufl

from .membrane import energy_density

P1_RULE = {"quadrature_degree": 2}     # exact for products of two P1 (or DG1) functions
FLUX_RULE = {"quadrature_degree": 4}   # exact for |a + σ|², a constant, σ ∈ RT_1


def flux_squared(mu, u, sigma, w, dx=ufl.dx):
    """η_F,K,α² = ‖μ_α^{1/2} ∇u_αh + μ_α^{-1/2} σ_α‖_K² (§7), per cell with w ∈ DG0.

    Written as μ^{-1} |μ ∇u_h + σ|²: the sum μ ∇u_h + σ is formed at each quadrature point
    before squaring, so that the near-cancellation of a good flux against the discrete flux
    -μ ∇u_h costs no more than the round-off of their sum."""
    e = mu * ufl.grad(u) + sigma
    return ufl.inner(e, e) / mu * w * dx


def weighted_norm_squared(mu, v, w, dx=ufl.dx):
    """‖μ^{-1/2} v‖_K² per cell (w ∈ DG0): η_alg,K,α² for v = σ_α,alg (§7), or the
    remainder's μ_α^{-1} ‖r_α ∓ δλ‖_K² (§6) for a scalar v."""
    return ufl.inner(v, v) / mu * w * dx


def cell_norm_squared(v, w, dx=ufl.dx):
    """‖v‖_K² per cell (w ∈ DG0), v scalar or vector: ‖λ^pos‖_K², ‖λ^neg‖_K² (§7)."""
    return ufl.inner(v, v) * w * dx


def contact_estimator(u1, u2, lam_pos, w, dx=ufl.dx):
    """η_C,K = 2 (u1h - u2h, λ^pos)_K per cell (w ∈ DG0; §7). Not a square: its sign is that
    of the complementarity defect, and Σ_C = Σ_K η_C,K enters the bound as max(0, Σ_C)."""
    return 2 * (u1 - u2) * lam_pos * w * dx


def energy_squared(mu1, mu2, e1, e2, w, dx=ufl.dx):
    """|||(e1, e2)|||_K² = μ1 ‖∇e1‖_K² + μ2 ‖∇e2‖_K² per cell (w ∈ DG0; §1): η_lin1,K² for
    e = s_h - u_h (§7), the energy error for e = u - u_h."""
    return energy_density(mu1, mu2, e1, e2) * w * dx


def oscillation_squared(mu, f, pf, w, dx=ufl.dx):
    """η_osc,K,α² = (h_K/π)² μ_α^{-1} ‖f_α - Π_P1 f_α‖_K² per cell (w ∈ DG0; §7), with
    h_K = ufl.CellDiameter (the largest distance between two vertices of K: for a triangle
    its longest edge, the h_K of `membranes.fem.meshes.cell_diameters`) and pf = Π_P1 f_α,
    the L² projection of f_α onto discontinuous P1 (the divergence of σ_α,disc, §5).
    dx: a data measure."""
    h = ufl.CellDiameter(ufl.domain.extract_unique_domain(w))
    d = f - pf
    return (h / ufl.pi) ** 2 / mu * d * d * w * dx


def projection_load(f, q, dx=ufl.dx):
    """(f, q) for q ∈ discontinuous P1: the right-hand side of Π_P1 f, the cell-wise L²
    projection onto discontinuous P1 (dx a data measure)."""
    return f * q * dx



def recovery_load(mu, u, v, dx=ufl.dx):
    """(μ_α ∇u_αh, v) for v a P1² test function: with the lumped mass (1, ψ_a) of each vertex
    (`forms.membrane.contact_term` with λ = 1), the nodal values G_a = (μ ∇u_h, ψ_a)/(1, ψ_a) of the
    averaged (recovered) flux G_α ∈ P1² of the Newton gate
    (`membranes.estimation.estimators.Estimators.recovered`). Exact with `P1_RULE` (a constant
    times P1)."""
    return mu * ufl.inner(ufl.grad(u), v) * dx
