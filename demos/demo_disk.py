# # Two membranes in contact: exact, inexact and adaptive Newton on the disk
#
# This demo solves the contact problem between two elastic membranes on the unit disk, the
# test case of Dabaghi, Martin and Vohralík (J. Sci. Comput. 84:28, 2020) whose exact solution
# is known ([theory](../docs/theory.md) §9), with the three semismooth Newton methods of §8.
# It shows
#
# - how to build a scene with a hierarchy of meshes (`membranes.scenes`),
# - how `membranes.solve` runs exact, inexact and adaptive inexact Newton,
# - the guaranteed bound η ≥ |||u − u_h||| that certifies each answer, and its split into
#   discretisation, linearisation and algebraic parts (§7),
# - the picture of the energy error and of η against wall time,
# - the files a run writes (`summary.json`, `history.csv`, `solution.xdmf`).
#
# Run it as `python demos/demo_disk.py [--quick] [--out DIR]` (`--quick`, or the environment
# variable `MEMBRANES_DEMO_QUICK=1`, takes a coarse mesh and runs in seconds); under
# `mpirun -n P` the same script runs on P processes.
#
# ## Equations
#
# Membrane 1 (modulus $\mu_1$, held at height $g$ on $\partial\Omega$) lies above membrane 2
# ($\mu_2$, held at 0); loads $f_1, f_2$ push them, and where they touch a contact pressure
# $\lambda \ge 0$ keeps them apart:
#
# $$
# -\mu_1 \Delta u_1 - \lambda = f_1, \quad -\mu_2 \Delta u_2 + \lambda = f_2, \quad
# u_1 - u_2 \ge 0,\ \lambda \ge 0,\ (u_1 - u_2)\lambda = 0 .
# $$
#
# On the disk $\mu_1 = \mu_2 = 1$, $g = 0.05$, and the membranes touch on the disk
# $r \le 1/\sqrt{2}$, where $\lambda = 2g$ (§9). P1 finite elements with a lumped contact
# term turn this into $N$ complementarity conditions at the vertices (§2); a C-function
# ($\min$ here) turns those into equations, which semismooth Newton solves (§3).

# +
import os

from mpi4py import MPI

from membranes import scenes, solve
from membranes.app.demo import figure_class, options, say
from membranes.app.outputs import write_outputs

out, quick = options("disk", "exact, inexact and adaptive Newton on the disk",
                     "folder for the picture and the outputs")
comm = MPI.COMM_WORLD
# -

# ## The scene
#
# `scenes.disk(h, levels)` meshes the unit disk with gmsh (target size `h`) and refines it
# `levels` times uniformly; each refinement moves the new boundary vertices onto the circle,
# so the finest mesh $T_J$ approximates the disk, not the first polygon (§9). The scene
# carries the data and the exact solution, so every run below also measures its true error.
# The data jump across the circle $r = 1/\sqrt{2}$, which cuts cells: those cells are
# integrated with a composite quadrature rule.

h, levels = (0.4, 1) if quick else (0.2, 3)
problem = scenes.disk(h=h, levels=levels)
say(f"disk: h = {h}, {levels} refinements; T_J has "
    f"{problem.mesh.topology.index_map(0).size_global} vertices, "
    f"{problem.mesh.topology.index_map(2).size_global} cells")

# ## Three Newton methods
#
# All three start on the coarse mesh $T_0$ from $X^0 = (g, 0, 0)$ and use nested iteration:
# the solution on $T_j$, prolonged, is the initial guess on $T_{j+1}$. Each Newton step is
# solved by FGMRES with a BoomerAMG preconditioner for the mean and the gap of the two
# membranes (`solver="amg"`, §10). They differ in when they stop (§8):
#
# - **exact**: every linear solve to a relative residual of $2\cdot10^{-12}$, Newton until
#   the nonlinear residual is $10^{-10}$ of the data;
# - **inexact**: each linear solve only as far as the current nonlinear residual;
# - **adaptive**: the estimators decide. Krylov stops once
#   $\eta_{alg} \le \gamma_{alg} \max(\eta_{disc}, \eta_{lin})$, Newton once
#   $\eta_{lin} \le \gamma_{lin}\, \eta_{disc}$ ($\gamma = 0.3$): no iteration is spent on an
#   error the discretisation error already hides.
#
# `errors="iterates"` also records the energy error of every iterate, computed off the clock,
# for the picture below. Every answer comes with its certificate: the estimators at the final
# iterate, `sol.estimates`.

# +
runs = {}
for variant in ("exact", "inexact", "adaptive"):
    runs[variant] = solve(problem, newton=variant, errors="iterates")

