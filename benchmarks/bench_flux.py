"""The two algebraic fluxes side by side: ν extra iterations and the multilevel flux.

    python benchmarks/bench_flux.py [--sizes 5 6] [--scenes disk square] [--procs 1]

The estimators balance the algebraic residual with a flux σ_alg (§6): by default the flux of
ν extra Krylov iterations (Ern–Vohralík), or the multilevel flux over the hierarchy
(Papež–Rüde–Vohralík–Wohlmuth, `alg_flux="multilevel"`), which the paper uses. Per scene,
size `J[:H0]` and process count, `solve(problem, alg_flux=...)` with the API's other defaults
runs once with each flux, each in a fresh process, one after the other; the hierarchy is
built outside the method's clock.

Printed: one row per run (vertices, Newton and Krylov steps, the estimators' set-up and
evaluation seconds, method and whole-process seconds, the largest peak resident memory per
process, η, η_alg and the effectivity η / energy error), then per pair the ratios
multilevel / ν of the method time and the peak and the relative difference of η. Nothing is
asserted.
"""

import argparse

import fresh

SCENES = ("disk", "square")
FLUXES = ("nu", "multilevel")

CHILD = r"""
import json, resource, sys
from mpi4py import MPI
from membranes import scenes, solve
from membranes.app.logs import quiet_jit_logging
quiet_jit_logging()
scene, flux, j, h0 = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
comm = MPI.COMM_WORLD
problem = getattr(scenes, scene)(h=h0, levels=j)
sol = solve(problem, alg_flux=flux)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
peaks = comm.gather(peak, root=0)
top = [comm.allreduce(t, op=MPI.MAX) for t in
       (sol.wall_time_s, sol.estimator_times[0], sol.estimator_times[1])]
if comm.rank == 0:
    print(json.dumps({"vertices": int(problem.mesh.topology.index_map(0).size_global),
                      "newton": sol.newton_iterations, "linear": sol.linear_iterations,
                      "converged": bool(sol.converged), "method_s": top[0], "setup_s": top[1],
                      "estimates_s": top[2], "eta": sol.estimates["eta"],
                      "eta_alg": sol.estimates["eta_alg"],
                      "energy_error": sol.energy_error, "peaks_gib": peaks}), flush=True)
"""


def run(scene, flux, arg, processes, timeout, threads):
    j, h0 = fresh.size(arg)
    return fresh.run_code(CHILD, [scene, flux, j, h0], processes, timeout, threads)


def row(scene, arg, processes, flux, r):
    if "failed" in r:
        return f"| {scene} | {arg} | {processes} | {flux} | failed: {r['failed']} |"
    effectivity = r["eta"] / r["energy_error"] if r["energy_error"] else float("nan")
    steps = f"{r['newton']}, {r['linear']}" + ("" if r["converged"] else " (not converged)")
    return (f"| {scene} | {arg} | {processes} | {flux} | {r['vertices']:,} | {steps} | "
            f"{r['setup_s']:.2f} | {r['estimates_s']:.2f} | {r['method_s']:.2f} | "
            f"{r['process_s']:.2f} | {max(r['peaks_gib']):.3f} | {r['eta']:.6e} | "
            f"{r['eta_alg']:.2e} | {effectivity:.3f} |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES,
                        help="the scenes (default: disk square)")
    args = fresh.parse_common(parser, argv, sizes=("5", "6"), procs=(1,))
    if any(fresh.size(s)[0] < 1 for s in args.sizes):
        parser.error("the multilevel flux needs J >= 1 in every size")
    print(f"# bench_flux: BLAS threads: {fresh.blas_threads(args.blas_threads)}")
    print(f"# software: {fresh.software()}")
    if not args.no_warmup:
        for flux in FLUXES:
            run("disk", flux, "2", 1, args.timeout, args.blas_threads)
    pairs = []
    print("\n| scene | size | P | flux | vertices | Newton, Krylov | set-up s | estimates s | "
          "method s | process s | peak GiB | η | η_alg | η / error |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for processes in args.procs:
        for scene in args.scenes:
            for arg in args.sizes:
                runs = [run(scene, flux, arg, processes, args.timeout, args.blas_threads)
                        for flux in FLUXES]
                for flux, r in zip(FLUXES, runs):
                    print(row(scene, arg, processes, flux, r), flush=True)
                pairs.append((scene, arg, processes, runs))
    print()
    for scene, arg, processes, (nu, ml) in pairs:
        if "failed" in nu or "failed" in ml:
            continue
        print(f"{scene} {arg}, P = {processes}: multilevel / ν: method time "
              f"{ml['method_s'] / nu['method_s']:.2f}, peak "
              f"{max(ml['peaks_gib']) / max(nu['peaks_gib']):.2f}; η relative difference "
              f"{abs(ml['eta'] - nu['eta']) / abs(nu['eta']):.1e}")


if __name__ == "__main__":
    main()
