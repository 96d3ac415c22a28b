"""Benchmark (issue 6): our adaptive inexact semismooth Newton against PETSc's SNES VI peer,
from about 1e4 to 1e6 vertices, side by side in one run.

Disk scene (DESIGN §9) on the hierarchy of a gmsh mesh of size H0 = 0.2 refined J times
(J = 3, 5, 7: 6.9e3, 1.1e5, 1.7e6 vertices), computed on the finest mesh. For each size, four
fresh processes (so that each peak memory is its own):

* ours: `solve(newton="adaptive", cfun="min", system="eliminated", pc_type vertex_amg,
  alg_flux nu)` with nested iteration where the driver has it (its default on a hierarchy),
  estimators on (the method uses them);
* ours-ml: the same with the multilevel algebraic flux on T_J (`alg_flux multilevel`, the
  driver's default on a hierarchy; its set-up on T_J is the difference);
* ours-2: ours under `mpirun -n 2`: Newton and GMRES on process 0, the estimators on
  process 1, overlapped (membranes.pipeline; the mesh is replicated);
* peer: `vinewtonrsls` on the decoupled problem (DESIGN §10), CG + BoomerAMG
  (membranes.decoupled.AMG), on the same mesh, to its own convergence (rtol 1e-14).

Printed per size: Newton (SNES) iterations, linear iterations (GMRES, CG) and per Newton
step, wall time of the method (discretisation included; ours: estimator set-up and
evaluations included, shown apart), time of the whole process (mesh hierarchy included),
peak resident memory, final energy error; then the ratios the issue asks for: our time /
peer time, energy error ours / peer, the speed-up of 2 processes (and whether they found the
same iterate: largest difference relative to one process), GMRES per Newton step at the
largest size / at the smallest, the growth exponent of the whole-run time in N. With them,
each run's system time and fresh memory (minor page faults) during the method, per process:
where memory is dear at its first write, they tell a slow run from slow code.

Usage: `.venv/bin/python benchmarks/bench_scaling.py [--pairs R] [J[:H0] ...]` (default 3 5 7;
`6:0.132`: J = 6 on a coarse mesh of size 0.132, about 1.0e6 vertices). With `--pairs R`, R - 1
more pairs of runs (ours, then ours-2, each in fresh processes) follow each size's four runs,
and the speed-up of 2 processes is also given pair by pair, with the median: the two runs of a
pair come one right after the other, while the machine's speed drifts (BENCHMARKS.md).
"""

import json
import math
import resource
import subprocess
import sys
import time

H0 = 0.2
DEFAULT_LEVELS = (3, 5, 7)
# our runs and their algebraic flux (DESIGN §6): with vertex_amg, GMRES reaches round-off within
# ν = 10 iterations and the adaptive run does not estimate X^0, so the ν flux is never needed
# (σ_alg = 0 up to the round-off remainder), while the multilevel flux costs its set-up on T_J
# (measured side by side)
OURS = {"ours": "nu", "ours-ml": "multilevel", "ours-2": "nu"}


def _size(arg):
    """'J' or 'J:H0' -> (J, H0)."""
    j, _, h0 = str(arg).partition(":")
    return int(j), float(h0) if h0 else H0