say(f"{'method':9s} {'Newton':>6s} {'per level':>10s} {'Krylov':>6s} {'time [s]':>8s} "
    f"{'error':>10s} {'eta':>10s} {'eta_disc':>10s} {'eta_lin':>10s} {'eta_alg':>10s} "
    f"{'eta/error':>9s}")
for variant, sol in runs.items():
    est = sol.estimates
    per_level = "+".join(str(p["newton_iterations"]) for p in sol.per_level)
    say(f"{variant:9s} {sol.newton_iterations:6d} {per_level:>10s} "
        f"{sol.linear_iterations:6d} {sol.wall_time_s:8.2f} {sol.energy_error:10.3e} "
        f"{est['eta']:10.3e} {est['eta_disc']:10.3e} {est['eta_lin']:10.3e} "
        f"{est['eta_alg']:10.3e} {est['eta'] / sol.energy_error:9.3f}")
# -

# ## What the certificate says
#
# $\eta$ is a guaranteed upper bound of the energy error $|||u - u_h|||$ of the iterate the
# method returns, whatever the solvers did (§7): it holds for the exact solution of the
# discrete problem and equally for an iterate stopped early, because the residual that an
# early stop leaves is part of the bound. The effectivity $\eta / |||u - u_h|||$ says how
# sharp it is. (On the disk, the error is measured on the polygon of $T_J$ against the
# disk's exact solution; docs/choices.md says what that means.)
#
# The split tells where the error comes from. Exact and inexact Newton end with
# $\eta_{lin}$ and $\eta_{alg}$ far below $\eta_{disc}$: their last iterations bought
# nothing visible in the error. The adaptive method stops as soon as the linearisation and
# algebraic parts are a fraction of the discretisation part:

adaptive = runs["adaptive"]
est, opts = adaptive.estimates, adaptive.options
say(f"adaptive: eta_lin = {est['eta_lin']:.3e} <= gamma_lin eta_disc = "
    f"{opts['gamma_lin'] * est['eta_disc']:.3e}; eta_alg = {est['eta_alg']:.3e} "
    f"(gamma_alg = {opts['gamma_alg']})")
for variant, sol in runs.items():
    bound = sol.estimates["eta"] >= sol.energy_error
    say(f"{variant}: eta = {sol.estimates['eta']:.4e} >= error = {sol.energy_error:.4e}: "
        f"{bound}")

# ## Error and estimate against time
#
# Every history record (one per Newton iterate here; the adaptive run also records every
# ν-th Krylov iterate) carries the run's clock when it was made, its energy error, and, where
# the method estimated it, the estimators. Plotted against time, the error of each method
# falls level by level with the nested iteration; the adaptive method's η follows its error
# from above at every iterate it estimated, while exact and inexact Newton carry a single
# certificate, at the end. The estimates are not free: the adaptive run leaves the coarse
# levels by a residual test without estimators (`coarse="residual"`, docs/choices.md),
# then sets up the flux equilibration of $T_J$ (the pause before its first Newton step)
# and evaluates the estimators at the iterates its stopping tests read; whether that pays
# off depends on how much the Krylov and Newton steps it saves cost. `membranes report`
# measures it for every method side by side.

# +
picture = os.path.join(out, "error_vs_time.png")
Figure = figure_class()       # None without matplotlib: the demo goes on without it
if comm.rank == 0 and Figure is not None:
    fig = Figure(figsize=(7.5, 4.8), layout="constrained")
    ax = fig.add_subplot()
    for i, (variant, sol) in enumerate(runs.items()):
        records = [r for r in sol.history if r["kind"] != "krylov"]
        t = [r["wall_time_s"] for r in records if r["energy_error"]]
        err = [r["energy_error"] for r in records if r["energy_error"]]
        ax.plot(t, err, "-o", ms=3, color=f"C{i}", label=f"{variant}: error")
        t = [r["wall_time_s"] for r in records if r["eta"] is not None]
        eta = [r["eta"] for r in records if r["eta"] is not None]
        ax.plot(t, eta, "--s" if len(eta) > 1 else "s", ms=5 if len(eta) > 1 else 9,
                color=f"C{i}", label=f"{variant}: η")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("energy error |||u - u_h|||, estimate η")
    ax.set_title(f"disk, J = {levels}: error and η at the Newton iterates")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(picture, dpi=100)
    say("picture:", picture)
# -

# ## Outputs
#
# `write_outputs` writes `summary.json` (counts, times, η and its parts, the energy error
# and the effectivity), `history.csv` (one row per recorded iterate with its estimates) and
# `solution.xdmf` + `.h5` with `u1`, `u2`, `lambda` and the local estimator `eta` ($\eta_K$,
# one value per cell) for ParaView. `membranes solve --scene disk --h 0.2 --levels 3 --out DIR`
# does the same from the command line (docs/cli.md, docs/outputs.md).

say("written to", write_outputs(adaptive, os.path.join(out, "adaptive")))
