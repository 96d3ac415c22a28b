"""Files a run writes to its output folder.

* ``summary.json`` — the keys of :meth:`membranes.driver.Solution.summary`;
* ``history.csv``  — one row per recorded iterate, columns HISTORY_COLUMNS: X^0 (kind
  "initial"), every Newton iterate ("newton") and every ν-th Krylov iterate inside a Newton
  step ("krylov");
* ``solution.xdmf`` (+ ``solution.h5``) — P1 functions ``u1``, ``u2``, ``lambda`` (and the DG0
  estimated error distribution ``eta`` where the estimators ran and bound the error) on the
  computational mesh, readable by ParaView.

Everything is written into a fresh temporary folder beside the target and moved into place
at the end, so an interrupted or failed run leaves nothing half-written in the output folder.
"""

import contextlib
import csv
import json
import math
import os
import shutil
import tempfile

from .app.checks import check_output_folder
from .estimators import COLUMNS as ESTIMATOR_COLUMNS

HISTORY_COLUMNS = ("level", "newton_it", "linear_it", "cumulative_linear_its", "wall_time_s",
                   "residual", "alg_residual", "kind", "energy_error") + ESTIMATOR_COLUMNS \
    + ("bound", "cfun", "step_length", "linearised_at")


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_summary(path, summary):
    with open(path, "w") as f:
        json.dump({k: _json_safe(v) for k, v in summary.items()}, f, indent=2)
        f.write("\n")


def write_history(path, history, columns=HISTORY_COLUMNS):
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for rec in history:
            writer.writerow(["" if rec.get(c) is None else rec[c] for c in columns])


def write_solution(path, mesh, functions, eta_K=None):
    """u1, u2, lambda (P1) and, where estimated, the local distribution η_K (DG0 `eta`)."""
    from dolfinx import fem
    from dolfinx.io import XDMFFile
    if eta_K is not None:
        DG0 = fem.FunctionSpace(mesh, ("DG", 0))
        eta = fem.Function(DG0, name="eta")
        ncells = mesh.topology.index_map(2).size_local
        eta.x.array[DG0.dofmap.list.array[:ncells]] = eta_K
        eta.x.scatter_forward()
        functions = list(functions) + [eta]
    with XDMFFile(mesh.comm, path, "w") as xdmf:
        xdmf.write_mesh(mesh)
        for f in functions:
            xdmf.write_function(f)


@contextlib.contextmanager
def staged_folder(out):
    """Yield a fresh temporary folder beside `out` (one process); when the block ends without
    an error, every file in it moves into `out` (created if missing); the temporary folder
    goes in any case. ValueError (one line, nothing left behind) if `out` exists and is not a
    folder or cannot be written (membranes.app.checks.check_output_folder)."""
    out = os.path.abspath(out)
    check_output_folder(out)
    parent = os.path.dirname(out)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".membranes-", dir=parent)
    try:
        yield tmp
        os.makedirs(out, exist_ok=True)
        for name in os.listdir(tmp):
            os.replace(os.path.join(tmp, name), os.path.join(out, name))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def write_outputs(solution, out_dir):
    """Write the three outputs of `solution` into `out_dir` (created if missing). With several
    processes (membranes.parallel: each holds the whole solution) process 0 writes them; every
    process returns once they are in place, or raises the error process 0 met."""
    comm = solution.comm
    error = None
    if comm is None or comm.rank == 0:
        try:
            with staged_folder(out_dir) as tmp:
                write_solution(os.path.join(tmp, "solution.xdmf"), solution.problem.mesh,
                               solution.functions, solution.eta_K)
                write_summary(os.path.join(tmp, "summary.json"), solution.summary())
                write_history(os.path.join(tmp, "history.csv"), solution.history)
        except Exception as e:     # noqa: BLE001  (handed to every process below)
            error = e
    if comm is not None:
        error = comm.bcast(error, root=0)
    if error is not None:
        raise error
    return os.path.abspath(out_dir)
