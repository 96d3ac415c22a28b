"""Run by tests/test_parallel.py under `mpirun -n P`: solve the small scenes of VARIANTS on P
processes (comm=MPI.COMM_WORLD: Newton on process 0, the estimators on the others,
membranes.pipeline) and save, from process 0, every run's final iterate X and estimates to the
.npz file named first on the command line; further arguments name the variants to run (all by
default)."""

import sys

import numpy as np
from mpi4py import MPI

from membranes import scenes, solve

# (name, scene keyword arguments, solve keyword arguments): every Newton variant, with the
# estimators, on a disk hierarchy (multilevel flux on T_1, nested) and on one mesh (ν flux)
VARIANTS = [
    ("exact-min", {"h": 0.3, "levels": 1}, {}),
    ("exact-fb-direct", {"h": 0.3, "levels": 1}, {"cfun": "fb", "linear_solver": "direct"}),
    ("inexact-min", {"h": 0.3, "levels": 1}, {"newton": "inexact"}),
    ("adaptive-min", {"h": 0.3, "levels": 1}, {"newton": "adaptive"}),
    ("adaptive-fb-amg", {"h": 0.3, "levels": 1},
     {"newton": "adaptive", "cfun": "fb", "system": "eliminated",
      "petsc_options": {"pc_type": "vertex_amg"}}),
    ("adaptive-min-nu", {"h": 0.2}, {"newton": "adaptive"}),
    # three levels: process 0 makes levels 1 and 2 while it waits, the estimator process
    # discretises the level it serves next while it waits (membranes.pipeline)
    ("adaptive-min-amg-3", {"h": 0.3, "levels": 2},
     {"newton": "adaptive", "system": "eliminated", "petsc_options": {"pc_type": "vertex_amg"}}),
]


def run(name, scene, options, comm):
    sol = solve(scenes.disk(comm=MPI.COMM_SELF, **scene), comm=comm, **options)
    last = sol.final_record
    out = {}
    if comm is not None:        # every process returns process 0's solution
        same = [np.array_equal(X, sol.X) and e == last["eta"] for X, e in
                comm.gather((sol.X, last["eta"]), root=0) or []]
        out[f"{name}/same_on_all"] = np.array([all(same)])
    return out | {f"{name}/X": sol.X, f"{name}/eta": np.array([last["eta"]]),
                  f"{name}/eta_K": sol.eta_K,
                  f"{name}/etas": np.array([np.nan if r.get("eta") is None else r["eta"]
                                            for r in sol.history]),
                  f"{name}/newton": np.array([sol.newton_iterations]),
                  f"{name}/linear": np.array([sol.linear_iterations])}


if __name__ == "__main__":
    comm = MPI.COMM_WORLD
    out, chosen = {}, sys.argv[2:]
    for name, scene, options in VARIANTS:
        if not chosen or name in chosen:
            out.update(run(name, scene, options, comm))
    if comm.rank == 0:
        np.savez(sys.argv[1], **out)
