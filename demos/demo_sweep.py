# # A load sweep on one mesh: kept set-ups and a certificate per load
#
# A parameter study solves the same contact problem for many data: here the load $f_1 = -t$
# on membrane 1 grows, and the contact set with it. This demo shows
#
# - how to vary the data of a `membranes.Problem` on one mesh hierarchy
#   (`dataclasses.replace`),
# - how a `membranes.Setups` keeps the flux equilibration of the mesh between the solves: its
#   patch systems depend on the mesh only, so only the first solve sets them up
#   ([theory](../docs/theory.md) §5, §12),
# - that each answer still carries its own guaranteed bound η (§7),
# - a picture of η and of the contact set's share of the domain against the load.
#
# Run it as `python demos/demo_sweep.py [--quick] [--out DIR]` (`--quick`, or
# `MEMBRANES_DEMO_QUICK=1`, takes a coarse mesh); under `mpirun -n P` the same script runs on
# P processes.
#
# ## Equations
#
# On the unit square, membrane 1 ($\mu_1 = 1$, height $g = 0.05$ on the boundary) lies above
# membrane 2 ($\mu_2 = 1$, height 0), and the load $f_1 = -t$ pushes membrane 1 down:
#
# $$
# -\mu_1 \Delta u_1 - \lambda = -t, \quad -\mu_2 \Delta u_2 + \lambda = 0, \quad
# u_1 - u_2 \ge 0,\ \lambda \ge 0,\ (u_1 - u_2)\lambda = 0 .
# $$
#
# Without contact $u_2 = 0$ and $u_1 = g - t w$, where $-\Delta w = 1$ in the square and $w = 0$
# on its boundary ($\max w \approx 0.0737$): the membranes touch in the middle once
# $t > g / \max w \approx 0.68$, and the contact set grows with $t$. No exact solution is
# known: η alone tells how good each answer is.

# +
import os
from dataclasses import replace

import numpy as np
from mpi4py import MPI

from membranes import Setups, scenes, solve
from membranes.app.demo import figure_class, options, say

out, quick = options("sweep", "a load sweep with kept set-ups", "folder for the picture")
comm = MPI.COMM_WORLD
# -

# ## One hierarchy, several loads
#
# `scenes.user` builds the mesh hierarchy once. `replace(base, f1=...)` makes a new Problem
# on the same meshes (a formula in x, y is checked to be finite on the mesh, as any user
# data). A `Setups` handed to every `solve` keeps the flux equilibration of $T_J$: the second
# and later solves skip the colouring, the patch blocks and their inverses, and assemble only
# the data parts of the certificate (§5: the loads $-(\psi_a f_\alpha, q)$).

# +
h, levels = (0.25, 1) if quick else (0.1, 3)
loads = (0.5, 2.0, 8.0) if quick else (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
base = scenes.user(mu1=1.0, mu2=1.0, g=0.05, f1="-1", f2="0", domain="square", h=h,
                   levels=levels)
say(f"unit square: h = {h}, {levels} refinements, "
    f"{base.mesh.topology.index_map(0).size_global} vertices on T_J")

kept = Setups()
rows = []
for t in loads:
    sol = solve(replace(base, f1=f"-{t:g}"), setups=kept)
    # the contact set: vertices with λ > 0 (owned ones, summed over the processes)
    n = sol.disc.n
    touching = comm.allreduce(int(np.count_nonzero(sol.lam.x.array[:n] > 0)), op=MPI.SUM)
    share = touching / sol.disc.n_global
    est = sol.estimates
    rows.append((t, sol.wall_time_s, sol.estimator_times[0], est["eta"], est["eta_disc"],
                 share, sol.converged and est["bound"]))
kept.clear()                       # the kept systems are freed here, not at the end of a solve

say(f"{'load t':>7s} {'time [s]':>9s} {'set-up [s]':>10s} {'eta':>10s} {'eta_disc':>10s} "
    f"{'contact':>8s} {'bound':>6s}")
for t, seconds, setup, eta, eta_disc, share, bound in rows:
    say(f"{t:7g} {seconds:9.2f} {setup:10.2f} {eta:10.3e} {eta_disc:10.3e} "
        f"{share:8.1%} {str(bound):>6s}")
# -

# The first solve sets the equilibration up; the others take it (their set-up column is what
# remains: the loads and the estimators' forms). Each row's η is the guaranteed bound of
# that load's answer, computed at its own final iterate: keeping the set-up changes how fast
# it is obtained, not what it is (tests/test_setups.py checks that a kept set-up gives the
# same η as a fresh one).
#
# (η is the bound of §7, which combines the parts more sharply than their sum,
# η ≤ η_disc + η_lin + η_alg; so η_disc alone may exceed it.)
#
# ## η and the contact set against the load

# +
picture = os.path.join(out, "sweep.png")
Figure = figure_class()       # None without matplotlib: the demo goes on without it
if comm.rank == 0 and Figure is not None:
    t = [r[0] for r in rows]
    fig = Figure(figsize=(7.5, 4.2), layout="constrained")
    ax = fig.add_subplot()
    ax.plot(t, [r[3] for r in rows], "-o", color="C0", label="η (guaranteed bound)")
    ax.plot(t, [r[4] for r in rows], "--s", color="C0", ms=4, label="η_disc")
    ax.set_xlabel("load t (f1 = -t)")
    ax.set_ylabel("estimate")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    right = ax.twinx()
    right.plot(t, [100 * r[5] for r in rows], "-^", color="C1", label="contact set")
    right.set_ylabel("vertices in contact [%]")
    handles = ax.get_legend_handles_labels()
    more = right.get_legend_handles_labels()
    ax.legend(handles[0] + more[0], handles[1] + more[1], fontsize=8, loc="upper left")
    ax.set_title(f"load sweep on one mesh ({levels} refinements), kept set-ups")
    fig.savefig(picture, dpi=100)
    say("picture:", picture)
elif comm.rank == 0:
    say("no picture: matplotlib is not installed (the folder stays empty)")
# -
