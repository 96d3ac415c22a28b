"""Benchmark: exact, inexact and adaptive inexact semismooth Newton (DESIGN §8) on the disk.

The disk scene (DESIGN §9) on gmsh meshes with about as many cells as the paper's (gmsh h
calibrated once: 2026, 4088, 7884, 16781, 20900, 27260, 34796 cells for 2048 … 34592) and a
larger one (68857 cells; at 136599 cells inexact Newton alone takes ~10 minutes), no
hierarchy (J = 0, so the adaptive method stops on the ν-extra-iterations flux), Newton-min,
full 3N system, GMRES(30) + ILU(0), ν = 10, γ_lin = γ_alg = 0.3, at most 500 Newton steps
(inexact Newton needs more than the default 100 on the finer meshes; the paper's needed up
to 174). For each mesh and variant: Newton steps, total GMRES steps, wall time (`solve`'s:
discretisation and method; for adaptive the estimators' set-up and evaluations count, since
the method uses them, and the set-up is also shown apart), final energy error and
effectivity η/|||u - u_h||| (η at the final iterate where it is a guaranteed bound; the last
inexact iterate has no later iterate for the ν-flux, so its η is missing unless its residual
is at round-off). Then the table beside the paper's figures (DESIGN §8) with the ratio
adaptive/exact of the GMRES steps.

Usage: `.venv/bin/python benchmarks/bench_newton.py [number of meshes, default all 8]`.
"""

import sys
import time

from membranes import scenes, solve
from membranes.cli import quiet_jit_logging

# paper's element count -> gmsh h of the disk mesh with about that many cells
MESHES = [(2048, 0.0605), (4064, 0.0427), (7840, 0.0306), (16832, 0.0209), (20928, 0.0187),
          (27328, 0.0164), (34592, 0.0145), (None, 0.0103)]
VARIANTS = ("exact", "inexact", "adaptive")
# DESIGN §8: (Newton steps, total GMRES steps) of exact, inexact, adaptive
PAPER = {2048: ((8, 330), (16, 160), (7, 80)), 4064: ((12, 585), (27, 270), (11, 120)),
         7840: ((15, 930), (46, 460), (14, 180)), 16832: ((19, 1485), (76, 760), (18, 340)),
         20928: ((22, 1920), (86, 860), (21, 410)), 27328: ((25, 2460), (174, 1740), (23, 490)),
         34592: ((28, 2985), (166, 1660), (27, 670))}


def run(problem, newton):
    """The figures of one solve."""
    options = {"gamma_lin": 0.3, "gamma_alg": 0.3} if newton == "adaptive" else {}
    sol = solve(problem, newton=newton, cfun="min", system="full", nu=10, max_newton=500,
                **options)
    s = sol.summary()
    return {"converged": sol.converged, "newton": sol.newton_iterations,
            "gmres": sol.linear_iterations, "wall": sol.wall_time_s,
            "setup": s["estimator_setup_s"] if newton == "adaptive" else None,
            "error": sol.energy_error, "effectivity": s["effectivity"],
            "cells": s["n_cells"]}


def _fmt(value, spec):
    return "—" if value is None else format(value, spec)


def table(results):
    """Markdown table of [(paper's cell count or None, {variant: figures})]: ours beside the
    paper's, per mesh and variant."""
    lines = ["| cells (paper) | variant | Newton (paper) | GMRES (paper) | adaptive/exact GMRES "
             "(paper) | wall time s | of which estimator set-up s | energy error | "
             "effectivity |", "|" + "---|" * 9]
    for paper_cells, by_variant in results:
        exact = by_variant["exact"]["gmres"]
        paper = PAPER.get(paper_cells, ((None, None),) * 3)
        for v, (paper_newton, paper_gmres) in zip(VARIANTS, paper):
            r = by_variant[v]
            ratio = ""
            if v == "adaptive":
                ratio = f"{r['gmres'] / exact:.2f}"
                if paper_gmres is not None:
                    ratio += f" ({paper_gmres / paper[0][1]:.2f})"
            flag = "" if r["converged"] else " (not converged)"
            lines.append(
                f"| {r['cells']} ({_fmt(paper_cells, 'd')}) | {v}{flag} | {r['newton']} "
                f"({_fmt(paper_newton, 'd')}) | {r['gmres']} ({_fmt(paper_gmres, 'd')}) | "
                f"{ratio} | {r['wall']:.2f} | "
                f"{_fmt(r['setup'], '.2f')} | {r['error']:.4e} | "
                f"{_fmt(r['effectivity'], '.3f')} |")
    return "\n".join(lines)


def main(count=len(MESHES)):
    quiet_jit_logging()
    for v in VARIANTS:                     # JIT-compile every form outside the clock
        run(scenes.disk(h=0.3), v)
    start, results = time.perf_counter(), []
    for paper_cells, h in MESHES[:count]:
        problem = scenes.disk(h=h)
        results.append((paper_cells, {}))
        for v in VARIANTS:
            r = results[-1][1][v] = run(problem, v)
            flag = "" if r["converged"] else " (NOT converged)"
            print(f"h = {h}: {r['cells']} cells, {v:8s}{flag}: {r['newton']:3d} Newton, "
                  f"{r['gmres']:5d} GMRES, {r['wall']:7.2f} s, energy error {r['error']:.4e}, "
                  f"effectivity {_fmt(r['effectivity'], '.3f')}", flush=True)
    print(f"\n(all solves: {time.perf_counter() - start:.0f} s)\n")
    print(table(results))


if __name__ == "__main__":
    main(*map(int, sys.argv[1:]))
