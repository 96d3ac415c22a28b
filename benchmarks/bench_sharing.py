"""What sharing each piece of work between 2 processes would give (issue 6): the linear solve
of a Newton step and the estimators' patch problems on the finest level, on 1 process and
split over 2, side by side.

Our 2-process runs split the work by kind (membranes.pipeline): Newton and GMRES on process 0,
the estimators on process 1. A level then takes at least process 0's Newton chain plus the
estimate of its last iterate, which is why the speed-up at 9.3e5 vertices stays near 1.5
(BENCHMARKS.md). The other way is to share every piece between the processes. This script
measures how the two largest pieces would gain from it on this machine:

* the linear solve with the vertex-block AMG (membranes.preconditioner: for Newton-min, one
  V-cycle on the gap operator K = S on the free vertices per iteration). K is taken from the
  disk scene on T_J (`bench_scaling.py`'s run: adaptive Newton-min, eliminated system,
  vertex_amg): S = μ1 S (μ1 = 1 here) restricted to the interior vertices that are free at
  the final iterate (newton.active_set's rule). K's rows are split into P contiguous blocks
  (dolfinx numbers the vertices of a mesh locally); hypre BoomerAMG with our inner options
  (`DEFAULT_INNER`) preconditions GMRES to a relative residual of 1e-10 from x = 0 for a
  fixed right side; set-up and solve are timed separately, REPEATS times per process (the
  first left out: it loads hypre's code);
* the estimators' set-up (`Estimators` with `owned`: each process sets up the patches of its
  block of vertices, as the estimator processes do when P ≥ 3, membranes.parallel) and the
  flux equilibration at the final iterate (σ_1, σ_2 of the owned patches; three times),
  twice per process (the first left out).

Each measurement runs in fresh processes (`mpirun -n P`, each process bound to a core), and
the rounds alternate P = 1 and P = 2, since the machine's speed drifts (BENCHMARKS.md).
Printed: each round's times, the medians and the ratios P = 1 / P = 2.

Usage: `.venv/bin/python benchmarks/bench_sharing.py [J[:H0]] [rounds]` (default 6:0.132,
about 9.3e5 vertices, and 3 rounds; about 4 minutes).
"""

import json
import subprocess
import sys
import time

REPEATS = 4
OPERATOR = "/tmp/bench_sharing_K.npz"
ITERATE = "/tmp/bench_sharing_X.npy"


def export(size):
    """Solve the disk on T_J as bench_scaling.py does and save K (module notes)."""
    import dataclasses

    import numpy as np
    import scipy.sparse as sp

    from membranes import scenes, solve
    from membranes.cli import quiet_jit_logging
    from membranes.newton_system import linear_rows, split
    from membranes.preconditioner import principal_submatrix
    quiet_jit_logging()
    levels, _, h0 = size.partition(":")
    problem = scenes.disk(h=float(h0 or 0.2), levels=int(levels))
    sol = solve(dataclasses.replace(problem, exact=None), newton="adaptive", cfun="min",
                system="eliminated", petsc_options={"pc_type": "vertex_amg"}, alg_flux="nu")
    rows = linear_rows(sol.disc)
    u1, u2, lam = split(sol.X, rows.n)
    free = (u1 - u2) > rows.kappa * lam             # not predicted in contact
    free[rows.boundary] = False                     # Dirichlet rows: no unknowns
    K = principal_submatrix(sol.disc.S1, np.flatnonzero(free)).tocsr()
    sp.save_npz(OPERATOR, K)
    np.save(ITERATE, sol.X)
    print(json.dumps({"vertices": rows.n, "rows": K.shape[0], "nnz": K.nnz}), flush=True)


def amg():
    """One measurement on the processes of COMM_WORLD: JSON lines from process 0."""
    import numpy as np
    import scipy.sparse as sp
    from mpi4py import MPI
    from petsc4py import PETSc

    from membranes.preconditioner import DEFAULT_INNER
    comm = MPI.COMM_WORLD
    K = sp.load_npz(OPERATOR).tocsr()
    n = K.shape[0]
    bounds = np.linspace(0, n, comm.size + 1).round().astype(int)
    lo, hi = bounds[comm.rank], bounds[comm.rank + 1]
    block = K[lo:hi]
    A = PETSc.Mat().createAIJ(size=((hi - lo, n), (hi - lo, n)), comm=comm,
                              csr=(block.indptr.astype(PETSc.IntType),
                                   block.indices.astype(PETSc.IntType), block.data))
    A.assemble()
    b, x = A.createVecLeft(), A.createVecRight()
    b.array[:] = np.random.default_rng(0).standard_normal(n)[lo:hi]
    options = PETSc.Options()
    for key, value in (DEFAULT_INNER | {"ksp_type": "gmres", "ksp_rtol": 1e-10,
                                        "ksp_max_it": 500}).items():
        options[key] = value
    for _ in range(REPEATS):
        ksp = PETSc.KSP().create(comm)
        ksp.setOperators(A)
        ksp.setFromOptions()
        comm.barrier()
        t0 = time.perf_counter()
        ksp.setUp()
        comm.barrier()
        t1 = time.perf_counter()
        x.set(0.0)
        ksp.solve(b, x)
        comm.barrier()
        t2 = time.perf_counter()
        if comm.rank == 0:
            print(json.dumps({"setup": t1 - t0, "solve": t2 - t1,
                              "its": ksp.getIterationNumber()}), flush=True)
        ksp.destroy()