def child(which, size):
    """One measurement in this process; prints one JSON line."""
    levels, h0 = _size(size)
    t0 = time.perf_counter()
    from mpi4py import MPI

    from membranes import scenes
    from membranes.cli import quiet_jit_logging
    quiet_jit_logging()
    problem = scenes.disk(h=h0, levels=levels)
    t_mesh = time.perf_counter() - t0
    n = problem.mesh.topology.index_map(0).size_global
    world = MPI.COMM_WORLD
    before = resource.getrusage(resource.RUSAGE_SELF)
    if which in OURS:
        # the run does not know the exact solution: a scene without one runs the same way.
        # (With it, process 0 of ours-2 sets up the energy error of every level, which the
        # wall time leaves out, while the estimator process goes on: that hid up to 2.8 s of
        # waiting at 9.3e5 vertices.) The final energy error is computed afterwards.
        import dataclasses

        from membranes import solve
        from membranes.discretisation import EnergyError
        sol = solve(dataclasses.replace(problem, exact=None), newton="adaptive", cfun="min",
                    system="eliminated", petsc_options={"pc_type": "vertex_amg"},
                    alg_flux=OURS[which],
                    progress=lambda line: print(line, file=sys.stderr, flush=True),
                    comm=world)
        import numpy as np
        np.save(f"/tmp/bench_scaling_{which}_{size}.npy", sol.X)
        error = None
        if world.rank == 0:
            fine = dataclasses.replace(sol.disc, problem=dataclasses.replace(
                sol.disc.problem, exact=problem.exact))
            error = EnergyError(fine)(sol.X)
        out = {"converged": sol.converged, "newton": sol.newton_iterations,
               "linear": sol.linear_iterations, "time": sol.wall_time_s,
               "estimator_setup": sol.estimator_times[0],
               "estimator_time": sol.estimator_times[1],
               "energy_error": error, "eta": sol.summary()["eta"],
               "per_level": [lvl["newton_iterations"] for lvl in (sol.per_level or [])]}
    else:
        from membranes.report import run_peer
        peer, records = run_peer(problem, lambda line: print(line, file=sys.stderr))
        out = {"converged": peer.converged, "newton": peer.newton_iterations,
               "linear": peer.linear_iterations, "time": peer.wall_time_s,
               "energy_error": records[-1]["energy_error"]}
    # per process: the peak, and the method's system time and fresh pages (minor faults, 4 KiB
    # each): on a virtual machine whose freed memory goes back to the host, a page's first
    # write costs several times more than on memory used a moment before (BENCHMARKS.md,
    # seventh session)
    after = resource.getrusage(resource.RUSAGE_SELF)
    per = world.gather((after.ru_maxrss / 2 ** 20, after.ru_stime - before.ru_stime,
                        (after.ru_minflt - before.ru_minflt) * 4096 / 2 ** 30), root=0)
    if world.rank > 0:
        return
    peaks, sys_s, fresh = zip(*per)
    out.update({"which": which, "levels": size, "vertices": n, "mesh_time": t_mesh,
                "process_time": time.perf_counter() - t0,
                "peak_gib": max(peaks), "peak_total_gib": sum(peaks),
                "sys_s": list(sys_s), "fresh_gib": list(fresh)})
    print(json.dumps(out), flush=True)


def _system_time(r):
    """'sys (fresh)' of a run's processes, '+' between them."""
    return " + ".join(f"{t:.1f} ({g:.1f})" for t, g in zip(r["sys_s"], r["fresh_gib"]))


def measure(which, levels):
    command = [sys.executable, __file__, "--child", which, str(levels)]
    env = None
    if which == "ours-2":
        import os
        env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
        command = ["mpirun", "--allow-run-as-root", "--oversubscribe", "-n", "2"] + command
    proc = subprocess.run(command, capture_output=True, text=True, env=env)
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = proc.stderr.strip().splitlines()[-3:]
        return {"which": which, "levels": levels, "failed": " | ".join(tail)}
    return json.loads(lines[-1])


