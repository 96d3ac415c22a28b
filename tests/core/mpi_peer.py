"""Checks of the SNES VI peer (§10) that hold on any number of processes, and the script that
runs them on P processes.

`discrete_checks(result)` measures how well the peer's iterate (u1, u2, λ) solves the discrete
complementarity problem of §2: the relative residual of the linear rows E X = F at the interior
vertices, the smallest gap w = u1 - u2 and λ, the largest λ w, and the boundary values.
`invariants(result)` gives numbers that do not depend on how the vertices are numbered or
distributed: norms of u1, u2, λ, moments Σ_a u(a) φ(x_a) against a few polynomials φ, the
active-set size and the exact energy error.

Run as a script (`mpirun -n P python tests/core/mpi_peer.py J RTOL`) it solves the disk scene
(h0 = 0.2, J levels) with the nested and the plain peer at SNES rtol RTOL and prints, on rank 0,
one JSON line {"nested": {...}, "plain": {...}} with the checks, the invariants and PETSc's
counts, after checking that every rank holds the same numbers.
"""

import sys

import numpy as np
from mpi4py import MPI

MOMENTS = {"1": lambda x: 1.0 + 0.0 * x[0], "x": lambda x: x[0], "y": lambda x: x[1],
           "x2": lambda x: x[0] ** 2, "xy": lambda x: x[0] * x[1], "y3": lambda x: x[1] ** 3}


def _sum(comm, value):
    return comm.allreduce(float(value), op=MPI.SUM)


def _max(comm, a):
    return comm.allreduce(float(np.max(a, initial=-np.inf)), op=MPI.MAX)


def _min(comm, a):
    return comm.allreduce(float(np.min(a, initial=np.inf)), op=MPI.MIN)


def stiffness_times(disc, a):
    """S a (owned entries) for an array a of the owned P1 values."""
    x = disc.S.createVecRight()
    x.setArray(a)
    y = disc.S.createVecLeft()
    disc.S.mult(x, y)
    return y.array_r.copy()


def discrete_checks(result):
    """The discrete complementarity problem of §2 at the peer's iterate:
    rows: ‖E X - F‖ at the interior vertices / (‖F1‖ + ‖F2‖) for each membrane;
    w_min, lam_min; lam_w: max |λ w| / (max λ · max w); boundary: max |u1 - g|, |u2|, |λ|
    on ∂Ω."""
    disc = result.disc
    comm = disc.comm
    u1, u2, lam = disc.split(result.X)
    D, F1, F2 = disc.D.array_r, disc.F1.array_r, disc.F2.array_r
    r1 = disc.mu1 * stiffness_times(disc, u1) - D * lam - F1
    r2 = disc.mu2 * stiffness_times(disc, u2) + D * lam - F2
    inner, b = disc.interior, disc.boundary_owned
    norm = [np.sqrt(_sum(comm, (a[inner] ** 2).sum())) for a in (r1, r2, F1, F2)]
    w = u1 - u2
    return {"rows1": norm[0] / (norm[2] + norm[3]), "rows2": norm[1] / (norm[2] + norm[3]),
            "w_min": _min(comm, w), "lam_min": _min(comm, lam),
            "lam_w": _max(comm, np.abs(lam * w)) / (_max(comm, lam) * _max(comm, w)),
            "boundary": max(_max(comm, np.abs(u1[b] - disc.g)), _max(comm, np.abs(u2[b])),
                            _max(comm, np.abs(lam[b])))}


def invariants(result, energy_error=None):
    """Numbers independent of the numbering and distribution of the vertices."""
    disc = result.disc
    comm = disc.comm
    x = disc.V.tabulate_dof_coordinates()[:disc.n, :2].T
    out = {}
    for name, a in zip(("u1", "u2", "lam"), disc.split(result.X)):
        out[f"{name}.l2"] = np.sqrt(_sum(comm, (a ** 2).sum()))
        out[f"{name}.l1"] = _sum(comm, np.abs(a).sum())
        out[f"{name}.max"] = _max(comm, a)
        for key, phi in MOMENTS.items():
            out[f"{name}.m_{key}"] = _sum(comm, (a * phi(x)).sum())
    out["active"] = result.levels[-1].active
    out["vertices"] = disc.n_global
    if energy_error is not None:
        out["energy_error"] = energy_error(result.X)
    return out


def main(levels, rtol):
    from membranes.app.peer import nested_peer, plain_peer
    from membranes.estimation.energy_error import EnergyError
    from membranes.model import scenes
    comm = MPI.COMM_WORLD
    problem = scenes.disk(h=0.2, levels=levels, comm=comm)
    out = {}
    for run in (nested_peer, plain_peer):
        r = run(problem, rtol=rtol)
        out[r.label] = {**discrete_checks(r), **invariants(r, EnergyError(r.disc)),
                        "snes": [lv.snes_iterations for lv in r.levels],
                        "converged": r.converged}
    from mpi_common import print_agreed  # run as a script from tests/core
    print_agreed(comm, out)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 2,
         float(sys.argv[2]) if len(sys.argv) > 2 else 1e-12)
