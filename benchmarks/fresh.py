"""One measurement in a fresh process, for the benchmarks of this folder.

Run as a script, this is the *child*: `python benchmarks/fresh.py METHOD J[:H0]` (under
`mpirun -n P` for P > 1) builds the disk scene (§9) `scenes.disk(h=H0, levels=J)`, runs one
method on it and prints, on process 0, one JSON line:

* ``ours``: `solve(problem)` with the API's defaults (adaptive Newton, the 'amg' preset,
  nested iteration, the ν algebraic flux, the final certificate; §3, §6-§8);
* ``nested``: the nested SNES VI peer, `nested_peer(problem)` (§10);
* ``certified``: the nested peer, then our estimators at its final iterate
  (`membranes.app.peer.certify`, the report's certified peer too): their set-up and one
  evaluation with R the residual of its linear rows (§4, §7);
* ``plain``: the plain peer, `plain_peer(problem)` (§10).

The line holds the vertex count, the mesh time (the hierarchy's meshes, outside every
method's clock; its prolongations are made inside the nested methods, which read them), the
method's own wall time (the largest over the processes: `Solution.wall_time_s` for ours;
for a peer its solver and discretisation time, plus the certificate's for ``certified``),
Newton (SNES) and Krylov steps, the final energy error against the exact
solution, η where certified, and the peak resident memory of every process
(`resource.getrusage`, at the end of the method: the peers' energy errors, computed
afterwards, are not in it; ours computes its own inside `solve`, off its clock), and the
kernel's share of the method: its system CPU seconds (the largest over the processes) and
minor page faults (summed), which on a machine that hands out new pages slowly are a
visible part of the method time and grow with the peak (BENCHMARKS.md, "page faults").

The parent side (`launch`, `sizes`, `memory_guard`) starts such a child, times the whole
process around it, and refuses to start one whose estimated memory exceeds what the machine
has available.
"""

import json
import os
import resource
import subprocess
import sys
import time

H0 = 0.2                   # the coarse mesh size of a size 'J' (BENCHMARKS.md's meshes)
METHODS = ("ours", "nested", "certified", "plain")
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
GIB = 2.0 ** 30


def size(arg):
    """'J' or 'J:H0' -> (J, H0); ValueError for anything else."""
    j, _, h0 = str(arg).partition(":")
    try:
        j, h0 = int(j), float(h0) if h0 else H0
    except ValueError:
        j, h0 = -1, 0.0
    if j < 0 or not h0 > 0:
        raise ValueError(f"size {arg!r} is not J or J:H0 (J >= 0, H0 > 0)")
    return j, h0


def vertices(arg):
    """The vertex count of T_J for size 'J[:H0]': gmsh's coarse mesh counted (a fraction of
    a second), then the exact recursion of uniform refinement (model.checks)."""
    from mpi4py import MPI

    from membranes.fem import meshes
    from membranes.model import checks
    j, h0 = size(arg)
    mesh = meshes.unit_disk(h0, MPI.COMM_SELF)
    v, t = (mesh.topology.index_map(d).size_global for d in (0, 2))
    return int(round(checks.refined_vertices(v, t, j)))


# ## The child

def phases_of_ours(sol):
    """Where the method time of a run of ours went (rank 0's clock), from what `solve`
    records: the coarse levels (whole levels), then on T_J the Newton steps (linearisation,
    matrices, Krylov solves), the estimators' set-up, the estimates (the η_rec / η_lin gates and
    the full evaluations), and the rest (T_J's discretisation, the prolongation onto it).
    For the default coarse='residual', which sets estimators up on T_J only (with
    'estimated' the coarse levels' set-ups and estimates would count twice)."""
    coarse = sum(level["wall_time_s"] for level in sol.per_level[:-1])
    times = sol.per_level[-1]["times"]
    setup, estimates = (t or 0.0 for t in sol.estimator_times)
    phases = {"coarse": coarse, "solve": times["assembly"] + times["solve"],
              "set-up": setup, "estimates": estimates}
    phases["rest"] = sol.wall_time_s - sum(phases.values())
    return phases