def main(levels_list, pairs=1):
    # small runs first, not reported: the disk caches of compiled code (dolfinx's forms, the
    # kept kernels of membranes.compiled) are then warm for every measured process, as for any
    # run after the first. J = 3 and each of our variants: a J = 1 run of `ours` alone left out
    # kernels that only meshes with translation classes use, and the multilevel flux's
    ms = [measure(which, "3") for which in ("ours", "ours-ml", "ours-2")]
    if any("failed" in r for r in ms):
        print("warm-up failed:", [r.get("failed") for r in ms])
    results, again = [], {}
    for levels in levels_list:
        for which in ("ours", "ours-ml", "ours-2", "peer"):
            r = measure(which, levels)
            results.append(r)
            print(json.dumps(r), flush=True)
        # further pairs (ours, ours-2) one right after the other: the machine's speed drifts
        # by 15-30 % within minutes (BENCHMARKS.md), a pair's two runs see nearly the same
        for _ in range(pairs - 1):
            pair = [measure(which, levels) for which in ("ours", "ours-2")]
            again.setdefault(levels, []).append(pair)
            print(json.dumps(pair), flush=True)
    print()
    print("| J | vertices | method | Newton (per level) | linear | linear/Newton | method s | "
          "estimators (set-up + evals) s | process s | peak GiB | energy error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        if "failed" in r:
            print(f"| {r['levels']} | | {r['which']} | failed: {r['failed']} |||||||")
            continue
        est = (f"{r['estimator_setup']:.1f} + {r['estimator_time']:.1f}"
               if r.get("estimator_setup") is not None else "—")
        levels = f" ({', '.join(map(str, r['per_level']))})" if r.get("per_level") else ""
        print(f"| {r['levels']} | {r['vertices']} | {r['which']} | {r['newton']}{levels} | "
              f"{r['linear']} | {r['linear'] / max(r['newton'], 1):.1f} | {r['time']:.1f} | "
              f"{est} | {r['process_time']:.1f} | {r['peak_gib']:.2f} | "
              f"{r['energy_error']:.4e} |")
    print()
    import numpy as np
    ok = {(r["which"], r["levels"]): r for r in results if "failed" not in r}
    for levels in levels_list:
        a, b, m = (ok.get((w, levels)) for w in ("ours", "peer", "ours-ml"))
        if a and b:
            times = [a["time"]] + [c["time"] for c, _ in again.get(levels, [])
                                   if "failed" not in c]
            median = (f" (with the median of our {len(times)} runs, "
                      f"{float(np.median(times)):.2f} s: "
                      f"{float(np.median(times)) / b['time']:.3f})" if len(times) > 1 else "")
            print(f"J = {levels} ({a['vertices']} vertices): time ours / peer = "
                  f"{a['time'] / b['time']:.3f}{median}" +
                  (f" (ours-ml / peer = {m['time'] / b['time']:.3f})" if m else "") +
                  f"; energy error ours / peer = {a['energy_error'] / b['energy_error']:.4f}")
            print(f"J = {levels}: system time of the method, s (fresh pages, GiB): " +
                  ", ".join(f"{w} {_system_time(ok[(w, levels)])}"
                            for w in ("ours", "ours-ml", "ours-2", "peer") if (w, levels) in ok))
    for levels in levels_list:
        a, b = ok.get(("ours", levels)), ok.get(("ours-2", levels))
        if a and b:
            X1, X2 = (np.load(f"/tmp/bench_scaling_{w}_{levels}.npy") for w in ("ours", "ours-2"))
            print(f"J = {levels}: speed-up of 2 processes = {a['time'] / b['time']:.2f} "
                  f"(whole process {a['process_time'] / b['process_time']:.2f}); peak "
                  f"{b['peak_gib']:.2f} GiB per process, {b['peak_total_gib']:.2f} together; "
                  f"iterate differs from one process by "
                  f"{np.abs(X2 - X1).max() / np.abs(X1).max():.1e} (relative)")
            more = [(c, d) for c, d in again.get(levels, [])
                    if "failed" not in c and "failed" not in d]
            if more:
                pairs_run = [(a, b)] + more
                ups = sorted(c["time"] / d["time"] for c, d in pairs_run)
                print(f"J = {levels}: speed-up of each pair (ours s / ours-2 s) " +
                      ", ".join(f"{c['time']:.2f} / {d['time']:.2f} = "
                                f"{c['time'] / d['time']:.2f}" for c, d in pairs_run)
                      + f"; median {float(np.median(ups)):.2f}")
                print(f"J = {levels}: system time of each pair's runs, s (fresh pages, GiB; "
                      f"ours-2: process 0 + 1) " + ", ".join(
                          f"{_system_time(c)} / {_system_time(d)}" for c, d in pairs_run))
    ours = [ok[("ours", j)] for j in levels_list if ("ours", j) in ok]
    if len(ours) >= 2:
        first, last = ours[0], ours[-1]
        per = [r["linear"] / max(r["newton"], 1) for r in (first, last)]
        print(f"GMRES per Newton step: {per[0]:.1f} at {first['vertices']} vertices, "
              f"{per[1]:.1f} at {last['vertices']}: ratio {per[1] / per[0]:.2f}")
        for key in ("time", "process_time"):
            p = math.log(last[key] / first[key]) / math.log(last["vertices"] / first["vertices"])
            print(f"{key} grows like N^{p:.2f} from {first['vertices']} to {last['vertices']}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[3])
    else:
        import argparse
        parser = argparse.ArgumentParser(
            description="Ours against the PETSc SNES VI peer on the disk scene (issue 6); "
                        "the module notes say what is measured.")
        parser.add_argument("sizes", nargs="*", metavar="J[:H0]",
                            help=f"refinements J of the gmsh mesh of size H0 (default "
                                 f"{H0}); default {' '.join(map(str, DEFAULT_LEVELS))}")
        parser.add_argument("--pairs", type=int, default=1, metavar="R",
                            help="R - 1 more (ours, ours-2) pairs per size (default 1)")
        options = parser.parse_args()
        for size in options.sizes:
            try:
                j, h0 = _size(size)
                if j < 0 or not h0 > 0:
                    raise ValueError
            except ValueError:
                parser.error(f"size {size!r} is not J or J:H0 (J >= 0, H0 > 0)")
        if options.pairs < 1:
            parser.error("--pairs must be at least 1")
        main(options.sizes or [str(j) for j in DEFAULT_LEVELS], options.pairs)
