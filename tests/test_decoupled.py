"""Independent check (DESIGN §10): PETSc SNES vinewtonrsls on the decoupled obstacle problem
solves the same discrete problem as our semismooth Newton on the coupled one.

Both end at round-off of their own linear solves (MUMPS); the difference is bounded by the
conditioning of the P1 stiffness (≈ h⁻², about 1e3 here) times machine precision, far below the
required 1e-8 relative (max norm relative to the largest nodal value of each field).
"""

import numpy as np
import pytest

from membranes.decoupled import AMG, solve_decoupled
from membranes.newton_system import split

from .conftest import solved


def _relative(a, b):
    return np.abs(a - b).max() / np.abs(a).max()


@pytest.mark.parametrize("name,h", [("disk", 0.05), ("square", 0.05)])
def test_same_discrete_solution(name, h):
    run = solved(name, h)
    assert run.converged
    if name == "square":  # the case μ1 ≠ μ2 and f1 + f2 ≠ 0, with a contact zone
        assert run.problem.mu1 != run.problem.mu2
        assert np.abs(run.disc.F1 + run.disc.F2).max() > 1e-3 * np.abs(run.disc.F1).max()
    u1, u2, lam = split(run.X, run.disc.n)
    assert (lam > 0).sum() > 10, "no genuine contact zone"
    peer = solve_decoupled(run.disc)
    assert peer.converged, peer.reason
    assert _relative(u1, peer.u1) <= 1e-8
    assert _relative(u2, peer.u2) <= 1e-8
    assert _relative(lam, peer.lam) <= 1e-8


def test_peer_with_amg_inner_solves():
    run = solved("disk", 0.05)
    peer = solve_decoupled(run.disc, AMG)
    assert peer.converged, peer.reason
    u1, u2, lam = split(run.X, run.disc.n)
    # CG is stopped at 1e-12 relative: the VI's active set is the same, values agree to ~1e-10
    assert _relative(lam, peer.lam) <= 1e-8
    assert peer.linear_iterations > peer.newton_iterations   # Krylov work is counted
