"""Energy-error convergence on the disk scene (DESIGN §9).

P1 with H² solutions converges with order 1 in the energy norm; the contact zone's free boundary
and the O(h²) polygon mismatch do not lower that. The issue asks for an observed order ≥ 0.9 on
the gmsh meshes h = 0.1, 0.05, 0.025; the order is measured against the actual mesh size
(largest cell diameter), and against the target size as well.
"""

import math

import pytest

from membranes.meshes import mesh_size

from .conftest import solved

H = (0.1, 0.05, 0.025)


def test_disk_energy_error_order():
    runs = [solved("disk", h) for h in H]
    for run in runs:
        assert run.converged, run.reason
    errors = [run.energy_error for run in runs]
    sizes = [mesh_size(run.problem.mesh) for run in runs]
    for k in range(2):
        order_actual = math.log(errors[k] / errors[k + 1]) / math.log(sizes[k] / sizes[k + 1])
        order_target = math.log(errors[k] / errors[k + 1]) / math.log(H[k] / H[k + 1])
        assert order_actual >= 0.9, (errors, sizes)
        assert order_target >= 0.9, (errors, H)


def test_disk_newton_terminates_at_tolerance():
    run = solved("disk", 0.05)
    newton = [rec for rec in run.history if rec["kind"] != "krylov"]
    assert newton[-1]["residual"] <= 1e-10
    assert all(rec["residual"] > 1e-10 for rec in newton[:-1])
    assert run.newton_iterations == len(newton) - 1


@pytest.mark.parametrize("name", ["disk", "square"])
def test_history_energy_error_is_final(name):
    run = solved(name, 0.1)
    assert run.energy_error == run.history[-1]["energy_error"]
    assert run.energy_error < run.history[0]["energy_error"]


def test_energy_error_expansion_is_the_integral():
    """EnergyError's total (expanded about the interpolant of the exact solution, two
    stiffness products per call) is the data measures' integral of |∇(u - u_h)|², which
    per_cell integrates cell by cell: the same quadrature, so the two agree to round-off,
    relative to the error, far from the solution and at it."""
    import numpy as np
    from membranes.discretisation import EnergyError
    for name in ("disk", "square"):
        run = solved(name, 0.1)
        error = EnergyError(run.disc)
        rng = np.random.default_rng(0)
        for X in (run.X, run.X + 1e-3 * rng.normal(size=run.X.size), np.zeros(run.X.size)):
            direct = np.sqrt((error.per_cell(X) ** 2).sum())
            assert abs(error(X) - direct) <= 1e-12 * direct
        assert error(run.X) == run.energy_error
