"""C-functions for the complementarity u1 - u2 ≥ 0, λ ≥ 0, (u1 - u2) λ = 0 (DESIGN §3).

With a = X1 - X2 and b = X3 (nodal), a C-function satisfies C(a, b) = 0 ⇔ a ≥ 0, b ≥ 0,
ab = 0. Each one here returns its value and one element of its Clarke Jacobian, written row by
row as α_l (X1 - X2)_l + β_l X3_l, so that the Newton rows read α a + β b = B3 with
B3 = α a + β b - C(a, b) (= J_C X - C(X) of DESIGN §3).
"""

import numpy as np


def c_min(a, b):
    """min(a, b)."""
    return np.minimum(a, b)


def jacobian_min(a, b):
    """Row e1 - e2 (α = 1, β = 0) where a ≤ b, else e3 (α = 0, β = 1)."""
    take_a = a <= b
    return take_a.astype(float), (~take_a).astype(float)


def c_fb(a, b):
    """Fischer–Burmeister: sqrt(a² + b²) - (a + b), computed without overflow (hypot)."""
    return np.hypot(a, b) - (a + b)


# At the kink (a, b) = (0, 0) any (ξ - 1, ζ - 1) with ξ² + ζ² ≤ 1 is in the Clarke Jacobian.
# We take ξ = ζ = 1/√2: the limit along the diagonal a = b > 0, symmetric in a and b.
FB_KINK = 1.0 / np.sqrt(2.0)


def jacobian_fb(a, b):
    """(a/ρ - 1, b/ρ - 1) with ρ = sqrt(a² + b²); (1/√2 - 1, 1/√2 - 1) at ρ = 0."""
    rho = np.hypot(a, b)
    kink = rho == 0
    safe = np.where(kink, 1.0, rho)
    alpha = np.where(kink, FB_KINK, a / safe) - 1.0
    beta = np.where(kink, FB_KINK, b / safe) - 1.0
    return alpha, beta


def project(a, b):
    """The nearest point (p, q) of the complementarity set {a ≥ 0, b ≥ 0, ab = 0} to (a, b),
    on the side min's Jacobian picks: (0, max(b, 0)) where a ≤ b (contact), else
    (max(a, 0), 0). (Nearest: the set is the two half-axes; where a ≤ b the distance² to
    the b half-axis is a² + min(b, 0)², to the a half-axis min(a, 0)² + b², no smaller.)"""
    contact = a <= b
    return np.where(contact, 0.0, np.maximum(a, 0.0)), np.where(contact, np.maximum(b, 0.0), 0.0)


def jacobian_fb_at_projection(a, b):
    """Fischer–Burmeister's Jacobian at the projection (p, q) of (a, b) (`project`): (-1, 0)
    where a ≤ b, else (0, -1). Off the origin FB is differentiable at (p, q) and this is its
    gradient ((p/ρ - 1, q/ρ - 1) with ρ = p or q); at the origin (both a, b ≤ 0) it is the
    element (ξ - 1, ζ - 1) with (ξ, ζ) = (0, 1) or (1, 0), on the unit circle (DESIGN §3): the
    limit of the gradient along the side picked. These are min's rows up to sign: the
    Newton step with them is the primal–dual active set step (newton: active-set steps)."""
    alpha, beta = jacobian_min(a, b)
    return -alpha, -beta


CFUNCTIONS = {"min": (c_min, jacobian_min), "fb": (c_fb, jacobian_fb)}


def get(name):
    """(C, Jacobian) of the C-function called `name` ('min' or 'fb')."""
    try:
        return CFUNCTIONS[name]
    except KeyError:
        raise ValueError(f"unknown C-function {name!r} (choose from: {', '.join(CFUNCTIONS)})") \
            from None


def linearise(name, a, b, kappa=1.0, at_projection=False):
    """α, β, B3 of the semismooth Newton rows α a + β b = B3 of C(a, κ b) at (a, b) (DESIGN
    §3): by the chain rule β = κ ∂C/∂b, and B3 = α a + β b - C(a, κ b). κ > 0 leaves the
    solutions of C = 0 unchanged; it sets the units (newton_system: κ λ is a displacement).

    at_projection (Fischer–Burmeister only): linearise C at the projection (p, q) of (a, κ b)
    onto the complementarity set (`project`) instead, C(p, q) + ∇C(p, q)·((a', κ b') - (p, q))
    = 0 with ∇C(p, q) = `jacobian_fb_at_projection`: the rows α a' + β b' = B3 with
    B3 = α p + (β/κ) q - C(p, q) = 0 (C vanishes at (p, q), and α p = 0, (β/κ) q = 0 for
    these rows)."""
    C, J = get(name)
    if at_projection:
        if name != "fb":
            raise ValueError("only Fischer-Burmeister is linearised at the projection")
        p, q = project(a, kappa * b)
        alpha, beta = jacobian_fb_at_projection(a, kappa * b)
        return alpha, kappa * beta, alpha * p + beta * q - c_fb(p, q)
    alpha, beta = J(a, kappa * b)
    return alpha, kappa * beta, alpha * a + kappa * beta * b - C(a, kappa * b)
