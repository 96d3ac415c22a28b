"""Benchmark: GMRES iterations per Newton step with ILU(0) and with the vertex-block AMG
preconditioner (membranes.preconditioner, `petsc_options={"pc_type": "vertex_amg"}`) on the
eliminated 2N Newton system, as the mesh is refined.

Disk scene (DESIGN §9), gmsh mesh at h = 0.0375 (about 2.6k vertices) refined uniformly
`levels` times (Plaza; each level multiplies the vertex count by about 4): levels 1, 3, 4 give
about 1e4, 1.7e5 and 6.6e5 vertices. Exact Newton (‖R_alg‖/‖B‖ ≤ 2e-12 at every step, Newton
stops at ‖R_lin‖/‖(F, 0)‖ ≤ 1e-10), Newton-min and Newton-Fischer–Burmeister, GMRES(30)
preconditioned on the right, unpreconditioned norm. For each run: Newton steps, GMRES
iterations per Newton step (mean and max over the steps, and the list), the solution's
`wall_time_s` (the method's time: discretisation and Newton loop, the same discretisation for
both preconditioners) and the wall time of the whole `solve` call (with the energy error).

ILU(0) is only run up to `--ilu-max` vertices (default 2e5): its iterations grow like 1/h, and
at 6.6e5 vertices the run would take hours.

Usage: `.venv/bin/python benchmarks/bench_preconditioner.py [--levels 1 3 4] [--h 0.0375]
[--ilu-max 200000] [--cfun min fb]`.
"""

import argparse
import time

import numpy as np

from membranes import scenes, solve
from membranes.cli import quiet_jit_logging

PRECONDITIONERS = {"ilu0": {}, "vertex_amg": {"pc_type": "vertex_amg"}}


def run(problem, cfun, options):
    """Figures of one exact-Newton solve on the eliminated system."""
    start = time.perf_counter()
    sol = solve(problem, newton="exact", cfun=cfun, system="eliminated",
                linear_solver="gmres", petsc_options=options, estimators=False)
    total = time.perf_counter() - start
    its = [rec["linear_it"] for rec in sol.history if rec["kind"] == "newton"]
    return {"converged": sol.converged, "newton": sol.newton_iterations, "its": its,
            "mean": float(np.mean(its)), "max": max(its), "total_s": total,
            "newton_s": sol.wall_time_s, "vertices": sol.disc.n}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, default=0.0375)
    parser.add_argument("--levels", type=int, nargs="+", default=[1, 3, 4])
    parser.add_argument("--ilu-max", type=float, default=2e5)
    parser.add_argument("--cfun", nargs="+", default=["min", "fb"])
    args = parser.parse_args()
    quiet_jit_logging()
    for options in PRECONDITIONERS.values():      # JIT-compile every form outside the clock
        run(scenes.disk(h=0.3), "min", options)
    rows = []
    for levels in args.levels:
        problem = scenes.disk(h=args.h, levels=levels)
        for cfun in args.cfun:
            for name, options in PRECONDITIONERS.items():
                n = problem.mesh.geometry.x.shape[0]
                if name == "ilu0" and n > args.ilu_max:
                    print(f"levels {levels}: {n} vertices, {cfun}, {name}: skipped "
                          f"(more than {args.ilu_max:.0f} vertices)", flush=True)
                    continue
                r = run(problem, cfun, options)
                flag = "" if r["converged"] else " (NOT converged)"
                print(f"levels {levels}: {r['vertices']} vertices, {cfun:3s}, {name:10s}{flag}: "
                      f"{r['newton']:3d} Newton, GMRES/step mean {r['mean']:6.1f} max "
                      f"{r['max']:4d}, wall_time_s {r['newton_s']:8.1f} s, whole solve "
                      f"{r['total_s']:8.1f} s; its {r['its']}", flush=True)
                rows.append((r["vertices"], cfun, name, r))
    print("\n| vertices | C-function | preconditioner | Newton steps | GMRES/step mean (max) | "
          "wall_time_s | whole solve s |\n|---|---|---|---|---|---|---|")
    for vertices, cfun, name, r in rows:
        flag = "" if r["converged"] else " (not converged)"
        print(f"| {vertices} | {cfun} | {name}{flag} | {r['newton']} | {r['mean']:.1f} "
              f"({r['max']}) | {r['newton_s']:.1f} | {r['total_s']:.1f} |")


if __name__ == "__main__":
    main()
