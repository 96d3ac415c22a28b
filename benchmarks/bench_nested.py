"""Benchmark: nested iteration (issue 6, item 1) against the single-mesh method on the disk.

The disk scene, h0 = 0.2, J levels of uniform refinement (default J = 4: 27,393 vertices on
T_4). For each C-function (min, fb) and method (exact with MUMPS; exact, inexact and
adaptive with GMRES(30) + ILU(0) on the full 3N system, the paper's solver; the same three
with GMRES + vertex_amg on the eliminated 2N system, "-amg"; ν = 10, γ = 0.3, at most 400
Newton steps per level), nested (T_0 .. T_J, `solve(nested=True)`) and not (T_J from
X^0 = (g, 0, 0)): the Newton steps and the linear iterations (GMRES; MUMPS solves) per
level, the totals, the wall time (`solve`'s: every level's discretisation, prolongation and
method; for adaptive the estimators' set-up and evaluations) and the final energy error.
Estimators run only where the method uses them (adaptive). Forms are JIT-compiled off the
clock by a warm-up solve.

Usage: `.venv/bin/python benchmarks/bench_nested.py [J] [min|fb ...]` (JSON lines on stdout).
"""

import json
import sys

from membranes import scenes, solve
from membranes.cli import quiet_jit_logging

VAMG = {"system": "eliminated", "petsc_options": {"pc_type": "vertex_amg"}}
METHODS = {"exact-mumps": {"newton": "exact", "linear_solver": "direct"},
           "exact": {"newton": "exact"}, "inexact": {"newton": "inexact"},
           "adaptive": {"newton": "adaptive"},
           "exact-amg": {"newton": "exact", **VAMG}, "inexact-amg": {"newton": "inexact", **VAMG},
           "adaptive-amg": {"newton": "adaptive", **VAMG}}


def run(problem, cfun, method, nested):
    options = METHODS[method]
    sol = solve(problem, cfun=cfun, nested=nested, max_newton=400,
                estimators=options["newton"] == "adaptive", **options)
    return {"cfun": cfun, "method": method, "nested": nested, "converged": sol.converged,
            "newton_per_level": [r["newton_iterations"] for r in sol.per_level],
            "linear_per_level": [r["linear_iterations"] for r in sol.per_level],
            "time_per_level": [round(r["wall_time_s"], 3) for r in sol.per_level],
            "newton": sol.newton_iterations, "linear": sol.linear_iterations,
            "wall_time_s": round(sol.wall_time_s, 3), "energy_error": sol.energy_error,
            "reason": sol.reason}


def main(argv):
    quiet_jit_logging()
    J = int(argv[0]) if argv else 4
    cfuns = argv[1:] or ["min", "fb"]
    warm = scenes.disk(h=0.3, levels=1)
    solve(warm, newton="adaptive")          # JIT-compile every form off the clock
    problem = scenes.disk(h=0.2, levels=J)
    for cfun in cfuns:
        for method in METHODS:
            for nested in (True, False):
                print(json.dumps(run(problem, cfun, method, nested)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
