# # UFL forms of the patchwise flux equilibration and of the estimators (DESIGN §5, §7)
#
# UFL only. The driver assembles the global Raviart–Thomas forms once per mesh and restricts
# them to each vertex patch; the estimator forms are tested with a piecewise-constant function
# so that one assembly gives a value per cell.

import ufl


def rt_mass(sigma, tau, dx=ufl.dx):
    """(σ, τ): the mass matrix of RT_1 (DESIGN §5, first equation)."""
    return ufl.inner(sigma, tau) * dx


def divergence(sigma, q, dx=ufl.dx):
    """(∇·σ, q): the divergence constraint against discontinuous P1 (DESIGN §5)."""
    return ufl.div(sigma) * q * dx


def vector_moment(w, tau, dx=ufl.dx):
    """(w, τ) for w in vector DG1: gives ∫_K ψ_a e_d · τ, the moments behind -(ψ_a μ ∇u_h, τ)."""
    return ufl.inner(w, tau) * dx


def weighted_mass(f, p, q, dx=ufl.dx):
    """(f p, q) on DG1: gives (ψ_a f, q)_K, the load part of the patch right-hand side."""
    return f * p * q * dx


def flux_estimator_squared(mu, u, sigma, w, dx=ufl.dx):
    """η_F,K² = ‖μ^{1/2} ∇u_h + μ^{-1/2} σ‖_K² per cell (w a DG0 test function; DESIGN §7)."""
    e = ufl.sqrt(mu) * ufl.grad(u) + sigma / ufl.sqrt(mu)
    return ufl.inner(e, e) * w * dx


def cell_norm_squared(v, w, dx=ufl.dx):
    """‖v‖_K² per cell (w a DG0 test function)."""
    return ufl.inner(v, v) * w * dx


# ## The coloured patch problems of the distributed code (DESIGN §5, §12)
#
# Trial (σ, γ) and test (τ, q) functions in RT_1 × DG1. The divergence equation of §5 is
# negated so that the patch matrix is symmetric (MUMPS then factorises it as LDLᵀ):
#
#     (σ, τ) - (γ, ∇·τ) - (∇·σ, q) = -(ψ μ ∇u, τ) - (g̃, q),
#     g̃ = ψ (f - r) ± Λ - μ ∇u·∇ψ,
#
# ψ = Σ_a ψ_a and Λ = Σ_a λ_a ψ_a over the vertices a of one colour: on the patch of a such
# vertex they are ψ_a and λ_a ψ_a, since no other vertex of the colour touches its cells.


def patch_system(sigma, gamma, tau, q, dx=ufl.dx):
    """(σ, τ) - (γ, ∇·τ) - (∇·σ, q): the symmetric mixed RT_1 × DG1 patch matrix (§5)."""
    return (ufl.inner(sigma, tau) - gamma * ufl.div(tau) - ufl.div(sigma) * q) * dx


def patch_rhs(psi, lam_c, sign, mu, u, r, tau, q, dx=ufl.dx):
    """The iterate's part of the right-hand side of the coloured patch problems (§5):
    -(ψ μ ∇u, τ) - (-ψ r ± Λ - μ ∇u·∇ψ, q), `sign` = +1 for α = 1, -1 for α = 2."""
    g = -psi * r + sign * lam_c - mu * ufl.inner(ufl.grad(u), ufl.grad(psi))
    return (-mu * psi * ufl.inner(ufl.grad(u), tau) - g * q) * dx


def patch_load(psi, f, q, dx=ufl.dx):
    """The data part -(ψ f, q) of the right-hand side (§5; dx a data measure)."""
    return -psi * f * q * dx


# ## The multilevel algebraic flux (DESIGN §6)


def multilevel_data(psi, r, rho, q, dx=ufl.dx):
    """(r ψ - ∇ρ_0·∇ψ, q): the divergence data of the coarse patch problems of §6 before
    projection, for ψ a P1 trial function (the prolonged hat functions ψ_{j-1,a}), r the lifted
    residual r_αh, ρ_0 the prolonged coarse solution and q a DG1 test function."""
    return (r * psi - ufl.inner(ufl.grad(rho), ufl.grad(psi))) * q * dx
