"""Serial time against an earlier commit of this repository, side by side in one run.

    python benchmarks/bench_commit.py [--commit 6b2f081] [--sizes 5 6:0.132] [--repeat 2]

Issue 28 asks that the distributed core's serial time stays within 1.3 x that of the serial
core it replaced (commit 6b2f081). This script checks the commit out into a temporary git
worktree and, per size `J[:H0]` of the disk scene (§9), runs in fresh processes, alternately:

* ``then``: that commit's fast configuration, the one its own bench_scaling.py called
  "ours": adaptive Newton-min, eliminated system, FGMRES + vertex_amg, nested iteration, ν
  flux (its API: `solve(problem, newton="adaptive", cfun="min", system="eliminated",
  petsc_options={"pc_type": "vertex_amg"}, alg_flux="nu")`);
* ``now``: this tree's `solve(problem)` with its defaults (fresh.py's ``ours``).

The commit's run imports from its worktree, with the pip packages its pyproject.toml names
and this interpreter lacks installed into the worktree (6b2f081: threadpoolctl; its numba is
Debian's python3-numba, which must be installed). Both certify their final iterate. Method
time is each `solve`'s own wall time; process time the whole process, measured here; the
energy error is computed after the method, outside both clocks. A small unreported run of
each (J = 3) comes first: it compiles that commit's numba kernels into its cache and this
tree's forms.

Printed: a table with one row per run (vertices, Newton and Krylov steps, method and process
time, peak memory, energy error), then per pair the ratios now / then of method and process
time. Nothing is asserted.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import fresh

THEN = r"""
import dataclasses, json, resource, sys, time
from mpi4py import MPI
from membranes import scenes, solve
from membranes.discretisation import EnergyError
j, h0 = int(sys.argv[1]), float(sys.argv[2])
t = time.perf_counter()
problem = scenes.disk(h=h0, levels=j)
mesh_s = time.perf_counter() - t
sol = solve(dataclasses.replace(problem, exact=None), newton="adaptive", cfun="min",
            system="eliminated", petsc_options={"pc_type": "vertex_amg"}, alg_flux="nu")
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
fine = dataclasses.replace(sol.disc, problem=dataclasses.replace(sol.disc.problem,
                                                                 exact=problem.exact))
print(json.dumps({"vertices": int(problem.mesh.topology.index_map(0).size_global),
                  "mesh_s": mesh_s, "method_s": sol.wall_time_s, "converged": sol.converged,
                  "newton": sol.newton_iterations, "linear": sol.linear_iterations,
                  "energy_error": float(EnergyError(fine)(sol.X)),
                  "eta": sol.summary()["eta"], "peaks_gib": [peak]}), flush=True)
"""


def then_dependencies(tree):
    """Install into `tree`/.deps (pip --target, without their own dependencies) the Python
    packages that the commit's pyproject.toml requires and this interpreter cannot import
    (6b2f081: threadpoolctl; its numba is Debian's python3-numba), so that its run does not
    depend on what an earlier venv happened to hold."""
    import importlib.util
    import re

    import tomllib
    with open(os.path.join(tree, "pyproject.toml"), "rb") as f:
        wanted = tomllib.load(f).get("project", {}).get("dependencies", [])
    missing = [spec for spec in wanted
               if importlib.util.find_spec(re.split(r"[<>=!~ ;\[]", spec)[0]) is None]
    if missing:
        deps = os.path.join(tree, ".deps")
        print(f"then: installing {', '.join(missing)} into {deps}", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps",
                        "--target", deps] + missing, check=True)


def run_then(tree, arg, timeout):
    j, h0 = fresh.size(arg)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env["PYTHONPATH"] = tree + os.pathsep + os.path.join(tree, ".deps")
    return fresh.run_json([sys.executable, "-c", THEN, str(j), str(h0)], env, timeout,
                          cwd=tree)


def row(label, r):
    if "failed" in r:
        return f"| {label} | failed: {r['failed']} |"
    return (f"| {label} | {r['vertices']:,} | {r['newton']} | {r['linear']} | "
            f"{r['method_s']:.1f} | {r['process_s']:.1f} | {max(r['peaks_gib']):.2f} | "
            f"{r['energy_error']:.4e} |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commit", default="6b2f081", help="the earlier commit (6b2f081)")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="pairs of runs per size (default 1)")
    args = fresh.parse_common(parser, argv, ("5", "6:0.132"))
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    known = subprocess.run(["git", "rev-parse", "--verify", "--quiet", f"{args.commit}^{{commit}}"],
                           cwd=fresh.ROOT, capture_output=True)
    if known.returncode != 0:
        parser.error(f"--commit {args.commit!r} is not a commit of this repository")
    tree = tempfile.mkdtemp(prefix="membranes-then-")
    os.rmdir(tree)
    subprocess.run(["git", "worktree", "add", "--detach", tree, args.commit], cwd=fresh.ROOT,
                   check=True, capture_output=True)
    try:
        then_dependencies(tree)
        print(f"then: {args.commit} (worktree {tree}); now: this tree; BLAS threads: "
              f"{fresh.blas_threads(args.blas_threads)}", flush=True)
        print(f"Software (now): {fresh.software()}", flush=True)
        if not args.no_warmup:
            run_then(tree, "3", args.timeout)
            fresh.launch("ours", "3", threads=args.blas_threads)
        print("| run | vertices | Newton | linear | method s | process s | peak GiB | "
              "energy error |\n|---|---|---|---|---|---|---|---|", flush=True)
        ratios = []
        for arg in args.sizes:
            for k in range(args.repeat):
                pair = {}
                for which in (("then", "now") if k % 2 == 0 else ("now", "then")):
                    pair[which] = (run_then(tree, arg, args.timeout) if which == "then" else
                                   fresh.launch("ours", arg, timeout=args.timeout,
                                                threads=args.blas_threads))
                    print(row(f"{which} {arg}", pair[which]), flush=True)
                if not any("failed" in r for r in pair.values()):
                    ratios.append((arg, pair["now"]["method_s"] / pair["then"]["method_s"],
                                   pair["now"]["process_s"] / pair["then"]["process_s"]))
        for arg, method, process in ratios:
            print(f"size {arg}: now / then = {method:.2f} (method), {process:.2f} (process)")
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", tree], cwd=fresh.ROOT,
                       capture_output=True)
        shutil.rmtree(tree, ignore_errors=True)


if __name__ == "__main__":
    main()
