# # Your own geometry and data
#
# This demo solves the two-membrane contact problem on a domain of your own, drawn and meshed
# with gmsh, with loads given as formulas. It shows how to
#
# - draw a domain with gmsh's Python API and save its triangular mesh as a `.msh` file,
# - give the moduli, the boundary height and the loads (`membranes.scenes.user`),
# - solve with the adaptive Newton method and read its certificate: with user data there is
#   no exact solution to compare with, and the guaranteed bound η is what tells you how
#   accurate the answer is ([theory](../docs/theory.md) §7),
# - draw the gap $u_1 - u_2$, the contact pressure $\lambda$ and the local estimator
#   $\eta_K$, which shows where the error sits,
# - use the finest mesh, written as XDMF, as the mesh of a second problem.
#
# Run it as `python demos/demo_user_mesh.py [--quick] [--out DIR]` (`--quick`, or
# `MEMBRANES_DEMO_QUICK=1`: a coarse mesh, seconds); `mpirun -n P` runs it on P processes.
#
# ## The domain
#
# An L-shaped membrane frame, $(-1, 1)^2$ without the quarter $(0, 1) \times (-1, 0)$, drawn
# with gmsh's OpenCASCADE kernel. The re-entrant corner at the origin makes the solution
# singular there; the estimator will show it. Any 2D triangular gmsh mesh will do: the file
# is read on process 0 and dolfinx distributes it. If the file has no physical surface, all
# its surfaces are taken.

# +
import os

import ufl
from dolfinx import fem
from mpi4py import MPI

from membranes import scenes, solve
from membranes.app.demo import options, say
from membranes.app.outputs import write_outputs
from membranes.app.render import snapshots

out, quick = options("user_mesh", "the contact problem on your own gmsh mesh",
                     "folder for the mesh file, the pictures and the outputs")
comm = MPI.COMM_WORLD
msh = os.path.join(out, "l_shape.msh")


