"""What sharing a Newton solve between 2 processes would give (issue 6): BoomerAMG + GMRES on
the gap operator of the finest level, on 1 process and distributed over 2, side by side.

Our 2-process runs split the work by kind (membranes.pipeline): Newton and GMRES on process 0,
the estimators on process 1. A level then takes at least process 0's Newton chain plus the
estimate of its last iterate, which is why the speed-up at 9.3e5 vertices stays near 1.5
(BENCHMARKS.md). This script measures the alternative for the largest piece of process 0's
work, the linear solve of a Newton step with the vertex-block AMG (membranes.preconditioner:
for Newton-min, one V-cycle on the gap operator K = S on the free vertices per iteration).

K is taken from the disk scene on T_J (`bench_scaling.py`'s run: adaptive Newton-min,
eliminated system, vertex_amg): S = μ1 S (μ1 = 1 here) restricted to the interior vertices
that are free at the final iterate (newton.active_set's rule). Each measurement runs in fresh
processes (`mpirun -n P`, each process bound to a core): K's rows are split into P contiguous
blocks (dolfinx numbers the vertices of a mesh locally), hypre BoomerAMG with our inner
options (`DEFAULT_INNER`) preconditions GMRES to a relative residual of 1e-10 from x = 0 for a
fixed right side; the set-up and the solve are timed separately, REPEATS times per process
(the first of them left out: it loads hypre's code). Rounds alternate P = 1 and P = 2, since
the machine's speed drifts (BENCHMARKS.md). Printed: each round's times, the medians and the
ratios P = 1 / P = 2.

Usage: `.venv/bin/python benchmarks/bench_distributed_amg.py [J[:H0]] [rounds]` (default
6:0.132, about 9.3e5 vertices, and 3 rounds; about 2 minutes).
"""

import json
import subprocess
import sys
import time

REPEATS = 4
OPERATOR = "/tmp/bench_distributed_amg_K.npz"


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
    seen = {1: [], 2: []}
    for r in range(rounds):
        for p in (1, 2):
            lines = run(["mpirun", "--allow-run-as-root", "-n", str(p), sys.executable,
                         __file__, "--amg"])[1:]
            seen[p].extend(lines)
            print(f"round {r + 1}, P = {p}: " + ", ".join(
                f"set-up {m['setup']:.3f} s + solve {m['solve']:.3f} s ({m['its']} its)"
                for m in lines), flush=True)
    med = {p: {k: float(np.median([m[k] for m in seen[p]])) for k in ("setup", "solve", "its")}
           for p in seen}
    for p in (1, 2):
        print(f"P = {p}: median set-up {med[p]['setup']:.3f} s, solve {med[p]['solve']:.3f} s, "
              f"{med[p]['its']:.0f} GMRES iterations")
    total = {p: med[p]["setup"] + med[p]["solve"] for p in med}
    print(f"ratio P = 1 / P = 2: set-up {med[1]['setup'] / med[2]['setup']:.2f}, solve "
          f"{med[1]['solve'] / med[2]['solve']:.2f}, both {total[1] / total[2]:.2f}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--export"]:
        export(sys.argv[2])
    elif sys.argv[1:2] == ["--amg"]:
        amg()
    else:
        main(sys.argv[1] if len(sys.argv) > 1 else "6:0.132",
             int(sys.argv[2]) if len(sys.argv) > 2 else 3)