def estimators(size):
    """One measurement of the estimators on the processes of COMM_WORLD (module notes)."""
    import dataclasses

    import numpy as np
    from mpi4py import MPI

    from membranes import parallel, scenes
    from membranes.cli import quiet_jit_logging
    from membranes.discretisation import discretise
    from membranes.estimators import Estimators
    quiet_jit_logging()
    comm = MPI.COMM_WORLD
    levels, _, h0 = size.partition(":")
    problem = scenes.disk(h=float(h0 or 0.2), levels=int(levels), comm=MPI.COMM_SELF)
    disc = discretise(dataclasses.replace(problem, exact=None), stiffness=False)
    X, n = np.load(ITERATE), disc.n
    owned = parallel.owned_vertices(n, comm)
    with parallel.one_blas_thread():
        for _ in range(2):
            comm.barrier()
            t0 = time.perf_counter()
            est = Estimators(disc, owned=owned)
            comm.barrier()
            t1 = time.perf_counter()
            for _ in range(3):
                est.flux.sigmas([(1, X[:n], None), (2, X[n:2 * n], None)], X[2 * n:])
            comm.barrier()
            t2 = time.perf_counter()
            if comm.rank == 0:
                print(json.dumps({"setup": t1 - t0, "solve": (t2 - t1) / 3}), flush=True)
            del est


def run(command):
    proc = subprocess.run(command, capture_output=True, text=True)
    lines = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not lines:
        sys.exit(f"failed: {' '.join(command)}: {proc.stderr.strip().splitlines()[-3:]}")
    return lines


def main(size, rounds):
    import numpy as np
    shape = run([sys.executable, __file__, "--export", size])[-1]
    print(f"K on T_J of the disk ({size}): {shape['vertices']} vertices, {shape['rows']} "
          f"free interior vertices, {shape['nnz']} entries")
    pieces = {"amg": ("BoomerAMG + GMRES on K", ["--amg"], REPEATS - 1),
              "estimators": ("estimators (set-up; one flux equilibration)",
                             ["--estimators", size], 1)}
    for piece, (title, args, keep) in pieces.items():
        seen = {1: [], 2: []}
        for r in range(rounds):
            for p in (1, 2):
                lines = run(["mpirun", "--allow-run-as-root", "-n", str(p), sys.executable,
                             __file__] + args)[-keep:]
                seen[p].extend(lines)
                print(f"{title}, round {r + 1}, P = {p}: " + ", ".join(
                    f"set-up {m['setup']:.3f} s + solve {m['solve']:.3f} s"
                    + (f" ({m['its']} its)" if "its" in m else "") for m in lines), flush=True)
        med = {p: {k: float(np.median([m[k] for m in seen[p]])) for k in seen[p][0]}
               for p in seen}
        for p in (1, 2):
            its = f", {med[p]['its']:.0f} GMRES iterations" if "its" in med[p] else ""
            print(f"{title}, P = {p}: median set-up {med[p]['setup']:.3f} s, solve "
                  f"{med[p]['solve']:.3f} s{its}")
        total = {p: med[p]["setup"] + med[p]["solve"] for p in med}
        print(f"{title}: ratio P = 1 / P = 2: set-up {med[1]['setup'] / med[2]['setup']:.2f}, "
              f"solve {med[1]['solve'] / med[2]['solve']:.2f}, both {total[1] / total[2]:.2f}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--export"]:
        export(sys.argv[2])
    elif sys.argv[1:2] == ["--amg"]:
        amg()
    elif sys.argv[1:2] == ["--estimators"]:
        estimators(sys.argv[2])
    else:
        main(sys.argv[1] if len(sys.argv) > 1 else "6:0.132",
             int(sys.argv[2]) if len(sys.argv) > 2 else 3)
