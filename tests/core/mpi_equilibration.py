"""Compatible data for the flux equilibration, and its check on P processes (§4, §5, §12).

`compatible(mesh)` builds P1 u, λ (λ = 0 on ∂Ω), a load f and, for α = 1, 2, the residual
R_l = (f, ψ_l) ± λ_l (ψ_l, 1) - μ (∇u, ∇ψ_l) at interior dofs (0 on ∂Ω) and its lifting r:
then the linear rows of §4 hold exactly, μ (∇u, ∇ψ_l) = (f ± λ_l - r, ψ_l), so every interior
patch problem of §5 is compatible. All integrals of f use one degree-6 rule (`DATA`), as the
assembled loads of the discretisation do.

Run as a script under mpirun (`python mpi_equilibration.py lifting|equilibration`): it builds
the same meshes on COMM_WORLD and, on rank 0, on COMM_SELF, checks on P processes what the
serial tests check, compares the parallel results with the serial ones, asserts that some
patches straddle processes, and prints one `OK ...` line per check on rank 0.
"""

import sys

import numpy as np
import ufl
from mpi4py import MPI

DATA = {"quadrature_degree": 6}
MU = 1.5


def square(comm, n=12, ghosts=False):
    from dolfinx import mesh as dm
    mode = dm.GhostMode.shared_facet if ghosts else dm.GhostMode.none
    return dm.create_unit_square(comm, n, n, dm.CellType.triangle, mode)


def ghosted_square(comm):
    """The square with a layer of ghost cells (GhostMode.shared_facet)."""
    return square(comm, 10, ghosts=True)


def disk(comm, h=0.2):
    from membranes.fem.meshes import unit_disk
    return unit_disk(h, comm)


def assembled(form):
    """An assembled P1 vector with owned entries final, as numpy (owned part)."""
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_vector
    from petsc4py import PETSc
    b = assemble_vector(fem.form(form))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    return b.array.copy()


def boundary(V):
    """Bool over the owned P1 dofs: on ∂Ω (dolfinx's exterior facets)."""
    from dolfinx import fem
    from dolfinx import mesh as dm
    mesh = V.mesh
    mesh.topology.create_connectivity(1, 2)
    dofs = fem.locate_dofs_topological(V, 1, dm.exterior_facet_indices(mesh.topology))
    b = fem.Function(V)
    b.x.array[dofs] = 1.0
    from dolfinx import la
    b.x.scatter_reverse(la.ScatterMode.add)
    return b.x.array[:V.dofmap.index_map.size_local] > 0


def projection(f, Q, dx):
    """The L² projection of f onto Q (mass matrix factorised by MUMPS)."""
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_matrix, assemble_vector
    from petsc4py import PETSc
    p, q = ufl.TrialFunction(Q), ufl.TestFunction(Q)
    M = assemble_matrix(fem.form(p * q * ufl.dx))
    M.assemble()
    b = assemble_vector(fem.form(f * q * dx))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    ksp = PETSc.KSP().create(Q.mesh.comm)
    ksp.setOperators(M)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    out = fem.Function(Q)
    ksp.solve(b, out.vector)
    out.x.scatter_forward()
    for obj in (ksp, M, b):
        obj.destroy()
    return out


