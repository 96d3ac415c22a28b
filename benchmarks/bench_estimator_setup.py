"""Benchmark (issue 6, round 4): the estimators' set-up per level, `Estimators(disc)` (DESIGN
§5, §7: the flux set-up, the data oscillation, the cell norms' tables), on the finest level of
the disk scene, with the time of its pieces, old tree against new.

It replaces bench_flux_setup.py (the flux set-up alone, `FluxEquilibration`, is one of the
pieces timed here). Each measurement is a fresh process that builds
`scenes.disk(h=H0, levels=J)`, discretises it, sets up the estimators on a small mesh first
(forms and kernels loaded off the clock), then times `Estimators(disc)` with BLAS on one
thread; with `--tree OLD` the two trees are measured alternately `--repeat` times each and the
medians compared (wall and CPU time). The results are compared between the trees: σ_disc of
fixed random data, η_osc per cell, and η and η_K at a random iterate (bitwise, or the largest
difference relative to the largest entry).

With `--levels R`, each tree's process instead sets up the estimators on every level
j = 1 .. J of the scene (as the nested iteration does) R times, level after level, and prints
the least time of each level and their sum (warm: the later rounds reuse the memory of the
earlier ones, which a fresh process's first round pays for).

Usage: `.venv/bin/python benchmarks/bench_estimator_setup.py [--tree OLD] [--repeat N]
[--levels R] J H0` (J = 6, H0 = 0.132: 9.3e5 vertices; J = 5, H0 = 0.2: 1.1e5).
"""

import functools
import importlib
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
           ["__init__", "_classes", "_translates", "_class_load", "_solve_patches"]),
          ("membranes.equilibration", "PatchSpace", ["__init__"]),
          ("membranes.estimators", None, ["oscillation"]),
          ("membranes.estimators", "CellFluxNorms", ["__init__"])]


