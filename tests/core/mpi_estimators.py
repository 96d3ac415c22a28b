"""A small estimator scene for the tests, and the script that evaluates it on P processes.

`scene(comm, N)` builds, on a perturbed N × N square mesh partitioned by dolfinx on `comm`,
a discretisation with cubic loads and a quadratic exact solution, an iterate X whose values
are functions of the vertex coordinates (so the same discrete functions on any partition),
two RT_1 fields σ and σ_alg given by formulas that RT_1 holds exactly, and DG1 residual
liftings; `iterate` and `residual` give iterates with the boundary values of §2 and their
residuals R = B - A X, for the flux equilibration. Run as a script
(`mpirun -n P python tests/core/mpi_estimators.py N`) it prints, on rank 0, one JSON line
with the global estimators, the remainder and the energy error, after checking that every
rank holds the same numbers: the estimators with the given fluxes, η_lin and η_rec alone,
and with the flux equilibration and the ν flux (and at an iterate that differs from the
last one at a single vertex).
"""

import sys

import numpy as np
import ufl
from mpi4py import MPI

MU1, MU2, G = 1.0, 3.0, 0.1


def _builders(np_or_ufl):
    """The scene's formulas in x = (x0, x1), for numpy arrays or UFL."""
    sin, cos = np_or_ufl.sin, np_or_ufl.cos
    return {
        "f1": lambda x: x[0] ** 3 - 2 * x[0] * x[1] + 1,
        "f2": lambda x: x[1] ** 2 * x[0] + 3 * x[1] ** 3,
        "exact_u1": lambda x: x[0] ** 2 + x[0] * x[1],
        "exact_u2": lambda x: x[1] ** 2 - x[0],
        "u1": lambda x: 0.2 + x[0] * (1 - x[0]) * sin(3 * x[1]),
        "u2": lambda x: 0.25 - 0.3 * x[1] * x[0],
        "lam": lambda x: cos(4 * x[0] + x[1]),
        # RT_1 = P1² + x P̃1 holds these exactly (the same p̃ in both components)
        "sigma1": lambda x: (x[0] + 2 * x[1] + x[0] * (x[0] - x[1]),
                             0.5 - x[1] + x[1] * (x[0] - x[1])),
        "sigma2": lambda x: (0.3 - x[1] + x[0] * (2 * x[0] + x[1]),
                             2 * x[0] + x[1] * (2 * x[0] + x[1])),
        "alg1": lambda x: (0.1 * x[1], 0.05 - 0.2 * x[0]),
        "alg2": lambda x: (0.1 + 0.2 * x[0] + 0.1 * x[0] * (x[0] + x[1]),
                           0.3 * x[1] + 0.1 * x[1] * (x[0] + x[1])),
        "r1": lambda x: 0.01 * sin(5 * x[0]) * x[1],
        "r2": lambda x: 0.02 * cos(2 * x[1]) - 0.01,
        "dlam": lambda x: 0.05 * x[0] * x[1],
    }


NP = _builders(np)
UFL = _builders(ufl)


class SquareProblem:
    """What `membranes.fem.discretisation.discretise` and the estimators read of a problem."""

    def __init__(self, mesh, mu1=MU1, mu2=MU2, f1=UFL["f1"], f2=UFL["f2"]):
        from membranes.model.problem import ExactSolution
        self.mesh, self.mu1, self.mu2, self.g = mesh, mu1, mu2, G
        self.f1, self.f2 = f1, f2
        self.interface = None
        self.exact = ExactSolution(UFL["exact_u1"], UFL["exact_u2"], lambda x: 0.0)

    def poincare_constant(self):
        return 1.0 / (np.pi * np.sqrt(2.0))           # the unit square (§7)


def perturbed_square(comm, N):
    """The unit square cut into N × N × 2 triangles, interior vertices moved by up to h/4
    (smooth in the coordinates: the same mesh on any partition)."""
    from dolfinx import mesh as dmesh
    m = dmesh.create_unit_square(comm, N, N, dmesh.CellType.triangle,
                                 dmesh.GhostMode.shared_facet)
    x = m.geometry.x
    bump = 0.25 / N * np.sin(np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1])
    x0 = x[:, 0].copy()
    x[:, 0] += bump * np.cos(9 * x[:, 1])
    x[:, 1] += bump * np.sin(11 * x0)
    return m


def nodal(V, formula):
    """Values of a formula at the P1 dofs (owned and ghost)."""
    return formula(V.tabulate_dof_coordinates()[:, :2].T)


def rt_function(RT, formula):
    from dolfinx import fem
    s = fem.Function(RT)
    s.interpolate(lambda x: np.vstack(formula(x)))
    return s