class Compatible:
    """u, λ, f, and per membrane α the residual R_α (owned), r_α (DG1), Π f (DG1); f times
    `load`, u interpolated from `u_of` (points (3, n) → values) if given."""

    def __init__(self, mesh, load=1.0, u_of=None):
        from dolfinx import fem

        from membranes.estimation.lifting import Lifting
        self.mesh = mesh
        self.V = V = fem.FunctionSpace(mesh, ("Lagrange", 1))
        x = ufl.SpatialCoordinate(mesh)
        self.f = load * (10.0 * ufl.sin(3.0 * x[0]) * ufl.exp(x[1]) + 1.0)
        self.dx_data = ufl.dx(domain=mesh, metadata=DATA)
        self.u = fem.Function(V)
        self.u.interpolate(u_of if u_of is not None else
                           lambda p: np.cos(2.0 * p[0]) * p[1] + p[0] ** 2 + 0.3 * p[0] * p[1])
        self.lam = fem.Function(V)
        self.lam.interpolate(lambda p: 4.0 * np.maximum(1.0 - p[0] ** 2 - p[1] ** 2, 0.0)
                             * p[0] * (1.0 - p[0]) * (1.0 + p[1]) ** 2)
        n = V.dofmap.index_map.size_local
        self.on_boundary = boundary(V)
        self.lam.x.array[:n][self.on_boundary] = 0.0
        self.lam.x.scatter_forward()
        v = ufl.TestFunction(V)
        F = assembled(self.f * v * self.dx_data)
        D = assembled(v * ufl.dx)
        S = assembled(MU * ufl.inner(ufl.grad(self.u), ufl.grad(v)) * ufl.dx)
        self.lifting = Lifting(V)
        self.Q = self.lifting.Q
        self.R, self.r = {}, {}
        for alpha, sign in ((1, 1.0), (2, -1.0)):
            R = F + sign * self.lam.x.array[:n] * D - S
            R[self.on_boundary] = 0.0
            self.R[alpha] = R
            self.r[alpha] = self.lifting(R)
        # Π f: the DG1 L² projection (a direct solve with the DG1 mass matrix)
        self.Pf = projection(self.f, self.Q, self.dx_data)

    def sign(self, alpha):
        return 1.0 if alpha == 1 else -1.0

    def divergence_defect(self, sigma, alpha):
        """(max_K ‖∇·σ - (Π f ± λ - r)‖_K, max_K ‖Π f ± λ - r‖_K) over all processes."""
        from dolfinx import fem

        from membranes.forms.estimators import cell_norm_squared
        w = ufl.TestFunction(fem.FunctionSpace(self.mesh, ("DG", 0)))
        target = self.Pf + self.sign(alpha) * self.lam - self.r[alpha]
        e = assembled(cell_norm_squared(ufl.div(sigma) - target, w))
        s = assembled(cell_norm_squared(target, w))
        comm = self.mesh.comm
        return (np.sqrt(comm.allreduce(e.max(initial=0.0), op=MPI.MAX)),
                np.sqrt(comm.allreduce(s.max(initial=0.0), op=MPI.MAX)))

    def functionals(self, sigma):
        """Partition-independent numbers of an RT function: ‖σ‖², ‖∇·σ‖², (σ, (1, x)),
        (σ, (y², xy))."""
        from dolfinx import fem
        x = ufl.SpatialCoordinate(self.mesh)
        forms = [ufl.inner(sigma, sigma), ufl.div(sigma) ** 2,
                 ufl.inner(sigma, ufl.as_vector((1.0, x[0]))),
                 ufl.inner(sigma, ufl.as_vector((x[1] ** 2, x[0] * x[1])))]
        comm = self.mesh.comm
        return np.array([comm.allreduce(fem.assemble_scalar(fem.form(g * ufl.dx)), op=MPI.SUM)
                         for g in forms])


def equilibrate(data):
    """FluxEquilibration on data.mesh and σ_1, σ_2."""
    from membranes.estimation.equilibration import FluxEquilibration
    eq = FluxEquilibration(data.V, measures=[data.dx_data])
    sigmas = {alpha: eq.sigma(alpha, data.u, data.lam, data.r[alpha], data.f, MU)
              for alpha in (1, 2)}
    return eq, sigmas


def straddling(eq):
    """Number of patches (over all colours) whose cells live on more than one process."""
    from mpi_patches import straddling as count  # run as a script from tests/core

    from membranes.estimation.equilibration import vertex_patches
    patches, _ = vertex_patches(eq.V, eq.colour, eq.ncolours, eq.on_boundary)
    return count(eq.comm, patches)


