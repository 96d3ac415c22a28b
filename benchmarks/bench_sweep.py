"""A parameter study on one hierarchy, with and without kept set-ups, side by side.

    python benchmarks/bench_sweep.py [--sizes 5 6] [--mu2 1 2 5] [--procs 1]

A user who solves several problems on one mesh (here the disk scene of §9 with μ2 running
over `--mu2`, everything else the API's defaults) either calls `solve(problem)` each time
(``fresh``) or hands every call one `membranes.Setups` (``kept``), so that the flux
equilibration of T_J (the patch systems of §5, which depend on the mesh only) is set up once
(membranes.app.setups). Per size, each way runs in a process of its own, one after the other;
the hierarchy is built once per process, outside every clock. Printed per size: every
solve's method time (`Solution.wall_time_s`) and estimator set-up time in both ways, their
ratio and the relative difference of η between the two (the runs are the same computation:
expect 0), the sweep's total and ratio, and the largest peak resident memory of the processes
in each way (the kept way holds the set-up between solves).
"""

import argparse

import fresh

CHILD = r"""
import dataclasses, json, resource, sys, time
from mpi4py import MPI
from membranes import Setups, scenes, solve
from membranes.app.logs import quiet_jit_logging
quiet_jit_logging()
way, j, h0 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
values = [float(v) for v in sys.argv[4:]]
comm = MPI.COMM_WORLD
problem = scenes.disk(h=h0, levels=j)
kept = Setups() if way == "kept" else None
runs = []
for mu2 in values:
    sol = solve(dataclasses.replace(problem, mu2=mu2, exact=None), setups=kept)
    runs.append({"mu2": mu2, "method_s": comm.allreduce(sol.wall_time_s, op=MPI.MAX),
                 "setup_s": comm.allreduce(sol.estimator_times[0], op=MPI.MAX),
                 "eta": sol.estimates["eta"], "converged": bool(sol.converged)})
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
peaks = comm.gather(peak, root=0)
if comm.rank == 0:
    print(json.dumps({"vertices": int(problem.mesh.topology.index_map(0).size_global),
                      "runs": runs, "peaks_gib": peaks}), flush=True)
"""


def run(way, arg, values, processes, timeout, threads):
    j, h0 = fresh.size(arg)
    return fresh.run_code(CHILD, [way, j, h0] + list(values), processes, timeout, threads)


def report(arg, processes, values, fresh_run, kept_run):
    print(f"\n## size {arg}, {processes} process(es)")
    for label, r in (("fresh", fresh_run), ("kept", kept_run)):
        if "failed" in r:
            print(f"{label}: failed: {r['failed']}")
            return
    print(f"{fresh_run['vertices']:,} vertices; peak GiB fresh "
          f"{max(fresh_run['peaks_gib']):.3f}, kept {max(kept_run['peaks_gib']):.3f}; process "
          f"s fresh {fresh_run['process_s']:.1f}, kept {kept_run['process_s']:.1f}\n")
    print("| μ2 | fresh s (set-up) | kept s (set-up) | kept / fresh | η rel. diff |")
    print("|---|---|---|---|---|")
    for a, b in zip(fresh_run["runs"], kept_run["runs"]):
        diff = abs(a["eta"] - b["eta"]) / abs(a["eta"])
        ok = "" if a["converged"] and b["converged"] else " (not converged)"
        print(f"| {a['mu2']:g} | {a['method_s']:.2f} ({a['setup_s']:.2f}) | "
              f"{b['method_s']:.2f} ({b['setup_s']:.2f}) | "
              f"{b['method_s'] / a['method_s']:.2f} | {diff:.1e}{ok} |")
    total_a = sum(r["method_s"] for r in fresh_run["runs"])
    total_b = sum(r["method_s"] for r in kept_run["runs"])
    print(f"| sweep | {total_a:.2f} | {total_b:.2f} | {total_b / total_a:.2f} | |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mu2", nargs="+", type=float, default=[1.0, 2.0, 5.0],
                        help="the values of μ2 solved for, in order (default 1 2 5)")
    args = fresh.parse_common(parser, argv, sizes=("5", "6"), procs=(1,))
    if any(not v > 0 for v in args.mu2):
        parser.error("every μ2 must be positive")
    print(f"# bench_sweep: μ2 = {' '.join(f'{v:g}' for v in args.mu2)}; BLAS threads: "
          f"{fresh.blas_threads(args.blas_threads)}")
    print(f"# software: {fresh.software()}")
    if not args.no_warmup:
        run("kept", "2", [1.0], 1, args.timeout, args.blas_threads)
    for processes in args.procs:
        for arg in args.sizes:
            both = [run(way, arg, args.mu2, processes, args.timeout, args.blas_threads)
                    for way in ("fresh", "kept")]
            report(arg, processes, args.mu2, *both)


if __name__ == "__main__":
    main()
