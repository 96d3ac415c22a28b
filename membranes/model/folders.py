"""The output folder, checked before a run starts (issue 29; membranes.model.checks has the
other checks): `check_output_folder` creates it, writes and removes a probe file, moves it in
from a staging folder as the writers do (`staging_parent`), and removes what it created
again; it also refuses a folder in it with the name of an output file. `check_output_room`
refuses a filesystem without room for the outputs (HDF5 would fail halfway, with a page of
diagnostics per process). ValueError with one line; plain values only, nothing imported from
the rest of the package (membranes.app.outputs writes the files).
"""

import os
import shutil
import tempfile


def check_output_folder(path, comm=None, names=()):
    """Make sure the run can write its output folder `path` before it starts: the folder
    (and its missing parents) can be created, a file written, moved in from a staging folder
    (`staging_parent`, as membranes' writers do) and removed. Whatever this created is
    removed again; and none of the output file `names` is taken by a folder in it (the
    outputs could not move in at the end). ValueError with one line otherwise. With `comm`,
    process 0 looks (it writes the outputs) and every process gets its answer."""
    if not os.fspath(path).strip():
        # (os.path.abspath('') is the working folder: an unset shell variable would spill
        # the outputs there; a name of blanks is as likely a slip)
        raise ValueError(f"the output folder is an empty or blank path ({os.fspath(path)!r}): "
                         f"name a folder")
    looked_at_on_rank0(lambda: _probe_folder(os.path.abspath(os.fspath(path)), names), comm)


def looked_at_on_rank0(look, comm):
    """Run `look()` on process 0 of `comm` (everywhere without one) and raise its ValueError
    on every process, with the same message."""
    error = None
    if comm is None or comm.rank == 0:
        try:
            look()
        except ValueError as e:
            error = str(e)
    if comm is not None and comm.size > 1:
        error = comm.bcast(error, root=0)
    if error is not None:
        raise ValueError(error)


# The bytes of a run's outputs (membranes.app.outputs): solution.h5 holds the topology (3
# int64 per cell), the geometry (2 float64 per vertex), u1, u2, λ (1 float64 per vertex each)
# and η (1 float64 per cell), 8 (4 T + 5 V) bytes in all (a disk of 1 761 vertices and 3 392
# cells: 178 984 bytes of data in a 190 640-byte file); OUTPUT_EXTRA covers HDF5's own metadata, the
# XDMF, summary.json and history.csv (a few kB each).
OUTPUT_EXTRA = 1 << 20


def output_bytes(vertices, cells):
    """An upper estimate of the bytes a run on a mesh of `vertices` and `cells` (global
    counts) writes into its output folder."""
    return 8 * (4 * int(cells) + 5 * int(vertices)) + OUTPUT_EXTRA


def check_output_room(path, nbytes, comm=None):
    """ValueError (one line) if the filesystem of the output folder `path` (of its nearest
    existing ancestor) has fewer than `nbytes` bytes free for this user. With `comm`,
    process 0 looks and every process gets its answer."""
    def look():
        out = os.path.abspath(os.fspath(path))
        missing = _missing_folders(out)
        try:
            st = os.statvfs(os.path.dirname(missing[0]) if missing else out)
        except OSError:                   # no statvfs here: the writers report a failure
            return
        free = st.f_bavail * st.f_frsize
        if free < nbytes:
            raise ValueError(f"output folder {out} has {free / 2**20:.1f} MiB free, the "
                             f"outputs need about {nbytes / 2**20:.1f} MiB")

    looked_at_on_rank0(look, comm)


def staging_parent(out):
    """Where the outputs of the folder `out` are staged (membranes.app.outputs.staged_folder):
    inside `out` where it exists, so that a folder the user can write is enough (its parent
    may be read-only, as for a home folder); beside it, in its parent, where the run creates
    it. Either way on the filesystem of `out`, so that the outputs move in by renaming."""
    return out if os.path.isdir(out) else os.path.dirname(out)


def folder_named_as_output(out, names):
    """The first of the output file `names` that the folder `out` holds as a folder (not a
    link), or None: the outputs could not be moved in under that name."""
    return next((name for name in names if os.path.isdir(os.path.join(out, name))
                 and not os.path.islink(os.path.join(out, name))), None)


def _probe_folder(out, names=()):
    if os.path.lexists(out) and not os.path.isdir(out):
        what = "a link to nothing" if os.path.islink(out) else "not a folder"
        raise ValueError(f"output folder {out} exists and is {what}")
    taken = folder_named_as_output(out, names)
    if taken is not None:
        raise ValueError(f"output folder {out} holds a folder named {taken}, the name of an "
                         f"output file: move it away or choose another folder")
    created = []                     # the folders made here, the outermost first
    parent = staging_parent(out)
    stage = None
    try:
        for folder in _missing_folders(out):
            os.mkdir(folder)
            created.append(folder)
        stage = tempfile.mkdtemp(prefix=".membranes-probe-", dir=parent)
        probe = os.path.join(stage, ".membranes-probe")
        with open(probe, "w") as f:
            f.write("probe\n")
        os.replace(probe, os.path.join(out, ".membranes-probe"))
        os.remove(os.path.join(out, ".membranes-probe"))
    except OSError as e:
        reason = e.strerror or str(e)
        raise ValueError(f"output folder {out} cannot be written: {reason}") from None
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        for folder in reversed(created):
            try:
                os.rmdir(folder)
            except OSError:
                pass


def _missing_folders(out):
    """The folders from the first missing ancestor of `out` down to `out` itself."""
    missing = []
    while not os.path.exists(out):
        missing.append(out)
        parent = os.path.dirname(out)
        if parent == out:
            break
        out = parent
    return missing[::-1]
