"""Files a run writes to its output folder, in parallel (§12).

* ``summary.json`` — the keys of :meth:`membranes.app.solution.Solution.summary` (scene and
  mesh, the options of the run — ``solver``, ``system``, ``petsc_options``, ``nu``, γ's,
  ``alg_flux``, ``nested``, ``tol``, ``initial_guess`` —, ``processes``, ``per_level``,
  ``converged``, ``reason``, the counts, ``wall_time_s``, ``final_residual``,
  ``complementarity_violation``, ``energy_error`` and ``energy_error_kind`` (what that error
  measures), the estimators of §7 at the final iterate, ``bound_guaranteed``,
  ``effectivity``, ``estimator_setup_s``, ``estimator_time_s``). Non-finite numbers are
  written as null.
* ``history.csv`` — one row per recorded iterate, columns `HISTORY_COLUMNS`: X⁰ of every level
  (kind ``initial``), every Newton iterate (``newton``) and, in adaptive runs, every ν-th
  Krylov iterate inside a Newton step (``krylov``); ``wall_time_s`` is the run's clock when
  the record was made; empty cells where a value is unknown.
* ``solution.xdmf`` (+ ``solution.h5``) — the P1 functions ``u1``, ``u2``, ``lambda`` and,
  where the final iterate was estimated, the DG0 function ``eta`` (the local distribution η_K
  of §7) on the computational mesh, readable by ParaView.

**In parallel.** The mesh stays distributed: every process writes its own cells and
vertices into the one XDMF/HDF5 pair through dolfinx's `XDMFFile` on the mesh's
communicator (collective HDF5 I/O). Process 0 writes the JSON and CSV (the history and
summary are the same on every process).

**Nothing half-written.** Everything goes into a fresh temporary folder inside the target,
or beside it where the run creates the target (`folders.staging_parent`: the same — shared —
filesystem for every process, and a rename instead of a copy), and is moved into place by
process 0 only when every process has finished its part without error; the temporary folder
is removed in any case. The move is all or nothing: an output name taken by a folder is
refused before anything moves, and if a rename fails midway the files moved so far go back
and the older files they replaced are restored. A failure on any process
raises on every process. A filesystem with less room than the outputs need
(folders.output_bytes) is refused before anything is written: a collective HDF5 write that
runs out of room fails on the process that writes and can leave the others waiting inside
HDF5.
"""

import contextlib
import csv
import errno
import json
import math
import os
import shutil
import tempfile

import numpy as np
from mpi4py import MPI

from ..model.folders import (
    check_output_folder,
    check_output_room,
    folder_named_as_output,
    output_bytes,
    staging_parent,
)
from . import interrupts
from .solution import ESTIMATOR_COLUMNS

HISTORY_COLUMNS = ("level", "newton_it", "linear_it", "cumulative_linear_its", "wall_time_s",
                   "residual", "alg_residual", "kind", "energy_error") + ESTIMATOR_COLUMNS \
    + ("bound",)
FILES = ("summary.json", "history.csv", "solution.xdmf", "solution.h5")


# ## Plain files (process 0)

def json_safe(value):
    """`value` with numpy scalars and arrays as Python ones and non-finite floats as None."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_summary(path, summary):
    with open(path, "w", encoding="utf-8") as f:
        json.dump(json_safe(summary), f, indent=2)
        f.write("\n")


def _cell(value):
    value = json_safe(value)
    return "" if value is None else value


def write_rows(path, rows, columns=HISTORY_COLUMNS):
    """A CSV with the given columns, one line per dict of `rows` (missing values empty)."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for row in rows:
            writer.writerow([_cell(row.get(c)) for c in columns])


def write_columns(path, columns):
    """A CSV of equally long named columns ({name: values})."""
    names = tuple(columns)
    write_rows(path, [dict(zip(names, values)) for values in zip(*columns.values())], names)


# ## The solution (every process)

def eta_function(mesh, eta_K):
    """The DG0 Function `eta` with the values η_K of the owned cells (mesh cell order)."""
    from dolfinx import fem
    DG0 = fem.FunctionSpace(mesh, ("DG", 0))
    eta = fem.Function(DG0, name="eta")
    ncells = mesh.topology.index_map(2).size_local
    eta.x.array[DG0.dofmap.list.array[:ncells]] = eta_K
    eta.x.scatter_forward()
    return eta


