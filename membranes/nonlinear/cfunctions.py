"""C-functions for the complementarity u1 - u2 ≥ 0, λ ≥ 0, (u1 - u2) λ = 0 (§3).

With a = X1 - X2 and b = X3 (nodal values, vertex by vertex), a C-function satisfies
C(a, b) = 0 ⇔ a ≥ 0, b ≥ 0, ab = 0. Each C-function here comes with one element of its
Clarke Jacobian, written row by row as α_l (X1 - X2)_l + β_l X3_l, so that the Newton rows
of §3 read α a + β b = B3 with B3 = α a + β b - C(a, b) = J_C X - C(X).

Everything is vertex-local: plain numpy on the owned entries of a process.
"""

import numpy as np


def c_min(a, b):
    """min(a, b)."""
    return np.minimum(a, b)


def jacobian_min(a, b):
    """Row e1 - e2 (α = 1, β = 0) where a ≤ b, else e3 (α = 0, β = 1) (§3)."""
    take_a = a <= b
    return take_a.astype(float), (~take_a).astype(float)


def c_fb(a, b):
    """Fischer–Burmeister: sqrt(a² + b²) - (a + b), computed without overflow (hypot)."""
    return np.hypot(a, b) - (a + b)


# At the kink (a, b) = (0, 0) any (ξ - 1, ζ - 1) with ξ² + ζ² ≤ 1 is in the Clarke Jacobian
# (§3). We take ξ = ζ = 1/√2: the limit of the gradient along the diagonal a = b > 0, the
# choice symmetric in a and b.
FB_KINK = 1.0 / np.sqrt(2.0)


def jacobian_fb(a, b):
    """(a/ρ - 1, b/ρ - 1) with ρ = sqrt(a² + b²); (1/√2 - 1, 1/√2 - 1) at ρ = 0 (`FB_KINK`)."""
    rho = np.hypot(a, b)
    kink = rho == 0
    safe = np.where(kink, 1.0, rho)
    alpha = np.where(kink, FB_KINK, a / safe) - 1.0
    beta = np.where(kink, FB_KINK, b / safe) - 1.0
    return alpha, beta


CFUNCTIONS = {"min": (c_min, jacobian_min), "fb": (c_fb, jacobian_fb)}


def get(name):
    """(C, Jacobian) of the C-function called `name` ('min' or 'fb'); ValueError otherwise."""
    try:
        return CFUNCTIONS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown C-function {name!r} (choose from: "
                         f"{', '.join(CFUNCTIONS)})") from None


def value(name, a, b, kappa=1.0):
    """C(a, κ b): the C-function acting on the gap and the scaled pressure (§3, §11)."""
    return get(name)[0](a, kappa * b)


def linearise(name, a, b, kappa=1.0):
    """α, β, B3 of the semismooth Newton rows α a + β b = B3 of C(a, κ b) at (a, b) (§3).

    By the chain rule β = κ ∂C/∂b, and B3 = α a + β b - C(a, κ b). A fixed κ > 0 leaves the
    solutions of C = 0 unchanged and sets the units: with κ = (1/μ1 + 1/μ2)/2, κ D_a λ_a is
    the size of the gap change a nodal pressure λ_a makes, so κλ is a displacement per unit
    area (docs/theory.md §3; §11; `membranes.nonlinear.system`). Both C-functions are
    positively homogeneous of degree 1, so B3 = 0 up to round-off wherever (a, b) ≠ 0
    (Euler's identity): it is computed anyway, as §3 defines it."""
    C, J = get(name)
    alpha, beta = J(a, kappa * b)
    return alpha, kappa * beta, alpha * a + kappa * beta * b - C(a, kappa * b)
