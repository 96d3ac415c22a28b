"""Benchmark (issue 6, round 3): the set-up of the discretisation flux alone,
`FluxEquilibration(disc)` (DESIGN §5), on the finest level of the disk scene, with the time
of its pieces, old tree against new.

Each measurement is a fresh process: it builds `scenes.disk(h=H0, levels=J)` and discretises
it, sets up a flux on a small mesh first (forms compiled and numba kernels loaded off the
clock), then times `FluxEquilibration(disc)` with BLAS on one thread (as the driver sets the
estimators up), wrapping the set-up's functions to add up their wall times (nested pieces
are counted in their callers too). With `--tree OLD` the two trees are measured alternately
`--repeat` times each (the machine is shared: compare medians taken in the same conditions),
and the ratio new / old of the median totals is printed, of wall and of CPU time (the
set-up runs on one thread: its CPU time is less sensitive to other processes' load); σ of both is compared on fixed
random data (bitwise or the relative difference).

Usage: `.venv/bin/python benchmarks/bench_flux_setup.py [--tree OLD] [--repeat N] J H0`
(J = 6, H0 = 0.132: 9.3e5 vertices; J = 5, H0 = 0.2: 1.1e5).
"""

import functools
import inspect
import json
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
PIECES = [("membranes.equilibration", None, ["vertex_patches", "translation_classes",
                                             "load_moments"]),
          ("membranes.equilibration", "FluxEquilibration",
           ["_classes", "_translates", "_class_load", "_solve_patches", "_add_operators"]),
          ("membranes.equilibration", "PatchSpace", ["__init__"]),
          ("membranes.algebraic_flux", None, ["_bucket_scatter"])]


def _timed(owner, name, times):
    f = getattr(owner, name, None)
    if f is None:
        return
    label = name if name != "__init__" else "PatchSpace"
    if inspect.isgeneratorfunction(f):
        @functools.wraps(f)
        def g(*a, **k):
            it = f(*a, **k)
            while True:
                t = time.perf_counter()
                try:
                    x = next(it)
                except StopIteration:
                    times[label] = times.get(label, 0.0) + time.perf_counter() - t
                    return
                times[label] = times.get(label, 0.0) + time.perf_counter() - t
                yield x
    else:
        @functools.wraps(f)
        def g(*a, **k):
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                times[label] = times.get(label, 0.0) + time.perf_counter() - t
    setattr(owner, name, g)


def one(J, h0, out):
    import importlib
    import numpy as np
    from membranes import scenes
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from threadpoolctl import threadpool_limits
    import membranes.equilibration as eq
    quiet_jit_logging()
    eq.FluxEquilibration(discretise(scenes.disk(h=0.3, levels=2)))
    disc = discretise(scenes.disk(h=h0, levels=J))
    times = {}
    for module, cls, names in PIECES:
        owner = importlib.import_module(module)
        owner = getattr(owner, cls) if cls else owner
        for name in names:
            _timed(owner, name, times)
    with threadpool_limits(limits=1, user_api="blas"):
        t, c = time.perf_counter(), time.process_time()
        flux = eq.FluxEquilibration(disc)
        total, cpu = time.perf_counter() - t, time.process_time() - c
    rng = np.random.default_rng(1)
    u, lam, R = rng.standard_normal((3, disc.n))
    np.save(out, np.array([flux.sigma(a, u, lam, R) for a in (1, 2)]))
    return {"vertices": int(disc.n), "total": total, "cpu": cpu, "pieces": times}


def main(args):
    old, repeat = None, 1
    while args and args[0].startswith("--"):
        if args[0] == "--tree":
            old, args = os.path.abspath(args[1]), args[2:]
        elif args[0] == "--repeat":
            repeat, args = int(args[1]), args[2:]
        elif args[0] == "--one":
            print(json.dumps(one(int(args[1]), float(args[2]), args[3])))
            return
    J, h0 = int(args[0]), float(args[1])
    trees = {"new": os.path.dirname(HERE)}
    if old:
        trees["old"] = old
    runs = {k: [] for k in trees}
    for r in range(repeat):
        for name, tree in trees.items():
            env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
            out = f"/tmp/bench_flux_setup_{name}_{os.getpid()}.npy"
            p = subprocess.run([sys.executable, __file__, "--one", str(J), str(h0), out],
                               capture_output=True, text=True, env=env, cwd=tree)
            if p.returncode != 0:
                print(f"{name} failed:\n{p.stderr[-3000:]}")
                return
            res = json.loads(p.stdout.strip().splitlines()[-1])
            runs[name].append(res)
            print(f"{name} ({tree}), J = {J}, h0 = {h0}, {res['vertices']} vertices: "
                  f"FluxEquilibration {res['total']:.2f} s (CPU {res['cpu']:.2f} s) | "
                  + ", ".join(
                      f"{k} {v:.2f}" for k, v in sorted(res["pieces"].items(),
                                                        key=lambda kv: -kv[1])), flush=True)
    if old:
        import numpy as np
        a, b = (np.load(f"/tmp/bench_flux_setup_{n}_{os.getpid()}.npy") for n in ("new", "old"))
        same = "bitwise" if np.array_equal(a, b) else \
            f"relative difference {np.abs(a - b).max() / np.abs(b).max():.1e}"
        med = {k: statistics.median(r["total"] for r in v) for k, v in runs.items()}
        cpu = {k: statistics.median(r["cpu"] for r in v) for k, v in runs.items()}
        print(f"median set-up: new {med['new']:.2f} s, old {med['old']:.2f} s, "
              f"new / old {med['new'] / med['old']:.2f} (CPU: new {cpu['new']:.2f} s, old "
              f"{cpu['old']:.2f} s, {cpu['new'] / cpu['old']:.2f}); sigma {same}")


if __name__ == "__main__":
    main(sys.argv[1:])