def phases_of_peer(result):
    """The same for a peer run: its coarse levels (discretisation and solve), its solve on
    T_J (prolongation, operators, SNES, λ) and the rest (T_J's discretisation)."""
    *coarse, last = result.levels
    phases = {"coarse": sum(r.wall_time_s + r.setup_time_s for r in coarse),
              "solve": last.wall_time_s}
    phases["rest"] = result.wall_time_s + result.setup_time_s - sum(phases.values())
    return phases


def _peak_gib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0 / GIB   # KiB on Linux


def child(method, arg):
    from mpi4py import MPI

    from membranes import scenes, solve
    from membranes.app.logs import quiet_jit_logging
    from membranes.app.peer import certify, nested_peer, plain_peer
    from membranes.estimation.energy_error import EnergyError
    quiet_jit_logging()
    comm = MPI.COMM_WORLD
    j, h0 = size(arg)
    t0 = time.perf_counter()
    problem = scenes.disk(h=h0, levels=j)
    mesh_s = time.perf_counter() - t0
    out = {"method": method, "size": arg, "processes": comm.size,
           "vertices": int(problem.mesh.topology.index_map(0).size_global), "mesh_s": mesh_s}
    before = resource.getrusage(resource.RUSAGE_SELF)
    if method == "ours":
        sol = solve(problem)
        after = resource.getrusage(resource.RUSAGE_SELF)
        peak = _peak_gib()
        est = sol.estimates or {}
        out.update(converged=bool(sol.converged), method_s=sol.wall_time_s,
                   newton=sol.newton_iterations,
                   per_level=[lv["newton_iterations"] for lv in sol.per_level],
                   linear=sol.linear_iterations, energy_error=sol.energy_error,
                   eta=est.get("eta"), estimator_s=list(sol.estimator_times),
                   phases=phases_of_ours(sol))
    elif method in ("nested", "certified", "plain"):
        result = (plain_peer if method == "plain" else nested_peer)(problem)
        method_s = result.wall_time_s + result.setup_time_s
        eta = cert_s = None
        phases = phases_of_peer(result)
        if method == "certified":
            est, setup_s, cert_s = certify(result)
            eta = est["eta"]
            method_s += cert_s
            phases.update({"set-up": setup_s, "estimates": cert_s - setup_s})
        after = resource.getrusage(resource.RUSAGE_SELF)
        peak = _peak_gib()
        out.update(converged=bool(result.converged), method_s=method_s,
                   newton=result.snes_iterations,
                   per_level=[r.snes_iterations for r in result.levels],
                   linear=result.ksp_iterations,
                   energy_error=EnergyError(result.disc)(result.X), eta=eta,
                   certificate_s=cert_s, phases=phases)
    else:
        raise ValueError(f"unknown method {method!r} (choose from: {', '.join(METHODS)})")
    # every process's clock and peak: the slowest clock is the method's time; the kernel's
    # share of the method (system CPU seconds, the largest over the processes, and minor page
    # faults summed over them: mostly new pages as the heap grows to its peak)
    out["method_s"] = comm.allreduce(out["method_s"], op=MPI.MAX)
    out["system_s"] = comm.allreduce(after.ru_stime - before.ru_stime, op=MPI.MAX)
    out["page_faults"] = comm.allreduce(after.ru_minflt - before.ru_minflt, op=MPI.SUM)
    peaks = comm.gather(peak, root=0)
    if comm.rank == 0:
        out["peaks_gib"] = peaks
        print(json.dumps(out), flush=True)


# ## The parent

BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def blas_threads(threads=None):
    """What the children's BLAS threads are: `threads` if given, else the environment's."""
    if threads is not None:
        return f"{threads} per process (set by --blas-threads)"
    given = {k: os.environ[k] for k in BLAS_THREADS if k in os.environ}
    return (", ".join(f"{k}={v}" for k, v in given.items()) if given else
            "the BLAS library's default (one per core, per process)") + " (environment)"


def software():
    """The software the children run on, in one line (membranes.app.versions: the packages'
    installed versions, read without importing them), for the head of a benchmark's output."""
    if ROOT not in sys.path:
        sys.path.insert(0, ROOT)
    from membranes.app.versions import one_line
    from membranes.app.versions import software as versions
    return one_line(versions(libraries=False))


def run_json(command, env, timeout=None, cwd=ROOT):
    """Run `command` (a child that prints its record as a JSON line) and return that record
    with `process_s`, the wall time of the whole process measured here, or {"failed":
    reason} (a time-out, a non-zero exit or no JSON line)."""
    t = time.perf_counter()
    try:
        proc = subprocess.run(command, capture_output=True, text=True, env=env, cwd=cwd,
                              timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"failed": f"timed out after {timeout} s"}
    process_s = time.perf_counter() - t
    lines = [line for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = " | ".join(proc.stderr.strip().splitlines()[-3:])
        return {"failed": f"exit {proc.returncode}: {tail}"}
    record = json.loads(lines[-1])
    record["process_s"] = process_s
    return record


def run_code(code, args, processes=1, timeout=None, threads=None):
    """Run the Python source `code` with the command-line arguments `args` in a fresh process
    (`mpirun --oversubscribe -n P` for P > 1), this repository first on its path, and return
    its JSON record as `run_json` does. `threads`: the BLAS threads of each process (None:
    the environment's)."""
    command = [sys.executable, "-c", code] + [str(a) for a in args]
    if processes > 1:
        command = ["mpirun", "--allow-run-as-root", "--oversubscribe", "-n",
                   str(processes)] + command
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    if threads is not None:
        env.update({k: str(threads) for k in BLAS_THREADS})
    return run_json(command, env, timeout)


def launch(method, arg, processes=1, timeout=None, threads=None):
    """Run the child in a fresh process (`mpirun --oversubscribe -n P` for P > 1) and return
    its JSON record with `process_s`, the wall time of the whole process measured here, or
    {"failed": reason}. `threads`: the BLAS threads of each process (None: the
    environment's; OpenBLAS starts one per core in every process, which the batched small
    inverses of the estimators' set-up feel on a machine shared with other processes)."""
    command = [sys.executable, os.path.join(HERE, "fresh.py"), method, str(arg)]
    # a parent started under mpirun must not hand its own MPI environment to the child
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    if threads is not None:
        env.update({k: str(threads) for k in BLAS_THREADS})
    if processes > 1:
        command = ["mpirun", "--allow-run-as-root", "--oversubscribe", "-n",
                   str(processes)] + command
    record = run_json(command, env, timeout)
    if "failed" in record:
        record.update(method=method, size=arg, processes=processes)
    return record


def available_bytes():
    """MemAvailable now (the kernel's estimate of what can be allocated without swapping)."""
    from membranes.model import checks
    return checks.available_memory()


class MemoryGuard:
    """Estimated memory of a run of ours (the heaviest method here: the 'amg' preset and the
    estimators) on P processes, summed over them, against MemAvailable read just before the
    launch: `room(n, P)` gives None if it fits in `margin` of what is available, else the
    reason to skip. The estimate is the larger of model.checks's (bytes per vertex, the
    per-vertex part shared out over P, a base per process) and the figure measured by the
    runs of at least MEASURED_FROM vertices made so far (`measured`)."""

    MEASURED_FROM = 5e4     # below, the base of each process dominates: no per-vertex figure

    def __init__(self, margin=0.8):
        self.margin = margin
        self.per_vertex = 0.0

    def estimate(self, n, processes):
        from membranes.app.driver import MEMORY_METHOD
        from membranes.model import checks
        each = checks.estimate_memory(n, estimators=True, processes=processes,
                                      replicated=False, **MEMORY_METHOD["amg"])
        measured = processes * checks.BASE_BYTES + self.per_vertex * n
        return max(processes * each, measured)

    def measured(self, record):
        from membranes.model import checks
        if "failed" in record or record["vertices"] < self.MEASURED_FROM:
            return
        grows = sum(record["peaks_gib"]) * GIB - len(record["peaks_gib"]) * checks.BASE_BYTES
        self.per_vertex = max(self.per_vertex, grows / record["vertices"])

    def room(self, n, processes):
        need, have = self.estimate(n, processes), available_bytes()
        if have is not None and need > self.margin * have:
            return (f"skipped: {n} vertices on {processes} process(es) need about "
                    f"{need / GIB:.1f} GiB, {self.margin:.0%} of the "
                    f"{have / GIB:.1f} GiB available is {self.margin * have / GIB:.1f}")
        return None


def parse_common(parser, argv=None, sizes=(), procs=None):
    """Add the options the benchmarks share (--sizes with default `sizes`, --procs with default
    `procs` unless None, --no-warmup, --blas-threads, --timeout, --margin), parse `argv` and
    check the sizes (`size`), the process counts and BLAS threads (at least 1), the time-out
    (positive) and the margin (in (0, 1])."""
    parser.add_argument("--sizes", nargs="+", default=list(sizes), metavar="J[:H0]",
                        help=f"refinements J of the gmsh mesh of size H0 (default {H0}); "
                             f"default {' '.join(sizes)}")
    if procs is not None:
        parser.add_argument("--procs", nargs="+", type=int, default=list(procs), metavar="P",
                            help=f"numbers of processes (default {' '.join(map(str, procs))})")
    parser.add_argument("--no-warmup", action="store_true",
                        help="no small unreported run first (the JIT cache is then warm)")
    parser.add_argument("--blas-threads", type=int, default=None, metavar="T",
                        help="BLAS (OpenBLAS, OpenMP) threads of every process (default: "
                             "the environment's)")
    parser.add_argument("--timeout", type=float, default=None, metavar="S",
                        help="give up a run after S seconds")
    parser.add_argument("--margin", type=float, default=0.8, metavar="F",
                        help="skip a run estimated to need more than F of MemAvailable "
                             "(default 0.8)")
    args = parser.parse_args(argv)
    for s in args.sizes:
        try:
            size(s)
        except ValueError as e:
            parser.error(str(e))
    if procs is not None and any(p < 1 for p in args.procs):
        parser.error("every P must be at least 1")
    if args.blas_threads is not None and args.blas_threads < 1:
        parser.error("--blas-threads must be at least 1")
    if args.timeout is not None and not args.timeout > 0:
        parser.error("--timeout must be a positive number of seconds")
    if not 0 < args.margin <= 1:
        parser.error("--margin must lie in (0, 1]")
    return args


def child_main(argv):
    """The child's command line, `METHOD J[:H0]`: checked before anything is built, a bad one
    is one error line on stderr and exit 2 (as the benchmarks' own options)."""
    usage = f"usage: fresh.py {{{','.join(METHODS)}}} J[:H0]"
    if len(argv) != 2:
        return f"{usage}\nfresh.py: error: expected a method and a size, got {len(argv)} " \
               f"argument(s)"
    if argv[0] not in METHODS:
        return f"{usage}\nfresh.py: error: unknown method {argv[0]!r} (choose from: " \
               f"{', '.join(METHODS)})"
    try:
        size(argv[1])
    except ValueError as e:
        return f"{usage}\nfresh.py: error: {e}"
    child(argv[0], argv[1])
    return None


if __name__ == "__main__":
    error = child_main(sys.argv[1:])
    if error is not None:
        print(error, file=sys.stderr)
        sys.exit(2)
