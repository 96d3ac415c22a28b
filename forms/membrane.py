# # UFL forms of the two-membrane contact problem
#
# This module holds UFL only: no dolfinx, no assembly. Every function returns a form (or a
# UFL expression) built from the arguments it is given, so that `membranes.fem` decides spaces,
# measures and quadrature. Section numbers refer to docs/theory.md.

import ufl

# The lumped contact term uses the vertex quadrature rule: on a triangle K the rule puts the
# weight |K|/3 at each vertex, so that (u, v)_vertex is diagonal for P1 and its diagonal entry
# at vertex a is Σ_K |K|/3 = (ψ_a, 1), the weight D_aa of §2.
VERTEX_RULE = {"quadrature_rule": "vertex", "quadrature_degree": 1}


def membrane_bilinear(mu, u, v, dx=ufl.dx):
    """μ_α (∇u, ∇v): the operator of membrane α (§1, §2)."""
    return mu * ufl.inner(ufl.grad(u), ufl.grad(v)) * dx


def membrane_linear(f, v, dx=ufl.dx):
    """(f_α, v): the load of membrane α (§2)."""
    return f * v * dx


def contact_term(lam, v, dx=ufl.dx):
    """The lumped contact term λ_a (ψ_a, 1) of row a (§2), for λ a P1 trial function or
    coefficient: (λ, v) integrated with the vertex rule (`VERTEX_RULE`). As a bilinear form it
    assembles into the diagonal matrix D of E = [[μ1 S, 0, -D], [0, μ2 S, D]]; with λ = 1 into
    its diagonal, the lumped weights D_a = (ψ_a, 1)."""
    return lam * v * dx(metadata=VERTEX_RULE)


def energy_density(mu1, mu2, e1, e2):
    """μ1 |∇e1|² + μ2 |∇e2|²: the integrand of the energy norm (§1)."""
    return (mu1 * ufl.inner(ufl.grad(e1), ufl.grad(e1))
            + mu2 * ufl.inner(ufl.grad(e2), ufl.grad(e2)))