def write_solution(path, mesh, functions, eta_K=None):
    """u1, u2, lambda (P1) and, where given, η_K (DG0 `eta`) into XDMF + HDF5; collective on
    the mesh's communicator, every process writing its part."""
    from dolfinx.io import XDMFFile
    functions = list(functions)
    if eta_K is not None:
        functions.append(eta_function(mesh, eta_K))
    try:
        with XDMFFile(mesh.comm, path, "w") as xdmf:
            xdmf.write_mesh(mesh)
            for f in functions:
                xdmf.write_function(f)
    except RuntimeError as e:
        # (dolfinx reports a failed HDF5 write, a full disk among others, as RuntimeError:
        # an OSError, so that `staged_folder` makes it the same one line everywhere)
        raise OSError(f"the HDF5 write failed ({e})") from e


# ## Staging

@contextlib.contextmanager
def staged_folder(out, comm=MPI.COMM_SELF, nbytes=0, replaces=(), names=()):
    """Yield (on every process of `comm`) the path of a fresh temporary folder in `out`
    (beside it if missing: `folders.staging_parent`); when the block ends without an error on
    any process, process 0 moves every file in it into `out` (created if missing), and
    removes from `out` the files named in `replaces` that the block did not make (outputs a
    run may go without, such as a picture that could not be drawn: an older run's copy must
    not stand beside the new files), all or nothing (`_move_in`). Other files of `out` are
    left alone. The temporary folder goes in any case. ValueError (one line, nothing left
    behind) if `out` cannot be written or holds a folder of one of the output `names`
    (folders.check_output_folder), its filesystem has fewer than `nbytes` bytes free
    (folders.check_output_room) or the move fails, and on every process if a process's block
    fails to write (an OSError: a full disk, a quota): the same one line everywhere, not a
    traceback per process; otherwise a process whose block succeeded while another's failed
    raises RuntimeError."""
    interrupts.unsettle()            # (outputs not in place until this block's end)
    check_output_folder(out, comm, names)
    if nbytes:
        check_output_room(out, nbytes, comm)
    out = os.path.abspath(os.fspath(out))
    tmp, error = None, None
    if comm.rank == 0:
        try:
            parent = staging_parent(out)
            os.makedirs(parent, exist_ok=True)
            tmp = tempfile.mkdtemp(prefix=".membranes-", dir=parent)
            interrupts.staging = tmp    # (removed at once on Ctrl-C or SIGTERM)
        except OSError as e:
            error = f"output folder {out} cannot be written: {e.strerror or e}"
    tmp, error = comm.bcast((tmp, error), root=0)
    if error is not None:
        raise ValueError(error)
    # every process removes the folder on Ctrl-C or SIGTERM (one shared filesystem): the one
    # that meets the signal first may be any, and process 0 may then wait in an MPI call
    # for ever, until the job is killed
    interrupts.staging = tmp
    failed = None
    try:
        yield tmp
    except KeyboardInterrupt:
        # a signal: the staged files go, and the run ends here, without the collectives
        # below. The other processes met the signal too, each where it is (a process other
        # than 0 goes on a moment, `interrupts.among`), so no collective call can be counted
        # on to meet theirs: process 0 waited in one for ever, or took another's data for
        # its own; under mpirun a process that has gone ends the rest (membranes.app.cli)
        interrupts.caught()             # (no second raise inside the clean-up)
        shutil.rmtree(tmp, ignore_errors=True)
        interrupts.staging = None
        raise
    except BaseException as e:          # noqa: BLE001  (every process must learn of it)
        failed = e
    if comm.rank != 0:
        interrupts.staging = None       # (process 0 may move the files in from here on)
    everyone = comm.allreduce(failed is None, op=MPI.LAND)
    written = None                      # why a process could not write, if one could not
    signalled = False                   # whether a process has met a signal and goes on
    if not everyone:
        mine = f"{failed.strerror or failed}" if isinstance(failed, OSError) and \
            not isinstance(failed, BrokenPipeError) else None      # (`| head`: no output's)
        reasons = comm.allgather((mine, interrupts.pending()))
        signalled = any(s for _, s in reasons)
        if not signalled:
            written = next((r for r, _ in reasons if r is not None), None)
    error, stranded = None, False
    with interrupts.deferred():        # (a signal waits for the last rename)
        if comm.rank == 0:
            try:
                if everyone:
                    interrupts.staging = None     # (moving in: no longer removed as a whole)
                    os.makedirs(out, exist_ok=True)
                    _move_in(tmp, out, replaces)
            except OSError as e:
                where = f"{e.filename}: " if e.filename else ""
                stranded = getattr(e, "stranded", False)
                error = f"cannot move the outputs into {out}: {where}{e.strerror or e}; " + (
                    f"it could not be undone in full: the older files are in {tmp}/old" if
                    stranded else "nothing was changed")
            finally:
                if not stranded:
                    shutil.rmtree(tmp, ignore_errors=True)
                interrupts.staging = None
        error = comm.bcast(error, root=0)
        if everyone and error is None:
            interrupts.settle()        # (in place: a signal from here on does not end the run)
    if signalled:
        # the handler of a process that met it removed the folder the others write into
        # (`interrupts`): they end as it does, not with a failed write
        raise interrupts.Terminated from failed
    if written is not None:
        raise ValueError(f"the outputs cannot be written into {out}: {written}; nothing was "
                         f"written") from failed
    if failed is not None:
        raise failed
    if not everyone:
        raise RuntimeError(f"writing into {out} failed on another process; nothing was "
                           "written")
    if error is not None:
        raise ValueError(error)


