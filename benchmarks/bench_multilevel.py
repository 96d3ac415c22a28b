"""Benchmark: set-up and one evaluation of the estimators (DESIGN §5, §7) and of the multilevel
algebraic flux (DESIGN §6), time and memory, on the disk scene with a mesh hierarchy.

For each J (default 3 4 5) a fresh process builds `scenes.disk(h=0.2, levels=J)` (T_J has
about 1.1e4, 4.3e4, 1.7e5 ... vertices), discretises it and measures

* Estimators(disc): set-up time, one `evaluate` (median of 3) at a random iterate with a
  random algebraic residual;
* MultilevelFlux(disc, hierarchy): set-up time, one `.sigma(R)` (median of 3);
* the CPU seconds of the MultilevelFlux set-up (process time: on a shared machine less noisy
  than the wall time);
* memory: the bytes the set-up objects keep (numpy arrays and scipy matrices reachable from
  their attributes), the tracemalloc peak of each set-up and evaluation above what was
  allocated before it (numpy reports to tracemalloc; dolfinx's C++ allocations are not
  counted there), and the peak resident memory of the process (getrusage).

Usage: `.venv/bin/python benchmarks/bench_multilevel.py [J ...]` (one process per J).
`--one J` runs a single size in this process and prints one line of JSON.
"""

import json
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc

import numpy as np


def kept_bytes(obj, seen=None):
    """Bytes of the numpy arrays and scipy sparse matrices reachable from obj's attributes
    (lists, tuples, dicts followed; dolfinx objects not)."""
    import scipy.sparse as sp
    seen = set() if seen is None else seen
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        if isinstance(obj.base, np.ndarray):      # a view: count the array it views, once
            while isinstance(obj.base, np.ndarray):
                obj = obj.base
            if id(obj) in seen:
                return 0
            seen.add(id(obj))
        return obj.nbytes
    if sp.issparse(obj):
        return sum(getattr(obj, a).nbytes for a in ("data", "indices", "indptr", "row", "col",
                                                     "offsets") if hasattr(obj, a))
    if isinstance(obj, (list, tuple)):
        return sum(kept_bytes(o, seen) for o in obj)
    if isinstance(obj, dict):
        return sum(kept_bytes(o, seen) for o in obj.values())
    mod = type(obj).__module__ or ""
    if mod.startswith("membranes") and hasattr(obj, "__dict__"):
        return sum(kept_bytes(o, seen) for o in vars(obj).values())
    return 0


def rss_gib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


CPU = {}


def timed(fn, *args, **kwargs):
    """(result, seconds, tracemalloc peak above the start in bytes); the process's CPU seconds
    (less sensitive to a shared machine's load than wall time) go to CPU[fn]."""
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    c = time.process_time()
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    dt = time.perf_counter() - t
    CPU[fn] = time.process_time() - c
    return out, dt, tracemalloc.get_traced_memory()[1] - base


def one(J, repeat=3):
    from membranes import scenes
    from membranes.algebraic_flux import MultilevelFlux
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from membranes.estimators import Estimators
    quiet_jit_logging()
    warm = discretise(scenes.disk(h=0.3, levels=1))   # JIT-compile every form off the clock
    Estimators(warm).evaluate(np.ones(3 * warm.n))
    MultilevelFlux(warm, warm.problem.hierarchy).sigma(np.ones(3 * warm.n))
    del warm
    t = time.perf_counter()
    problem = scenes.disk(h=0.2, levels=J)
    disc = discretise(problem)
    t_disc = time.perf_counter() - t
    n = disc.n
    rng = np.random.default_rng(1)
    X = rng.standard_normal(3 * n) * 0.05
    R = rng.standard_normal(3 * n) * 1e-3
    for k in range(3):
        R[k * n + disc.boundary] = 0.0
    out = {"J": J, "vertices": int(n),
           "cells": int(problem.mesh.topology.index_map(2).size_local),
           "discretise_s": t_disc, "rss_before_gib": rss_gib()}
    tracemalloc.start()
    est, out["est_setup_s"], out["est_setup_peak"] = timed(Estimators, disc)
    out["est_kept"] = kept_bytes(est)
    ml, out["ml_setup_s"], out["ml_setup_peak"] = timed(MultilevelFlux, disc,
                                                        problem.hierarchy)
    out["ml_setup_cpu_s"] = CPU[MultilevelFlux]
    out["ml_kept"] = kept_bytes(ml)
    times, peaks = [], []
    for _ in range(repeat):
        sigma, dt, peak = timed(ml.sigma, R)
        times.append(dt)
        peaks.append(peak)
    out["ml_sigma_s"], out["ml_sigma_peak"] = statistics.median(times), max(peaks)
    times, peaks = [], []
    for _ in range(repeat):
        res, dt, peak = timed(est.evaluate, X, R, 1e-3, sigma_alg=sigma)
        times.append(dt)
        peaks.append(peak)
    out["est_eval_s"], out["est_eval_peak"] = statistics.median(times), max(peaks)
    out["eta"] = res["eta"]
    tracemalloc.stop()
    out["rss_peak_gib"] = rss_gib()
    return out


MB = 2 ** 20


def table(rows):
    print("| J | vertices | est. set-up s | est. kept MB | est. set-up peak MB "
          "| evaluate s | ML set-up s | ML set-up CPU s | ML kept MB | ML set-up peak MB "
          "| σ_alg s | process peak RSS GiB |")
    print("|---" * 12 + "|")
    for r in rows:
        print(f"| {r['J']} | {r['vertices']} | {r['est_setup_s']:.2f} | {r['est_kept'] / MB:.0f} "
              f"| {r['est_setup_peak'] / MB:.0f} | {r['est_eval_s']:.3f} "
              f"| {r['ml_setup_s']:.2f} | {r.get('ml_setup_cpu_s', float('nan')):.2f} "
              f"| {r['ml_kept'] / MB:.0f} "
              f"| {r['ml_setup_peak'] / MB:.0f} | {r['ml_sigma_s']:.3f} "
              f"| {r['rss_peak_gib']:.2f} |")
    if rows:
        r = rows[-1]
        s = 1e6 / r["vertices"]
        print(f"\nlinear extrapolation from J = {r['J']} to 1e6 vertices: kept "
              f"{(r['est_kept'] + r['ml_kept']) * s / 2 ** 30:.2f} GiB (estimators + multilevel), "
              f"set-up peaks {r['est_setup_peak'] * s / 2 ** 30:.2f} / "
              f"{r['ml_setup_peak'] * s / 2 ** 30:.2f} GiB, set-up "
              f"{(r['est_setup_s'] + r['ml_setup_s']) * s:.0f} s, evaluate + σ_alg "
              f"{(r['est_eval_s'] + r['ml_sigma_s']) * s:.2f} s")


def main(args):
    if args and args[0] == "--one":
        print(json.dumps(one(int(args[1]))))
        return
    rows = []
    for J in (int(a) for a in (args or ["3", "4", "5"])):
        p = subprocess.run([sys.executable, __file__, "--one", str(J)], capture_output=True,
                           text=True)
        if p.returncode != 0:
            print(f"J = {J} failed:\n{p.stderr[-3000:]}")
            break
        rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    table(rows)


if __name__ == "__main__":
    main(sys.argv[1:])