def scene(comm, N):
    """(disc, X, σ, σ_alg, r, δλ) of the module notes; X a numpy array of the owned values."""
    from dolfinx import fem

    from membranes.fem.discretisation import discretise
    mesh = perturbed_square(comm, N)
    disc = discretise(SquareProblem(mesh))
    V, n = disc.V, disc.n
    X = np.concatenate([nodal(V, NP[k])[:n] for k in ("u1", "u2", "lam")])
    RT = fem.FunctionSpace(mesh, ("RT", 2))
    sigma = [rt_function(RT, NP[k]) for k in ("sigma1", "sigma2")]
    alg = [rt_function(RT, NP[k]) for k in ("alg1", "alg2")]
    DG1 = fem.FunctionSpace(mesh, ("DG", 1))
    r = []
    for k in ("r1", "r2"):
        f = fem.Function(DG1)
        f.interpolate(lambda x, k=k: NP[k](x))
        r.append(f)
    dlam = nodal(V, NP["dlam"])[:n]
    return disc, X, sigma, alg, r, dlam


def residual(disc, X):
    """R = B - A X on the linear rows (§4): R_1 = F_1 - μ1 S u1 + D λ, R_2 = F_2 - μ2 S u2 - D λ
    on the interior dofs, 0 at the Dirichlet vertices (numpy, owned entries)."""
    n = disc.n
    u1, u2, lam = (disc.S.createVecRight() for _ in range(3))
    for v, part in zip((u1, u2, lam), disc.split(X)):
        v.array[:] = part
    D = disc.D.array_r[:n]
    R = []
    for u, F, mu, sign in ((u1, disc.F1, disc.mu1, 1.0), (u2, disc.F2, disc.mu2, -1.0)):
        Su = disc.S.createVecLeft()
        disc.S.mult(u, Su)
        part = F.array_r[:n] - mu * Su.array_r + sign * D * lam.array_r
        part[disc.boundary_owned] = 0.0
        R.append(part)
    return np.concatenate(R + [np.zeros(n)])


def iterate(disc, seed):
    """An iterate with the boundary values of §2 (u1 = g, u2 = λ = 0 on ∂Ω) and values from
    the coordinates elsewhere (the same on any partition), shifted by `seed`."""
    n = disc.n
    x = disc.V.tabulate_dof_coordinates()[:n, :2].T
    u1 = 0.1 + 0.3 * np.sin(3 * x[0] + seed) * x[1]
    u2 = 0.05 * np.cos(2 * x[1] - seed) + 0.1 * x[0]
    lam = np.sin(5 * x[0] * x[1] + seed)
    b = disc.boundary_owned
    u1[b], u2[b], lam[b] = disc.g, 0.0, 0.0
    return np.concatenate([u1, u2, lam])


def main(N):
    from membranes.estimation.energy_error import EnergyError
    from membranes.estimation.estimators import Estimators
    comm = MPI.COMM_WORLD
    disc, X, sigma, alg, r, dlam = scene(comm, N)
    est = Estimators(disc)
    eta_rem = est.remainder(r, dlam)
    plain = est.assemble(X, sigma)
    full = est.assemble(X, sigma, alg, eta_rem)
    out = {"eta_rem": eta_rem, "energy_error": EnergyError(disc)(X)}
    # the shortcuts without σ_disc (the gates' signals), reduced over the processes too
    lin = est.linearisation(X)
    eta_rec, rec_lin = est.recovered(X, linearisation=True)
    out.update({f"lin.{k}": v for k, v in lin.items()})
    out.update({f"rec.{k}": v for k, v in rec_lin.items()})
    out["rec.eta_rec"] = eta_rec
    for name, values in (("plain", plain), ("full", full)):
        for key, v in values.items():
            if key == "eta_K":
                v = float(np.sqrt(comm.allreduce(float((v ** 2).sum()), op=MPI.SUM)))
            out[f"{name}.{key}"] = v
    # with the flux equilibration, the ν flux between two iterates (§5, §6)
    from membranes.estimation.equilibration import FluxEquilibration
    est = Estimators(disc, FluxEquilibration(disc))
    X, X2 = iterate(disc, 0.0), iterate(disc, 0.7)
    R, R2 = residual(disc, X), residual(disc, X2)
    alg, eta_rem = est.nu_flux(X, R, X2, R2)
    for name, values in (("nu", est.evaluate(X, R, alg, eta_rem)), ("bare", est.evaluate(X, R))):
        for key, v in values.items():
            if key == "eta_K":
                v = float(np.sqrt(comm.allreduce(float((v ** 2).sum()), op=MPI.SUM)))
            out[f"{name}.{key}"] = v
    # an iterate that differs from X2 in λh at one vertex, owned by one process, and so does
    # its residual (D is diagonal): σ_disc(X2, R2), kept, is not its σ_disc on any process
    # (the kept pairs are compared on every process)
    n = disc.n
    xy = disc.V.tabulate_dof_coordinates()[:n, :2]
    d = np.hypot(xy[:, 0] - 0.5, xy[:, 1] - 0.5)
    X3 = X2.copy()
    X3[2 * n:][d == comm.allreduce(d.min(initial=np.inf), op=MPI.MIN)] += 0.5
    out["bump.eta"] = est.evaluate(X3, residual(disc, X3))["eta"]
    from mpi_common import print_agreed  # run as a script from tests/core
    print_agreed(comm, out)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 12)
