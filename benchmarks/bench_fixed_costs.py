"""Benchmark (issue 6): the fixed costs a fresh process pays in a serial solve.

The method of bench_scaling (`solve(newton="adaptive", cfun="min", system="eliminated",
pc_type vertex_amg, alg_flux nu)`, disk scene, H0 = 0.2 refined J times) in fresh processes;
in each, a first solve and then a second one on a NEW problem of the same size (a problem
built again: its meshes' connectivity is built again, as in the first solve, so that the
difference of the two is what the process, not the problem, pays the first time).

Printed per process, then the minimum over the processes: the wall time of each solve
(sol.wall_time_s, which runs from the call of solve) and of its level 0, and for the first
solve the parts of the first-use cost that can be told apart:

* kernels: the first call of each compiled kernel with its argument types, where its code is
  found (membranes.compiled: an extension module imported, or numba's import, CPU target and
  typing context the first time and its disk cache), and the first of them apart; whether
  the process imported numba at all;
* JIT look-ups: dolfinx.jit.ffcx_jit calls (forms, expressions, elements) and their time
  (each a UFL signature and a look-up in the FFCx disk cache).

Usage: `.venv/bin/python benchmarks/bench_fixed_costs.py [J[:H0]] [processes]` (default 5 4).
"""

import json
import subprocess
import sys
import time

from bench_scaling import _size  # 'J' or 'J:H0' (H0 = 0.2), as bench_scaling reads sizes

OPTIONS = {"newton": "adaptive", "cfun": "min", "system": "eliminated",
           "petsc_options": {"pc_type": "vertex_amg"}, "alg_flux": "nu"}


def child(size):
    """Two solves in this process; prints one JSON line."""
    levels, h0 = _size(size)
    from dolfinx import jit

    from membranes import compiled, scenes, solve
    from membranes.cli import quiet_jit_logging
    quiet_jit_logging()
    parts = {"kernels": 0.0, "n_kernels": 0, "first_kernel": None, "jit": 0.0, "n_jit": 0}
    entry = compiled._entry

    def timed_entry(f, key, args):    # a kernel's first call with these types: its code
        t = time.perf_counter()
        out = entry(f, key, args)
        dt = time.perf_counter() - t
        parts["kernels"] += dt
        parts["n_kernels"] += 1
        if parts["first_kernel"] is None:
            parts["first_kernel"] = dt
        return out

    compiled._entry = timed_entry
    ffcx_jit = jit.ffcx_jit

    def timed_jit(*args, **kwargs):
        t = time.perf_counter()
        out = ffcx_jit(*args, **kwargs)
        parts["jit"] += time.perf_counter() - t
        parts["n_jit"] += 1
        return out

    jit.ffcx_jit = timed_jit
    out = {}
    for run in ("fresh", "warm"):
        problem = scenes.disk(h=h0, levels=levels)
        if run == "warm":
            first = dict(parts)
        sol = solve(problem, **OPTIONS)
        out[run] = {"wall": sol.wall_time_s, "level0": sol.per_level[0]["wall_time_s"],
                    "newton": sol.newton_iterations, "linear": sol.linear_iterations,
                    "eta": sol.summary()["eta"], "energy_error": sol.energy_error}
    out["parts"] = first
    out["numba_imported"] = "numba" in sys.modules
    out["parts_warm"] = {k: parts[k] - first[k] for k in ("jit", "n_jit")}
    print(json.dumps(out))


def main(argv):
    size = argv[0] if argv else "5"
    processes = int(argv[1]) if len(argv) > 1 else 4
    rows = []
    for _ in range(processes):
        r = subprocess.run([sys.executable, __file__, "--child", size], capture_output=True,
                           text=True, check=True)
        row = json.loads(r.stdout.strip().splitlines()[-1])
        rows.append(row)
        p, f, w = row["parts"], row["fresh"], row["warm"]
        print(f"fresh {f['wall']:.3f} s (level 0 {f['level0']:.3f})  second solve, new problem "
              f"{w['wall']:.3f} s (level 0 {w['level0']:.3f})  |  {p['n_kernels']} kernels "
              f"{p['kernels']:.3f} s (the first {p['first_kernel']:.3f} s), numba imported: "
              f"{row['numba_imported']}, "
              f"{p['n_jit']} JIT look-ups {p['jit']:.3f} s (second solve: "
              f"{row['parts_warm']['n_jit']}, {row['parts_warm']['jit']:.3f} s)  |  "
              f"{f['newton']} Newton / {f['linear']} GMRES, eta {f['eta']:.6e}, "
              f"error {f['energy_error']:.6e}", flush=True)
    fresh = min(r["fresh"]["wall"] for r in rows)
    warm = min(r["warm"]["wall"] for r in rows)
    print(f"min over {processes} processes: fresh {fresh:.3f} s, second solve {warm:.3f} s, "
          f"first-use cost {fresh - warm:.3f} s; kernels "
          f"{min(r['parts']['kernels'] for r in rows):.3f} s, JIT look-ups "
          f"{min(r['parts']['jit'] for r in rows):.3f} s (some outside the clock: the energy "
          f"error's)")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        child(sys.argv[2])
    else:
        main(sys.argv[1:])
