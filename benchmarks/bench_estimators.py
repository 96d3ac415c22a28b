"""Benchmark: one full estimator evaluation against one exact (MUMPS) Newton step.

Disk scene (DESIGN §9) on a gmsh mesh of about 100,000 vertices (default h = 0.0061). In one
run and one process it measures

* the set-up of the estimators (patch problems solved once per mesh, DESIGN §5), done before
  Newton as a solve does it,
* one exact semismooth Newton step: linearisation, assembly of the full 3N system and its
  MUMPS solve, from the paper's initial guess,
* one full estimator evaluation (σ_disc for both membranes, every estimator of DESIGN §7, the
  bound) at the resulting iterate, median of 5,

and prints their ratio and the peak resident memory of the process. Target (issue 3): ratio
≤ 0.25 and peak memory ≤ 2 GiB. Usage: `.venv/bin/python benchmarks/bench_estimators.py [h]`.
"""

import resource
import statistics
import sys
import time

import numpy as np

from membranes import newton_system as ns
from membranes import scenes
from membranes.cli import quiet_jit_logging
from membranes.discretisation import discretise
from membranes.estimators import Estimators
from membranes.linear_solve import solve_direct


def peak_memory_gib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def main(h=0.0061):
    quiet_jit_logging()
    warm = scenes.disk(h=0.2)                       # JIT-compile every form outside the clock
    Estimators(discretise(warm)).evaluate(np.ones(3 * discretise(warm).n))
    t = time.perf_counter()
    problem = scenes.disk(h=h)
    t_mesh = time.perf_counter() - t
    t = time.perf_counter()
    disc = discretise(problem)
    rows = ns.linear_rows(disc)
    t_disc = time.perf_counter() - t
    print(f"disk h = {h}: {disc.n} vertices, "
          f"{problem.mesh.topology.index_map(2).size_local} cells "
          f"(mesh {t_mesh:.1f} s, discretisation {t_disc:.1f} s); "
          f"peak memory so far {peak_memory_gib():.2f} GiB", flush=True)

    t = time.perf_counter()
    est = Estimators(disc)
    t_setup = time.perf_counter() - t
    print(f"estimator set-up (once per mesh): {t_setup:.2f} s; "
          f"peak memory so far {peak_memory_gib():.2f} GiB", flush=True)
    X0 = ns.initial_guess(rows, problem.g)
    t = time.perf_counter()
    alpha, beta, B3 = ns.complementarity_rows(rows, "min", X0)
    A, B = ns.full_system(rows, alpha, beta, B3)
    X1, _ = solve_direct(A, B)
    t_newton = time.perf_counter() - t
    R = B - A @ X1
    print(f"one exact Newton step (full 3N system, MUMPS): {t_newton:.3f} s; "
          f"peak memory so far {peak_memory_gib():.2f} GiB", flush=True)

    times, result = [], None
    alg = float(np.linalg.norm(R) / np.linalg.norm(B))
    for _ in range(5):
        t = time.perf_counter()
        result = est.evaluate(X1, R, alg_residual=alg)
        times.append(time.perf_counter() - t)
    t_eval = statistics.median(times)
    print(f"one estimator evaluation: {t_eval:.3f} s (median of 5; eta = {result['eta']:.4e})")
    ratio = t_eval / t_newton
    peak = peak_memory_gib()
    print(f"ratio evaluation / Newton step = {ratio:.3f} (target <= 0.25: "
          f"{'met' if ratio <= 0.25 else 'NOT met'})")
    print(f"peak memory = {peak:.2f} GiB (target <= 2 GiB: {'met' if peak <= 2 else 'NOT met'})")


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:]))