def l_shape(path, h):
    """Mesh the L-shaped domain with gmsh at target size h and write it to `path`."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("l_shape")
        square = gmsh.model.occ.addRectangle(-1, -1, 0, 2, 2)
        quarter = gmsh.model.occ.addRectangle(0, -1, 0, 1, 1)
        gmsh.model.occ.cut([(2, square)], [(2, quarter)])
        gmsh.model.occ.synchronize()
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        gmsh.model.addPhysicalGroup(2, surfaces, 1)
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", h)
        gmsh.model.mesh.generate(2)
        gmsh.write(path)
    finally:
        gmsh.finalize()


h, levels = (0.35, 1) if quick else (0.1, 2)
if comm.rank == 0:
    l_shape(msh, h)
comm.barrier()
# -

# ## The data
#
# Membrane 1 is soft ($\mu_1 = 1$), held at $g = 0.02$ on the boundary and pushed down by a
# load that grows towards the top; membrane 2 is three times stiffer ($\mu_2 = 3$), held at 0
# and pushed up by a wavy load. Loads are formulas in `x` and `y` (with `pi`, `sin`, `cos`,
# `exp`, `sqrt`, `abs`, `min`, `max`), parsed safely and checked to be finite on the mesh.
# `levels` uniform refinements of the gmsh mesh give the hierarchy $T_0, \dots, T_J$ for
# nested iteration. The command line takes the same data:
#
#     membranes solve --mesh l_shape.msh --levels 2 --mu1 1 --mu2 3 --g 0.02 \
#         --f1 "-0.15 - 0.1*y" --f2 "0.2 + 0.1*sin(2*pi*x)*cos(pi*y)" --out DIR

problem = scenes.user(mu1=1.0, mu2=3.0, g=0.02, f1="-0.15 - 0.1*y",
                      f2="0.2 + 0.1*sin(2*pi*x)*cos(pi*y)", mesh=msh, levels=levels)
say(f"{problem.description}: T_J has {problem.mesh.topology.index_map(0).size_global} "
    f"vertices")

# ## Solve and certify
#
# The default method: adaptive inexact semismooth Newton with nested iteration and the `amg`
# solver (§8). It stops Krylov and Newton as soon as the algebraic and linearisation parts of
# the estimate are a fraction of the discretisation part, and returns the estimators at the
# iterate it accepts: $|||u - u_h||| \le \eta$ holds for the exact solution $u$ of the
# continuous problem, which nobody knows here.

# +
sol = solve(problem)
est = sol.estimates
say(f"converged = {sol.converged}: {sol.newton_iterations} Newton steps "
    f"({'+'.join(str(p['newton_iterations']) for p in sol.per_level)} per level), "
    f"{sol.linear_iterations} Krylov steps, {sol.wall_time_s:.2f} s")
say(f"guaranteed bound |||u - u_h||| <= eta = {est['eta']:.4e}; parts: "
    f"eta_disc = {est['eta_disc']:.3e}, eta_lin = {est['eta_lin']:.3e}, "
    f"eta_alg = {est['eta_alg']:.3e}")
# -

# How large is that? The energy norm of the discrete solution, $|||u_h|||$, gives the scale:
# the relative error is at most $\eta / |||u_h|||$ (up to the error itself, which is small).

# +
norm_sq = fem.form(problem.mu1 * ufl.inner(ufl.grad(sol.u1), ufl.grad(sol.u1)) * ufl.dx
                   + problem.mu2 * ufl.inner(ufl.grad(sol.u2), ufl.grad(sol.u2)) * ufl.dx)
norm = comm.allreduce(fem.assemble_scalar(norm_sq), op=MPI.SUM) ** 0.5
say(f"|||u_h||| = {norm:.4e}: relative error at most {est['eta'] / norm:.2%}")
# -

# ## Pictures
#
# `membranes.app.render.snapshots` draws pictures of fields on the (distributed) mesh with
# pyvista, off-screen, all in one rendering process: P1 functions at the vertices, per-cell
# values on the cells. The gap vanishes where the membranes touch, and there the pressure is
# positive; $\eta_K$ (logarithmic scale) is largest by far at the re-entrant corner, where
# the solution is least smooth, smallest inside the contact zone, and a little larger along
# the free boundary, the edge of the contact zone, than around it.

# +
gap = fem.Function(sol.disc.V)
gap.x.array[:] = sol.u1.x.array - sol.u2.x.array
contact_png = os.path.join(out, "contact.png")
eta_png = os.path.join(out, "eta_K.png")
pictures = [([("u1 - u2", "point", gap, "gap u1 - u2"),
              ("lambda", "point", sol.lam, "contact pressure lambda")], contact_png,
             dict(cmap="plasma")),
            ([("eta_K", "cell", sol.eta_K, "local estimator eta_K")], eta_png, dict(log=True))]
# (None: drawn; else why not, as when pyvista cannot draw here: the rest goes on)
missing = [why for why in snapshots(sol.disc.V, pictures) if why]
if missing:
    say("pictures skipped:", "; ".join(missing))
else:
    say("pictures:", contact_png, eta_png)
# -

# ## Outputs
#
# `summary.json`, `history.csv` and `solution.xdmf` (with `u1`, `u2`, `lambda` and `eta`)
# for ParaView, as `membranes solve --out` writes them (docs/outputs.md).

say("written to", write_outputs(sol, os.path.join(out, "solution")))

# ## The mesh again, from the XDMF file
#
# An XDMF file is a mesh file too (`--mesh`, `mesh=`), as dolfinx or meshio write it, read
# and checked on process 0 as a `.msh` file is. `solution.xdmf` holds $T_J$, so a second
# problem on it, here a stronger load on membrane 1, needs neither gmsh nor the refinements
# again. Its hierarchy is $T_J$ alone, so it is solved on that one mesh.

# +
again = scenes.user(mu1=1.0, mu2=3.0, g=0.02, f1="-0.3 - 0.1*y",
                    f2="0.2 + 0.1*sin(2*pi*x)*cos(pi*y)",
                    mesh=os.path.join(out, "solution", "solution.xdmf"))
sol2 = solve(again)
say(f"on T_J read back ({again.mesh.topology.index_map(0).size_global} vertices), f1 = "
    f"-0.3 - 0.1*y: {sol2.newton_iterations} Newton steps, eta = {sol2.estimates['eta']:.4e}")
# -
