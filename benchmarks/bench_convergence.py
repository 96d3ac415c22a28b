"""The disk with curved refinement: energy-error order and the guaranteed bound (issue 30).

    python benchmarks/bench_convergence.py [--levels 5] [--eff-levels 4]

Prints (1) the energy error of exact Newton on the disk, h0 = 0.2, J = 1 … --levels, and the
observed order log2(e_{J-1}/e_J) (h halves exactly under uniform refinement); (2) for J = 0 …
--eff-levels, every Newton variant and C-function with the default solver: iterations, the
energy error, η, the effectivity η/error at convergence and the smallest η/error over all
certified iterates of the run (η ≥ error is the guarantee of §7).
"""

import argparse
import math

from membranes import scenes, solve
from membranes.app.driver import MEMORY_METHOD
from membranes.model.checks import check_request


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--levels", type=int, default=5, metavar="J",
                   help="(1) exact Newton on J = 1 ... J (default 5)")
    p.add_argument("--eff-levels", type=int, default=4, metavar="J",
                   help="(2) every variant and C-function on J = 0 ... J (default 4)")
    p.add_argument("--h0", type=float, default=0.2, help="gmsh size of T_0 (default 0.2)")
    a = p.parse_args()
    if a.levels < 0 or a.eff_levels < 0:
        p.error("--levels and --eff-levels must be non-negative integers")
    if not (math.isfinite(a.h0) and a.h0 > 0):
        p.error(f"--h0 must be a positive number, got {a.h0}")
    try:     # the largest mesh asked for: refused at once if beyond memory (model.checks)
        check_request(a.h0, max(a.levels, a.eff_levels), "disk", estimators=True,
                      processes=1, replicated=False, **MEMORY_METHOD["amg"])
    except ValueError as e:
        p.error(str(e))
    print("J  vertices  Newton  Krylov  energy_error  order")
    last = None
    for J in range(1, a.levels + 1):
        s = solve(scenes.disk(h=a.h0, levels=J), newton="exact", estimators=False)
        order = math.log2(last / s.energy_error) if last else float("nan")
        last = s.energy_error
        print(f"{J}  {s.disc.n_global}  {s.newton_iterations}  {s.linear_iterations}  "
              f"{s.energy_error:.4e}  {order:.3f}", flush=True)
    print("J  cfun  newton  converged  Newton  Krylov  error  eta  eta/error  certified  "
          "min_eta/error")
    for J in range(a.eff_levels + 1):
        problem = scenes.disk(h=a.h0, levels=J)
        for cfun in ("min", "fb"):
            for newton in ("exact", "inexact", "adaptive"):
                s = solve(problem, newton=newton, cfun=cfun, errors="iterates")
                cert = [r for r in s.history
                        if r.get("bound") and r.get("energy_error") is not None]
                worst = min(r["eta"] / r["energy_error"] for r in cert)
                eta = s.estimates["eta"]
                print(f"{J}  {cfun}  {newton}  {s.converged}  {s.newton_iterations}  "
                      f"{s.linear_iterations}  {s.energy_error:.4e}  {eta:.4e}  "
                      f"{eta / s.energy_error:.3f}  {len(cert)}  {worst:.3f}", flush=True)


if __name__ == "__main__":
    main()
