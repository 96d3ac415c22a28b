"""Benchmark (issue 6.3): the set-up of the estimators (flux equilibration, DESIGN §5) alone,
time and memory, on the disk scene with a mesh hierarchy (translated patch classes) and, with
`--unstructured`, on a plain gmsh mesh (every patch solved on its own).

For each J (default 4 5) a fresh process builds `scenes.disk(h=0.2, levels=J)` (T_J has about
2.7e4, 1.1e5, 4.4e5 vertices for J = 4, 5, 6), discretises it, compiles every form off the
clock on a small mesh, then measures `Estimators(disc)`: wall time, the bytes the object keeps
(numpy arrays and scipy matrices reachable from its attributes, `bench_multilevel.kept_bytes`),
the tracemalloc peak of the set-up above what was allocated before it, and the process's peak
resident memory (getrusage; includes the mesh hierarchy and the discretisation).

Usage: `.venv/bin/python benchmarks/bench_equilibration.py [--tree DIR] [--unstructured H]
[J ...]`; `--tree DIR` measures the `membranes` package of another checkout (for before/after
comparisons in the same conditions).
"""

import json
import os
import subprocess
import sys
import time
import tracemalloc

HERE = os.path.dirname(os.path.abspath(__file__))


def one(spec):
    import numpy as np
    sys.path.insert(0, HERE)
    from bench_multilevel import kept_bytes, rss_gib
    from threadpoolctl import threadpool_limits

    from membranes import scenes
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from membranes.estimators import Estimators
    quiet_jit_logging()
    warm = discretise(scenes.disk(h=0.3, levels=1))   # JIT-compile every form off the clock
    Estimators(warm).evaluate(np.ones(3 * warm.n))
    del warm
    kind, value = spec
    problem = scenes.disk(h=0.2, levels=value) if kind == "J" else scenes.disk(h=value)
    disc = discretise(problem)
    out = {kind: value, "vertices": int(disc.n), "rss_before_gib": rss_gib()}
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    with threadpool_limits(limits=1, user_api="blas"):     # as the driver sets estimators up
        t, c = time.perf_counter(), time.process_time()
        est = Estimators(disc)
        out["setup_s"] = time.perf_counter() - t
        out["setup_cpu_s"] = time.process_time() - c
    out["setup_peak_mb"] = (tracemalloc.get_traced_memory()[1] - base) / 2 ** 20
    tracemalloc.stop()
    seen = set()
    kept_bytes(disc, seen)                   # the discretisation's own arrays are not counted
    kept = kept_bytes(est, seen)
    out["kept_mb"] = kept / 2 ** 20
    out["kept_b_per_vertex"] = kept / disc.n
    out["rss_peak_gib"] = rss_gib()
    return out


def main(args):
    tree = os.path.dirname(HERE)
    if args[:1] == ["--tree"]:
        tree, args = os.path.abspath(args[1]), args[2:]
    if args[:1] == ["--one"]:
        spec = (args[1], float(args[2]) if args[1] == "h" else int(args[2]))
        print(json.dumps(one(spec)))
        return
    specs = []
    while args:
        if args[0] == "--unstructured":
            specs.append(("h", args[1]))
            args = args[2:]
        else:
            specs.append(("J", args[0]))
            args = args[1:]
    env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
    print(f"tree: {tree}")
    print("| mesh | vertices | set-up s | set-up CPU s | kept MB | kept B/vertex "
          "| set-up peak MB | process peak RSS GiB |")
    print("|---" * 8 + "|")
    for kind, value in specs or [("J", "4"), ("J", "5")]:
        p = subprocess.run([sys.executable, __file__, "--one", kind, str(value)],
                           capture_output=True, text=True, env=env, cwd=tree)
        if p.returncode != 0:
            print(f"{kind} = {value} failed:\n{p.stderr[-3000:]}")
            break
        r = json.loads(p.stdout.strip().splitlines()[-1])
        print(f"| {kind} = {value} | {r['vertices']} | {r['setup_s']:.2f} "
              f"| {r['setup_cpu_s']:.2f} | {r['kept_mb']:.0f} "
              f"| {r['kept_b_per_vertex']:.0f} | {r['setup_peak_mb']:.0f} "
              f"| {r['rss_peak_gib']:.2f} |", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
