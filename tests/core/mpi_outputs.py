"""Run under `mpirun -n P`: write a run's outputs in parallel, then (process 0) read
solution.h5 back and compare it with the iterate gathered from every process; then make one
process fail inside a staged folder. Prints one JSON line (process 0).

    mpirun -n 2 python tests/core/mpi_outputs.py OUT_PARENT
"""

import errno
import json
import os
import sys

import numpy as np
from mpi4py import MPI

from membranes.app.driver import solve
from membranes.app.outputs import staged_folder, write_outputs
from membranes.model import scenes


def by_coordinates(points, values):
    """values sorted by the points' (x, y), rounded to 12 digits to match across files."""
    order = np.lexsort(np.round(points[:, :2], 12).T[::-1])
    return np.round(points[order, :2], 12), values[order]


def h5_values(folder):
    """{name: (points, values)} of the P1 functions and (centres, values) of eta, from
    solution.h5."""
    import h5py
    with h5py.File(os.path.join(folder, "solution.h5"), "r") as h5:
        x = h5["/Mesh/mesh/geometry"][:]
        cells = h5["/Mesh/mesh/topology"][:]
        out = {name: by_coordinates(x, h5[f"/Function/{name}/0"][:].ravel())
               for name in ("u1", "u2", "lambda")}
        out["eta"] = by_coordinates(x[cells].mean(axis=1), h5["/Function/eta/0"][:].ravel())
    return out


def gathered(sol):
    """The same, gathered from the solution on every process (owned dofs and cells)."""
    comm, disc = sol.comm, sol.disc
    x = disc.V.tabulate_dof_coordinates()[:disc.n]
    mesh = disc.mesh
    nc = mesh.topology.index_map(2).size_local
    centres = mesh.geometry.x[mesh.geometry.dofmap.array.reshape(-1, 3)[:nc]].mean(axis=1)
    parts = comm.gather((x, [a.copy() for a in disc.split(sol.X)], centres, sol.eta_K), root=0)
    if comm.rank != 0:
        return None
    x = np.concatenate([p[0] for p in parts])
    out = {name: by_coordinates(x, np.concatenate([p[1][k] for p in parts]))
           for k, name in enumerate(("u1", "u2", "lambda"))}
    out["eta"] = by_coordinates(np.concatenate([p[2] for p in parts]),
                                np.concatenate([p[3] for p in parts]))
    return out


def main(parent):
    comm = MPI.COMM_WORLD
    sol = solve(scenes.disk(h=0.3, levels=1))
    folder = write_outputs(sol, os.path.join(parent, "run"))
    theirs = gathered(sol)
    # one process fails inside a staged folder: every process raises, nothing is left
    failed_target = os.path.join(parent, "failed")
    raised = None
    try:
        with staged_folder(failed_target, comm) as tmp:
            if comm.rank == 0:
                with open(os.path.join(tmp, "partial.txt"), "w") as f:
                    f.write("half\n")
            comm.barrier()
            if comm.rank == comm.size - 1:
                raise RuntimeError("planted failure")
    except RuntimeError as e:
        raised = str(e)
    raised = comm.gather(raised, root=0)
    # process 0 cannot write (a full disk): every process raises the same one-line ValueError
    full = None
    try:
        with staged_folder(os.path.join(parent, "full"), comm):
            if comm.rank == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    except ValueError as e:
        full = str(e)
    full = comm.gather(full, root=0)
    if comm.rank == 0:
        mine = h5_values(folder)
        result = {"processes": comm.size, "files": sorted(os.listdir(folder)),
                  "left": sorted(os.listdir(parent)), "raised": raised, "full": full,
                  "converged": bool(sol.converged)}
        for name, (px, pv) in mine.items():
            qx, qv = theirs[name]
            result[name] = {"points": bool(px.shape == qx.shape and np.array_equal(px, qx)),
                            "max_diff": float(np.abs(pv - qv).max()) if pv.shape == qv.shape
                            else None, "size": float(np.abs(qv).max())}
        with open(os.path.join(folder, "summary.json")) as f:
            result["summary_processes"] = json.load(f)["processes"]
        print(json.dumps(result))


if __name__ == "__main__":
    main(sys.argv[1])