def _move_in(tmp, out, replaces):
    """Move every file of the staging folder `tmp` into `out`, and the files (not folders) of
    `out` named in `replaces` that `tmp` lacks out of it, all or nothing (`staged_folder`):
    an output name that `out` holds as a folder raises before anything moves; the files of
    `out` that get replaced or removed are first renamed into `tmp`/old, so that a rename
    that fails midway puts back what had moved, and they go with `tmp` once all have
    moved."""
    made = sorted(os.listdir(tmp))
    taken = folder_named_as_output(out, made)
    if taken is not None:
        raise IsADirectoryError(errno.EISDIR, "a folder has the name of an output",
                                os.path.join(out, taken))
    stale = [name for name in set(replaces) - set(made)        # (a folder of such a name stays)
             if os.path.isfile(os.path.join(out, name))
             or os.path.islink(os.path.join(out, name))]
    old = os.path.join(tmp, "old")
    os.mkdir(old)
    kept, moved = [], []                 # (old file of out, its copy in tmp/old), names
    try:
        for name in sorted(made + stale):
            target = os.path.join(out, name)
            if os.path.lexists(target):
                os.replace(target, os.path.join(old, name))
                kept.append((target, os.path.join(old, name)))
            if name in made:
                os.replace(os.path.join(tmp, name), target)
                moved.append(name)
    except OSError as e:
        # undone as far as the filesystem lets; if it does not, tmp (the older files in
        # tmp/old) is kept and named (`staged_folder`)
        back = [_try_replace(os.path.join(out, name), os.path.join(tmp, name))
                for name in moved]
        back += [_try_replace(copy, target) for target, copy in kept]
        e.stranded = not all(back)
        raise


def _try_replace(source, target):
    try:
        os.replace(source, target)
        return True
    except OSError:
        return False


def room_for(mesh):
    """The bytes the outputs of a run on `mesh` need (folders.output_bytes, global counts)."""
    topology = mesh.topology
    return output_bytes(topology.index_map(0).size_global, topology.index_map(2).size_global)


def write_outputs(solution, out_dir, summary=None):
    """Write summary.json, history.csv and solution.xdmf (+ .h5) of `solution` into
    `out_dir` (created if missing); collective on the solution's communicator. Returns the
    absolute path of `out_dir`. `summary`: `solution.summary()` if the caller has made it
    already (it measures T_J's cells: not twice for one run)."""
    comm = solution.comm
    if summary is None:
        summary = solution.summary()              # collective (MPI reductions)
    with staged_folder(out_dir, comm, room_for(solution.disc.mesh), names=FILES) as tmp:
        write_solution(os.path.join(tmp, "solution.xdmf"), solution.disc.mesh,
                       solution.functions, solution.eta_K)
        if comm.rank == 0:
            write_summary(os.path.join(tmp, "summary.json"), summary)
            write_rows(os.path.join(tmp, "history.csv"), solution.history)
    return os.path.abspath(out_dir)
