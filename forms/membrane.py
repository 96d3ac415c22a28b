# # UFL forms of the two-membrane contact problem
#
# This module holds UFL only: no dolfinx, no assembly. Every function returns a form (or a
# UFL expression) built from the arguments it is given, so that the driver in `membranes/`
# decides spaces, measures and quadrature. Section numbers refer to `../shared/DESIGN.md`.

import ufl


def membrane_bilinear(mu, u, v, dx=ufl.dx):
    """μ_α (∇u, ∇v): the operator of membrane α (DESIGN §1, §2)."""
    return mu * ufl.inner(ufl.grad(u), ufl.grad(v)) * dx


def membrane_linear(f, v, dx=ufl.dx):
    """(f_α, v): the load of membrane α (DESIGN §2)."""
    return f * v * dx


def contact_weight(v, dx=ufl.dx):
    """(ψ_a, 1): the lumped contact weight D_aa of vertex a (DESIGN §2).

    Assembled against the P1 test function v it gives the diagonal D of the block form
    E = [[μ1 S, 0, -D], [0, μ2 S, D]].
    """
    return v * dx


def energy_density(mu1, mu2, e1, e2):
    """μ1 |∇e1|² + μ2 |∇e2|²: the integrand of the energy norm (DESIGN §1)."""
    return (mu1 * ufl.inner(ufl.grad(e1), ufl.grad(e1))
            + mu2 * ufl.inner(ufl.grad(e2), ufl.grad(e2)))


def energy_norm_squared(mu1, mu2, e1, e2, dx=ufl.dx, w=1.0):
    """|||(e1, e2)|||² = μ1 ‖∇e1‖² + μ2 ‖∇e2‖² (DESIGN §1); with w a DG0 test function, the
    squared energy norm on every cell."""
    return w * energy_density(mu1, mu2, e1, e2) * dx