def _timed(owner, name, label, times):
    """Wrap owner.name to add its wall times to times[label] (nested pieces are counted in
    their callers too)."""
    f = getattr(owner, name, None)
    if f is None:
        return

    @functools.wraps(f)
    def g(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            times[label] = times.get(label, 0.0) + time.perf_counter() - t
    setattr(owner, name, g)


def one(J, h0, out):
    import numpy as np
    from threadpoolctl import threadpool_limits

    from membranes import scenes
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from membranes.estimators import Estimators
    quiet_jit_logging()
    Estimators(discretise(scenes.disk(h=0.3, levels=2)))
    disc = discretise(scenes.disk(h=h0, levels=J))
    times = {}
    for module, cls, names in PIECES:
        owner = importlib.import_module(module)
        owner = getattr(owner, cls) if cls else owner
        for name in names:
            _timed(owner, name, cls if name == "__init__" else name, times)
    with threadpool_limits(limits=1, user_api="blas"):
        t, c = time.perf_counter(), time.process_time()
        est = Estimators(disc)
        total, cpu = time.perf_counter() - t, time.process_time() - c
    rng = np.random.default_rng(1)
    n = disc.n
    u, lam, R = rng.standard_normal((3, n)) * 1e-2
    sigma = [est.flux.sigma(a, u, lam, R) for a in (1, 2)]
    e = est.evaluate(np.concatenate([u, 0.5 * u, lam]))
    np.savez(out, sigma=np.array(sigma), osc=est.osc, eta=e["eta"], eta_K=e["eta_K"])
    return {"vertices": int(n), "total": total, "cpu": cpu, "pieces": times}


def levels(J, h0, rounds):
    """The least set-up time of `Estimators` on each level 1 .. J over `rounds` rounds."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from membranes import scenes
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from membranes.estimators import Estimators
    quiet_jit_logging()
    Estimators(discretise(scenes.disk(h=0.3, levels=2)))
    discs = [discretise(scenes.disk(h=h0, levels=j)) for j in range(1, J + 1)]
    best = [np.inf] * J
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(rounds):
            for j, disc in enumerate(discs):
                t = time.perf_counter()
                Estimators(disc)
                best[j] = min(best[j], time.perf_counter() - t)
    return {"vertices": [int(d.n) for d in discs], "levels": best}


def main(args):
    old, repeat, rounds = None, 1, 0
    while args and args[0].startswith("--"):
        if args[0] == "--tree":
            old, args = os.path.abspath(args[1]), args[2:]
        elif args[0] == "--repeat":
            repeat, args = int(args[1]), args[2:]
        elif args[0] == "--levels":
            rounds, args = int(args[1]), args[2:]
        elif args[0] == "--one":
            print(json.dumps(one(int(args[1]), float(args[2]), args[3])))
            return
        elif args[0] == "--one-levels":
            print(json.dumps(levels(int(args[1]), float(args[2]), int(args[3]))))
            return
    J, h0 = int(args[0]), float(args[1])
    trees = {"new": os.path.dirname(HERE)}
    if old:
        trees["old"] = old
    if rounds:
        per = {k: [] for k in trees}
        for r in range(repeat):
            for name, tree in trees.items():
                env = dict(os.environ,
                           PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
                p = subprocess.run([sys.executable, __file__, "--one-levels", str(J), str(h0),
                                    str(rounds)], capture_output=True, text=True, env=env,
                                   cwd=tree)
                if p.returncode != 0:
                    print(f"{name} failed:\n{p.stderr[-3000:]}")
                    return
                res = json.loads(p.stdout.strip().splitlines()[-1])
                per[name].append(res["levels"])
                print(f"{name} ({tree}), J = {J}, h0 = {h0}, least of {rounds} per level: "
                      + ", ".join(f"{v} vertices {t:.3f} s" for v, t in
                                  zip(res["vertices"], res["levels"]))
                      + f" | sum {sum(res['levels']):.3f} s", flush=True)
        if old:
            best = {k: [min(c) for c in zip(*v)] for k, v in per.items()}
            print("least per level, new / old: " + ", ".join(
                f"{a / b:.2f}" for a, b in zip(best["new"], best["old"]))
                + f" | sum new {sum(best['new']):.3f} s, old {sum(best['old']):.3f} s, "
                f"{sum(best['new']) / sum(best['old']):.2f}")
        return
    runs = {k: [] for k in trees}
    for r in range(repeat):
        for name, tree in trees.items():
            env = dict(os.environ, PYTHONPATH=tree + os.pathsep + os.environ.get("PYTHONPATH", ""))
            out = f"/tmp/bench_estimator_setup_{name}_{os.getpid()}.npz"
            p = subprocess.run([sys.executable, __file__, "--one", str(J), str(h0), out],
                               capture_output=True, text=True, env=env, cwd=tree)
            if p.returncode != 0:
                print(f"{name} failed:\n{p.stderr[-3000:]}")
                return
            res = json.loads(p.stdout.strip().splitlines()[-1])
            runs[name].append(res)
            print(f"{name} ({tree}), J = {J}, h0 = {h0}, {res['vertices']} vertices: "
                  f"Estimators set-up {res['total']:.2f} s (CPU {res['cpu']:.2f} s) | "
                  + ", ".join(
                      f"{k} {v:.2f}" for k, v in sorted(res["pieces"].items(),
                                                        key=lambda kv: -kv[1])), flush=True)
    if old:
        import numpy as np
        a, b = (np.load(f"/tmp/bench_estimator_setup_{n}_{os.getpid()}.npz")
                for n in ("new", "old"))
        same = ", ".join(
            f"{k} " + ("bitwise" if np.array_equal(a[k], b[k]) else
                       f"{np.abs(a[k] - b[k]).max() / np.abs(b[k]).max():.1e}")
            for k in ("sigma", "osc", "eta", "eta_K"))
        med = {k: statistics.median(r["total"] for r in v) for k, v in runs.items()}
        cpu = {k: statistics.median(r["cpu"] for r in v) for k, v in runs.items()}
        print(f"median set-up: new {med['new']:.2f} s, old {med['old']:.2f} s, "
              f"new / old {med['new'] / med['old']:.2f} (CPU: new {cpu['new']:.2f} s, old "
              f"{cpu['old']:.2f} s, {cpu['new'] / cpu['old']:.2f}); {same}")


if __name__ == "__main__":
    main(sys.argv[1:])