def reductions(comm):
    """`divergence.check` on P processes: the largest defect and the largest scale over the
    processes decide. Process p has defect (p + 1) 1e-10 and scale p + 1, so the relative
    defect is P 1e-10 / P = 1e-10 (to round-off), whatever P; a defect on the last process
    only is refused by every process. Returns the relative defect."""
    from membranes.estimation import divergence
    relative = divergence.check((comm.rank + 1) * 1e-10, comm.rank + 1.0, comm, "test")
    assert abs(relative - 1e-10) <= 1e-25, relative
    try:
        divergence.check(1.0 if comm.rank == comm.size - 1 else 0.0, 1.0, comm, "one flux")
    except RuntimeError:
        refused = True
    else:
        refused = False
    assert refused, "a defect on one process passed the check"
    return relative


def main(mode):
    comm = MPI.COMM_WORLD
    if mode == "equilibration":
        relative = reductions(comm)
        if comm.rank == 0:
            print(f"OK check P={comm.size} relative={relative:.3e}", flush=True)
    meshes = [("square", square), ("disk", disk)]
    if mode == "equilibration":
        meshes.append(("ghosted", ghosted_square))
    for name, build in meshes:
        data = Compatible(build(comm))
        serial = Compatible(build(MPI.COMM_SELF)) if comm.rank == 0 else None
        if mode == "lifting":
            from dolfinx import fem
            v = ufl.TestFunction(data.V)
            for alpha in (1, 2):
                back = assembled(data.r[alpha] * v * ufl.dx)
                err = comm.allreduce(np.abs(back - data.R[alpha]).max(initial=0.0), op=MPI.MAX)
                scale = comm.allreduce(np.abs(data.R[alpha]).max(initial=0.0), op=MPI.MAX)
                assert err <= 1e-13 * scale, (name, alpha, err, scale)
                norm = comm.allreduce(fem.assemble_scalar(fem.form(data.r[alpha] ** 2 * ufl.dx)))
                if comm.rank == 0:
                    ref = fem.assemble_scalar(fem.form(serial.r[alpha] ** 2 * ufl.dx))
                    assert abs(norm - ref) <= 1e-11 * ref, (name, alpha, norm, ref)
                    print(f"OK lifting {name} alpha={alpha} P={comm.size} "
                          f"rel={err / scale:.1e} |r|^2={norm:.12e} serial={ref:.12e}",
                          flush=True)
            continue
        eq, sigmas = equilibrate(data)
        nstraddle = straddling(eq)
        assert comm.size == 1 or nstraddle > 0, "no patch straddles processes"
        if comm.rank == 0:
            _, serial_sigmas = equilibrate(serial)
        for alpha in (1, 2):
            defect, scale = data.divergence_defect(sigmas[alpha], alpha)
            assert defect <= 1e-11 * scale, (name, alpha, defect, scale)
            values = data.functionals(sigmas[alpha])
            if comm.rank == 0:
                ref = serial.functionals(serial_sigmas[alpha])
                sdefect, _ = serial.divergence_defect(serial_sigmas[alpha], alpha)
                diff = np.abs(values - ref).max() / np.abs(ref).max()
                assert diff <= 1e-11, (name, alpha, values, ref)
                print(f"OK equilibration {name} alpha={alpha} P={comm.size} "
                      f"colours={eq.ncolours} straddling={nstraddle} "
                      f"defect={defect / scale:.1e} serial_defect={sdefect / scale:.1e} "
                      f"functionals_rel_diff={diff:.1e} |sigma|^2={values[0]:.12e}",
                      flush=True)


if __name__ == "__main__":
    import logging

    import ffcx  # noqa: F401  (installs its root handler: quiet it, as membranes.cli does)
    for handler in logging.getLogger().handlers:
        handler.setLevel(logging.WARNING)
    main(sys.argv[1] if len(sys.argv) > 1 else "equilibration")
