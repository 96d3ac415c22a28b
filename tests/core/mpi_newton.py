"""Newton runs on any number of processes, for tests/core/test_newton.py.

    mpirun -n P python tests/core/mpi_newton.py OUT.npz SCENE H RUN [RUN ...]

RUN = preset:cfun:variant (e.g. amg:min:exact); SCENE a scene's name, or its name and keyword
arguments (`make_scene`: radial,rho=0.1). Every run's final iterate is gathered on
rank 0 by vertex coordinates (the P1 dof coordinates, rounded to 1e-9 and sorted
lexicographically), so that runs on different numbers of processes, whose dof numberings
differ, can be compared value by value; rank 0 writes them with the Newton steps, Krylov
iterations and the final relative residual into OUT.npz and prints one JSON line per run,
with the number of contact vertices (λ > 0) each process owns at the end.
"""

import json
import sys

import numpy as np
from mpi4py import MPI


def by_coordinates(disc, X):
    """(coordinates, u1, u2, λ) of the owned dofs of every process, gathered on rank 0 and
    sorted by coordinates (None elsewhere)."""
    n = disc.n
    xy = disc.V.tabulate_dof_coordinates()[:n, :2]
    u1, u2, lam = (np.array(a) for a in disc.split(X))
    parts = disc.comm.gather((xy, u1, u2, lam), root=0)
    if disc.comm.rank != 0:
        return None
    xy, u1, u2, lam = (np.concatenate([p[i] for p in parts]) for i in range(4))
    key = np.round(xy, 9)
    order = np.lexsort((key[:, 1], key[:, 0]))
    return xy[order], u1[order], u2[order], lam[order]


def make_scene(scene, h, comm=MPI.COMM_WORLD):
    """The scene 'name' or 'name,key=value,...' (numbers) at size h on `comm`."""
    from membranes.model import scenes
    name, *pairs = scene.split(",")
    kwargs = {k: float(v) for k, v in (pair.split("=") for pair in pairs)}
    return scenes.make(name, h=h, comm=comm, **kwargs)


def run(scene, h, runs, comm=MPI.COMM_WORLD):
    """The final iterates of `runs` (preset:cfun:variant strings) on `scene` at size h."""
    from membranes.fem.discretisation import discretise
    from membranes.nonlinear.newton import newton
    disc = discretise(make_scene(scene, h, comm))
    out, lines = {}, []
    for spec in runs:
        preset, cfun, variant = spec.split(":")
        res = newton(disc, cfun=cfun, variant=variant, krylov=preset)
        gathered = by_coordinates(disc, res.X)
        contact = comm.allgather(int(np.sum(np.array(disc.split(res.X)[2]) > 0.0)))
        if comm.rank == 0:
            xy, u1, u2, lam = gathered
            out["xy"] = xy
            out[f"{spec}/X"] = np.stack([u1, u2, lam])
            lines.append({"run": spec, "converged": res.converged, "reason": res.reason,
                          "newton_steps": res.newton_steps, "krylov_steps": res.krylov_steps,
                          "residual": res.history[-1]["residual"], "processes": comm.size,
                          "vertices": disc.n_global, "contact_per_process": contact})
        res.X.destroy()
    return out, lines


if __name__ == "__main__":
    path, scene, h, runs = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4:]
    out, lines = run(scene, h, runs)
    if MPI.COMM_WORLD.rank == 0:
        np.savez(path, **{k.replace(":", "_").replace("/", "__"): v for k, v in out.items()})
        for line in lines:
            print(json.dumps(line), flush=True)
