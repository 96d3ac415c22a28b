# # Two membranes in contact: the disk test case
#
# This demo solves the contact problem between two elastic membranes on the unit disk, the
# test case of Dabaghi, Martin and Vohralík (J. Sci. Comput. 2020) whose exact solution is
# known (`../shared/DESIGN.md`, §9). It illustrates how to
#
# - build a scene (mesh, data, exact solution) with `membranes.scenes`,
# - solve the discrete problem by semismooth Newton with the C-functions `min` and
#   Fischer–Burmeister (`membranes.solve`), exactly and inexactly (GMRES),
# - certify the answer with the guaranteed a posteriori bound η (DESIGN §7),
# - check the answer against an independent solver (PETSc SNES VI on the decoupled
#   problem, DESIGN §10),
# - write `summary.json`, `history.csv` and `solution.xdmf` for ParaView.
#
# ## Equations
#
# Find $u_1, u_2, \lambda$ with
#
# $$
# -\mu_1 \Delta u_1 - \lambda = f_1, \quad -\mu_2 \Delta u_2 + \lambda = f_2, \quad
# u_1 - u_2 \ge 0,\ \lambda \ge 0,\ (u_1 - u_2)\lambda = 0,
# $$
#
# $u_1 = g$, $u_2 = 0$ on $\partial\Omega$. Membrane 1 lies above membrane 2 and $\lambda$ is
# the contact pressure. On the disk, $\mu_1 = \mu_2 = 1$, $g = 0.05$, and the membranes touch
# on the disk $r \le 1/\sqrt{2}$.

# +
import os
import sys

import numpy as np

from membranes import scenes, solve
from membranes.cli import quiet_jit_logging
from membranes.decoupled import solve_decoupled
from membranes.newton_system import split
from membranes.outputs import write_outputs

quiet_jit_logging()
out = sys.argv[1] if len(sys.argv) > 1 else os.path.join("out", "demo_disk")
# -

# ## The scene
#
# `scenes.disk(h)` meshes the unit disk with gmsh (target size `h`) and attaches the data and
# the exact solution. The data jump across the circle $r = 1/\sqrt{2}$, which cuts cells:
# those cells are integrated with a composite quadrature rule.

problem = scenes.disk(h=0.05)
print(f"disk: {problem.mesh.topology.index_map(0).size_global} vertices, "
      f"{problem.mesh.topology.index_map(2).size_global} cells")

# ## Semismooth Newton
#
# From the paper's initial guess $X^0 = (g, 0, 0)$, each Newton step linearises the
# C-function and solves the $3N \times 3N$ system with GMRES and ILU(0) to
# $\|R_{alg}\|/\|B\| \le 2 \cdot 10^{-12}$, until the nonlinear residual has dropped to
# $10^{-10}$ relative to the data. With `min` this is the primal–dual active set method;
# Fischer–Burmeister is smooth away from the origin. At every Newton iterate the estimators
# give $\eta \ge |||u - u_h|||$; the effectivity index is $\eta / |||u - u_h|||$.

solutions = {}
for cfun in ("min", "fb"):
    sol = solve(problem, cfun=cfun, progress=True)
    solutions[cfun] = sol
    s = sol.summary()
    print(f"{cfun:>3}: converged = {sol.converged}, {sol.newton_iterations} Newton steps, "
          f"{sol.linear_iterations} GMRES steps, energy error {sol.energy_error:.4e}, "
          f"eta {s['eta']:.4e} (effectivity {s['effectivity']:.3f}), "
          f"complementarity violation {sol.complementarity_violation():.1e}")

# Inexact Newton stops GMRES as soon as the algebraic residual is below the nonlinear one
# (checked every ν = 10 GMRES steps, as in the paper): cheaper steps, more of them. Its Krylov
# iterates carry no guaranteed bound yet (the algebraic flux comes with the next release).

inexact = solve(problem, newton="inexact", estimators=False)
print(f"inexact: {inexact.newton_iterations} Newton steps, {inexact.linear_iterations} GMRES "
      f"steps, energy error {inexact.energy_error:.4e}")

# Both C-functions define the same discrete solution:

n = solutions["min"].disc.n
for name, a, b in zip(("u1", "u2", "lambda"), split(solutions["min"].X, n),
                      split(solutions["fb"].X, n)):
    print(f"max |{name}(min) - {name}(fb)| / max |{name}| = "
          f"{np.abs(a - b).max() / np.abs(a).max():.1e}")

# ## An independent check
#
# $z = \mu_1 u_1 + \mu_2 u_2$ and $w = u_1 - u_2$ decouple the discrete system into a linear
# problem and an obstacle problem, which PETSc's `vinewtonrsls` solves.

peer = solve_decoupled(solutions["min"].disc)
u1, u2, lam = split(solutions["min"].X, n)
print(f"SNES VI: {peer.newton_iterations} iterations; "
      f"max relative difference in lambda {np.abs(lam - peer.lam).max() / lam.max():.1e}")

# ## Outputs
#
# `summary.json`, `history.csv` (one row per Newton iterate) and `solution.xdmf` with the P1
# functions `u1`, `u2`, `lambda`, to open in ParaView.

print("written to", write_outputs(solutions["min"], out))
