"""Energy-error convergence on the disk with curved refinement (theory §9).

P1 with H² solutions converges with order 1 in the energy norm. New boundary vertices go onto
the circle, so the polygon of T_J converges to the disk and the error keeps falling under
refinement (a hierarchy that kept the polygon of T_0 stalled at the O(h_0²) boundary mismatch).
Uniform refinement halves h exactly, so the observed order between two levels is
log2(error_{J-1} / error_J); the order asked for is ≥ 0.9 (order 1 up to the free boundary's
and the boundary's pre-asymptotic effects).
"""

import math

from .conftest import solved_on


def test_disk_energy_error_order_with_refinement():
    runs = [solved_on("disk", 0.2, J, newton="exact", estimators=False) for J in (1, 2, 3, 4)]
    for run in runs:
        assert run.converged, run.reason
    errors = [run.energy_error for run in runs]
    orders = [math.log2(errors[k] / errors[k + 1]) for k in range(len(errors) - 1)]
    assert min(orders[1:]) >= 0.9, (errors, orders)


def test_exact_newton_terminates_at_tolerance():
    run = solved_on("disk", 0.2, 2, newton="exact", estimators=False)
    finest = [rec for rec in run.history if rec["kind"] != "krylov" and rec["level"] == 2]
    assert finest[-1]["residual"] <= 1e-10
    assert all(rec["residual"] > 1e-10 for rec in finest[:-1])


def test_energy_error_per_cell_sums_to_the_total():
    """EnergyError's total is the root of the sum of its per-cell squares (the same
    quadrature: round-off), at the solution and away from it."""
    import numpy as np
    from mpi4py import MPI

    from membranes.estimation.energy_error import EnergyError
    run = solved_on("disk", 0.2, 1, newton="exact", estimators=False)
    error = EnergyError(run.disc)
    X = run.X.copy()
    for scale in (1.0, 0.5, 0.0):
        X.array[:] = scale * run.X.array_r
        direct = np.sqrt(MPI.COMM_WORLD.allreduce((error.per_cell(X) ** 2).sum()))
        assert abs(error(X) - direct) <= 1e-12 * direct
