"""Run by tests/test_parallel.py under `mpirun -n P`: solve the small scenes of VARIANTS with the
patches shared between the processes (comm=MPI.COMM_WORLD) and save, from process 0, every
run's final iterate X and estimates to the .npz file named on the command line."""

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
]


def run(name, scene, options, comm):
    sol = solve(scenes.disk(comm=MPI.COMM_SELF, **scene), comm=comm, **options)
    last = sol.final_record
    return {f"{name}/X": sol.X, f"{name}/eta": np.array([last["eta"]]),
            f"{name}/eta_K": sol.eta_K, f"{name}/newton": np.array([sol.newton_iterations]),
            f"{name}/linear": np.array([sol.linear_iterations])}


if __name__ == "__main__":
    comm = MPI.COMM_WORLD
    out = {}
    for name, scene, options in VARIANTS:
        out.update(run(name, scene, options, comm))
    if comm.rank == 0:
        np.savez(sys.argv[1], **out)
