# # UFL forms of the patchwise flux equilibration (§5) and of the multilevel flux (§6)
#
# UFL only. `membranes.estimation.homes.assemble_rows` assembles the mixed RT_1 × DG1 form
# per colour on the cells of the patches whose blocks are taken, and each patch matrix is a
# principal submatrix of it; the right-hand sides are assembled per colour from the forms
# below.

import ufl

# ## The coloured patch problems of the distributed code (§5, §12)
#
# Trial (σ, γ) and test (τ, q) functions in RT_1 × DG1. The divergence equation of §5 is
# negated so that the patch matrix is symmetric:
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


# ## The divergence identities the bound rests on (§5, §6, §7)
#
# Summed over the patches, the divergence rows above give ∇·σ_α,disc = Π f ± λ - r on every
# cell (Π: the L² projection onto DG1, with the data measures). Its DG1 moments less the
# data's, (∇·σ ∓ λ + r, q) - (f, q), vanish to round-off; `disc_divergence` is the first part
# (the loads' data parts, summed over the colours, are the second).


def disc_divergence(sigma, sign, lam, r, q, dx=ufl.dx):
    """(∇·σ - (± λ - r), q) for a DG1 test function q (§5), `sign` as in `patch_rhs`."""
    return (ufl.div(sigma) - sign * lam + r) * q * dx


# ## The multilevel algebraic flux (§6)


def flux_divergence(sigma, r, q, dx=ufl.dx):
    """(∇·σ - r, q): the DG1 moments of the defect of ∇·σ_alg = r_αh (§6)."""
    return (ufl.div(sigma) - r) * q * dx


def multilevel_data(psi, r, rho, q, dx=ufl.dx):
    """(r ψ - ∇ρ_0·∇ψ, q): the divergence data of the coarse patch problems of §6 before
    projection, for ψ a trial function (the prolonged hat functions ψ_{j-1,a}; the product
    takes ψ in DG1, the hats of the cells' ancestors, broken), r the lifted residual r_αh,
    ρ_0 the prolonged coarse solution and q a DG1 test function."""
    return (r * psi - ufl.inner(ufl.grad(rho), ufl.grad(psi))) * q * dx
