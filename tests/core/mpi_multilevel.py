"""The multilevel algebraic flux (§6) on P processes: the script of tests/core/test_multilevel.py.

`mpirun -n P python tests/core/mpi_multilevel.py SCENE J H` builds the scene (disk or square)
with J levels from mesh size H on P processes, lifts a residual R that is a fixed function of
the vertex coordinates (0 on ∂Ω), so that every partition sees the same r_h, computes σ_alg and
prints on rank 0 one JSON line: ‖σ_alg‖, the largest cell norm ‖σ_alg‖_K, the per-cell
divergence defect max_K ‖∇·σ_alg - r_h‖_K / |K|^{1/2} against max_K ‖r_h‖_K / |K|^{1/2}, and
per level the global number of coarse patches whose cells lie on more than one process, and
the relative difference between `defect_sq` of a perturbed σ (a defect far above round-off)
and ‖∇·σ - r_h‖² integrated by dolfinx over all processes. Every rank checks that it holds
the same global numbers.
"""

import sys

import numpy as np
import ufl
from mpi4py import MPI


def residual(disc):
    """R at the owned P1 dofs: a smooth function of the coordinates with ~6 oscillations
    across the domain (insensitive to the round-off of the coordinates), 0 on ∂Ω."""
    x = disc.V.tabulate_dof_coordinates()[:disc.n, :2]
    R = np.sin(41 * x[:, 0] + 3) * np.cos(37 * x[:, 1] - 1) + np.sin(29 * x[:, 0] * x[:, 1])
    R[disc.boundary_owned] = 0.0
    return R


def scene(name, J, h, comm):
    from membranes.fem.discretisation import discretise
    from membranes.model import scenes
    build = {"disk": scenes.disk, "square": scenes.square}[name]
    problem = build(h=h, levels=J, comm=comm)
    return problem, discretise(problem)


def cell_measures(sigma, r):
    """Per owned cell: ‖σ‖_K², ‖∇·σ - r‖_K², ‖r‖_K², |K| (DG0-tested forms)."""
    from dolfinx import fem
    from dolfinx.fem.petsc import assemble_vector

    from membranes.forms.estimators import cell_norm_squared
    mesh = r.function_space.mesh
    w = ufl.TestFunction(fem.FunctionSpace(mesh, ("DG", 0)))
    n = mesh.topology.index_map(2).size_local
    out = []
    for form in (cell_norm_squared(sigma, w), cell_norm_squared(ufl.div(sigma) - r, w),
                 cell_norm_squared(r, w), w * ufl.dx):
        b = assemble_vector(fem.form(form))
        out.append(b.array_r[:n].copy())
        b.destroy()
    return out


def divergence_defect(sigma, r, comm):
    """(max_K ‖∇·σ - r‖_K / |K|^{1/2}, max_K ‖r‖_K / |K|^{1/2}) over all processes."""
    _, defect, rr, area = cell_measures(sigma, r)
    return (comm.allreduce(float(np.sqrt(defect / area).max(initial=0.0)), op=MPI.MAX),
            comm.allreduce(float(np.sqrt(rr / area).max(initial=0.0)), op=MPI.MAX))


def straddling(flux, comm):
    """Per level, the global number of coarse patches with cells on more than one process."""
    from mpi_patches import straddling as count  # run as a script from tests/core
    return [count(comm, level.patches) for level in flux.levels]


def ghost_mismatch(mesh):
    """The largest distance between a local geometry node (owned or ghost) and its owner's
    copy over all processes: 0 when every process sees the same (curved, §9) mesh, also in
    its ghost cells."""
    from dolfinx import la
    x = mesh.geometry.x[:, :2]
    v = la.vector(mesh.geometry.index_map(), bs=2)
    v.array[:] = x.ravel()
    v.scatter_forward()
    local = float(np.abs(v.array.reshape(-1, 2) - x).max(initial=0.0))
    return mesh.comm.allreduce(local, op=MPI.MAX)


def defect_sq_error(flux, sigma, r, comm):
    """|defect_sq - ‖∇·σ' - r‖²| / ‖∇·σ' - r‖² for σ' = σ + 1e-3 sin(global dof number):
    `defect_sq` from the defect's moments, summed over the processes, against the cell
    integrals of `cell_measures` summed alike."""
    from dolfinx import fem
    bumped = fem.Function(sigma.function_space)
    imap = sigma.function_space.dofmap.index_map
    dofs = imap.local_to_global(np.arange(imap.size_local + imap.num_ghosts, dtype=np.int32))
    bumped.x.array[:] = sigma.x.array + 1e-3 * np.sin(np.asarray(dofs, dtype=float))
    bumped.x.scatter_forward()
    flux._check(bumped, scale=1e6)             # (a scale that lets the large defect pass)
    _, defect, _, _ = cell_measures(bumped, r)
    direct = comm.allreduce(float(defect.sum()), op=MPI.SUM)
    return abs(flux.defect_sq - direct) / direct


def main(name, J, h):
    from dolfinx import fem

    from membranes.estimation.lifting import Lifting
    from membranes.estimation.multilevel import MultilevelFlux
    comm = MPI.COMM_WORLD
    problem, disc = scene(name, J, h, comm)
    flux = MultilevelFlux(disc, problem.hierarchy)
    r = Lifting(disc.V)(residual(disc))
    sigma = flux.sigma(r)
    s2, _, _, _ = cell_measures(sigma, r)
    defect, scale = divergence_defect(sigma, r, comm)
    norm = np.sqrt(comm.allreduce(float(fem.assemble_scalar(
        fem.form(ufl.inner(sigma, sigma) * ufl.dx))), op=MPI.SUM))
    out = dict(processes=comm.size, vertices=disc.n_global, norm=float(norm),
               max_cell=comm.allreduce(float(np.sqrt(s2).max(initial=0.0)), op=MPI.MAX),
               defect=defect, scale=scale, straddling=straddling(flux, comm),
               ghost_mismatch=max(ghost_mismatch(mesh) for mesh in problem.hierarchy.meshes),
               summary=flux.summary(), defect_sq_error=defect_sq_error(flux, sigma, r, comm))
    from mpi_common import print_agreed  # run as a script from tests/core
    print_agreed(comm, out)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]))
