"""The outputs of a run (membranes.app.outputs): summary.json, history.csv and
solution.xdmf + .h5 as documented, read back and compared with the Solution they come from;
written by every process of a parallel run; nothing left behind when a write fails."""

import csv
import json
import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from mpi4py import MPI

from membranes.app import outputs
from membranes.app.driver import solve
from membranes.app.outputs import HISTORY_COLUMNS, staged_folder, write_outputs
from membranes.model import folders, scenes
from tests.conftest import mpirun
from tests.core.mpi_outputs import by_coordinates, gathered, h5_values

# XDMF writes a P1 function's values at the nodes as dolfinx's compute_point_values evaluates
# them (its three basis functions there, to round-off, summed): a few units in the last place
# of the largest value (5 seen) away from the iterate's; 16 ε of the largest allows for that
POINT_VALUES = 16 * np.finfo(float).eps

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
serial_only = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="reads files serially")

SUMMARY_KEYS = {"scene", "description", "n_vertices", "n_cells", "h", "h_coarse", "levels",
                "mu1", "mu2", "g", "processes", "newton", "cfun", "solver", "system",
                "petsc_options", "nu", "max_linear_its", "gamma_lin", "gamma_alg", "alg_flux",
                "nested", "tol", "coarse", "coarse_tol",
                "initial_guess", "per_level", "converged", "reason", "newton_iterations",
                "linear_iterations", "wall_time_s", "final_residual",
                "complementarity_violation", "energy_error", "energy_error_kind", "eta",
                "eta_disc", "eta_lin", "eta_alg", "eta_F", "eta_osc", "eta_C", "eta_lin1",
                "eta_lin2", "eta_lin3", "eta_rem", "bound_guaranteed", "effectivity",
                "estimator_setup_s", "estimator_time_s", "software"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The default method (adaptive, amg, nested) on the disk, J = 1, written out."""
    sol = solve(scenes.disk(h=0.3, levels=1))
    out = tmp_path_factory.mktemp("outputs") / "disk"
    assert write_outputs(sol, str(out)) == str(out)
    return sol, out


def test_files_and_nothing_else(run):
    sol, out = run
    assert sorted(os.listdir(out)) == sorted(outputs.FILES)
    assert [p.name for p in out.parent.iterdir()] == ["disk"]     # no staging folder left


def test_summary_keys_and_values(run):
    sol, out = run
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary) == SUMMARY_KEYS
    expected = outputs.json_safe(sol.summary())
    for key in SUMMARY_KEYS - {"wall_time_s"}:
        assert summary[key] == expected[key], key
    assert summary["solver"] == "amg" and summary["newton"] == "adaptive"
    assert summary["nested"] is True and len(summary["per_level"]) == 2
    # adaptive stops by γ_lin: no Newton tolerance of its own, as γ's are null for the others
    assert summary["tol"] is None and summary["gamma_lin"] == 0.3
    assert summary["converged"] is True and summary["bound_guaranteed"] is True
    # the certificate bounds the error (§7), and the effectivity is their ratio
    assert summary["eta"] >= summary["energy_error"] > 0
    assert summary["effectivity"] == pytest.approx(summary["eta"] / summary["energy_error"],
                                                   rel=1e-15)


def test_summary_names_the_software_that_ran(run):
    """summary.json's `software`: the versions the libraries of this process report of
    themselves (metadata for the packages; PETSc and MPI asked at run time)."""
    import dolfinx
    import ufl
    from petsc4py import PETSc

    import membranes
    software = json.loads((run[1] / "summary.json").read_text())["software"]
    assert software["membranes"] == membranes.__version__
    assert software["dolfinx"] == dolfinx.__version__ and software["ufl"] == ufl.__version__
    assert software["numpy"] == np.__version__
    assert software["PETSc"] == "%d.%d.%d" % PETSc.Sys.getVersion()
    assert software["MPI"] and MPI.Get_library_version().startswith(software["MPI"])


@serial_only
def test_version_option_prints_the_same(capsys):
    """`membranes --version`: exit 0, membranes's version, then the software's in one line."""
    from importlib import metadata

    import membranes
    from membranes.app import cli
    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0
    first, second = capsys.readouterr().out.splitlines()
    assert first == f"membranes {membranes.__version__}"
    assert second.startswith("python ")
    assert f", dolfinx {metadata.version('fenics-dolfinx')}, " in second


def _history(out):
    with open(out / "history.csv") as f:
        reader = csv.DictReader(f)
        return tuple(reader.fieldnames), list(reader)


def _value(cell):
    if cell == "":
        return None
    if cell in ("True", "False"):
        return cell == "True"
    try:
        return int(cell)
    except ValueError:
        pass
    try:
        return float(cell)
    except ValueError:
        return cell


def test_history_is_the_solutions(run):
    sol, out = run
    columns, rows = _history(out)
    assert columns == HISTORY_COLUMNS
    assert len(rows) == len(sol.history)
    for row, rec in zip(rows, sol.history):
        for c in HISTORY_COLUMNS:
            assert _value(row[c]) == rec.get(c), (c, row[c], rec.get(c))
    # the run's own bookkeeping: X⁰ of both levels, Newton steps counted per level, the
    # Krylov steps of the Newton rows adding up, a clock that never goes back
    newton = [r for r in rows if r["kind"] == "newton"]
    assert [r["level"] for r in rows if r["kind"] == "initial"] == ["0", "1"]
    assert len(newton) == sol.newton_iterations
    assert np.array_equal(np.cumsum([int(r["linear_it"]) for r in newton]),
                          [int(r["cumulative_linear_its"]) for r in newton])
    assert int(newton[-1]["cumulative_linear_its"]) == sol.linear_iterations
    times = [float(r["wall_time_s"]) for r in rows]
    assert times == sorted(times) and times[-1] <= sol.wall_time_s
    # adaptive: every Newton row of T_J carries η_lin, and its estimates with the bound
    # unless the gate skipped them (schedule.LevelEstimates), the last one is the
    # certificate; the coarse level stops by its residual, without estimators
    # (coarse='residual', the default)
    finest = str(len(sol.per_level) - 1)
    last = [r for r in newton if r["level"] == finest]
    assert all(r["eta_lin"] != "" and (r["eta"] == "") == (r["bound"] != "True") for r in last)
    assert last[-1]["bound"] == "True"
    assert all(r["eta"] == "" for r in rows if r["level"] != finest)
    assert float(newton[-1]["eta"]) == sol.estimates["eta"]
    assert float(rows[-1]["energy_error"]) == sol.energy_error


@serial_only
def test_solution_h5_reads_back(run):
    """u1, u2, lambda at the vertices and eta on the cells, matched by coordinates: the
    values of the iterate (to the last bits XDMF's point values may change)."""
    sol, out = run
    attributes = {a.get("Name") for a in ET.parse(out / "solution.xdmf").iter("Attribute")}
    assert attributes == {"u1", "u2", "lambda", "eta"}
    mine, theirs = h5_values(str(out)), gathered(sol)
    assert len(mine["u1"][1]) == sol.disc.n_global
    assert len(mine["eta"][1]) == sol.disc.mesh.topology.index_map(2).size_global
    for name in ("u1", "u2", "lambda", "eta"):
        (px, pv), (qx, qv) = mine[name], theirs[name]
        assert np.array_equal(px, qx), name
        assert np.allclose(pv, qv, rtol=0, atol=POINT_VALUES * np.abs(qv).max()), name
    # the boundary values of §2 survive the round trip
    assert np.abs(mine["u1"][1] - sol.problem.g).min() == 0.0


@serial_only
def test_without_estimates_no_eta(tmp_path):
    sol = solve(scenes.disk(h=0.3), newton="exact", solver="direct", estimators=False)
    write_outputs(sol, str(tmp_path / "run"))
    attributes = {a.get("Name") for a in ET.parse(tmp_path / "run" / "solution.xdmf")
                  .iter("Attribute")}
    assert attributes == {"u1", "u2", "lambda"}
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["eta"] is None and summary["effectivity"] is None
    # not computed: null (docs/outputs.md, "The certificate of X"), not 0 seconds
    assert summary["estimator_setup_s"] is None and summary["estimator_time_s"] is None
    assert summary["energy_error"] > 0


# ## Failures leave nothing behind

def test_unwritable_target_is_refused(run):
    sol, _ = run
    with pytest.raises(ValueError, match="cannot be written"):
        write_outputs(sol, "/proc/membranes-out")
    assert not os.path.exists("/proc/membranes-out")


def test_failure_while_writing_leaves_nothing(run, tmp_path, monkeypatch):
    """The XDMF pair is written, then the CSV fails: one line naming the folder and the
    reason (ValueError, exit 2 from the CLI), neither the new folder nor the staging folder
    remain; an existing folder keeps its content."""
    sol, _ = run

    def broken(*args, **kwargs):
        raise OSError("disk full (planted)")

    monkeypatch.setattr(outputs, "write_rows", broken)
    with pytest.raises(ValueError, match="cannot be written into .*new: disk full .planted."):
        write_outputs(sol, str(tmp_path / "new"))
    assert list(tmp_path.iterdir()) == []
    old = tmp_path / "old"
    old.mkdir()
    (old / "summary.json").write_text("previous\n")
    with pytest.raises(ValueError, match="planted"):
        write_outputs(sol, str(old))
    assert [p.name for p in tmp_path.iterdir()] == ["old"]
    assert [p.name for p in old.iterdir()] == ["summary.json"]
    assert (old / "summary.json").read_text() == "previous\n"


@serial_only
def test_output_bytes_bounds_the_files(run):
    """The room asked for (folders.output_bytes) covers the files written, and its data part
    8 (4 T + 5 V) (topology and η per cell, geometry, u1, u2, λ per vertex) is in the HDF5
    file: the estimate is neither short nor loose by more than the fixed extra."""
    sol, out = run
    topology = sol.disc.mesh.topology
    v, t = (topology.index_map(d).size_global for d in (0, 2))
    total = sum(p.stat().st_size for p in out.iterdir())
    assert 8 * (4 * t + 5 * v) <= (out / "solution.h5").stat().st_size
    assert total <= folders.output_bytes(v, t) <= total + folders.OUTPUT_EXTRA
    # the data part is the datasets' own bytes, read back: exact (the size check once
    # counted 3 T, forgetting η, and only the fixed extra hid it on small meshes)
    import h5py
    with h5py.File(out / "solution.h5", "r") as h5:
        datasets = []
        h5.visititems(lambda _, item: datasets.append(item.nbytes)
                      if isinstance(item, h5py.Dataset) else None)
    assert folders.output_bytes(v, t) - folders.OUTPUT_EXTRA == sum(datasets)


def test_no_room_is_refused_before_writing(run, tmp_path, monkeypatch):
    """A filesystem with less room than the outputs need: one line naming the folder and
    both sizes, nothing written (HDF5 would fail halfway, and hang a parallel write)."""
    sol, _ = run
    st = os.statvfs(tmp_path)
    free = st.f_bavail * st.f_frsize
    folders.check_output_room(tmp_path / "a" / "b", 1)               # room enough: silent
    with pytest.raises(ValueError, match=r"a/b has .* MiB free, the outputs need about"):
        folders.check_output_room(tmp_path / "a" / "b", free + 2 ** 30)
    monkeypatch.setattr(outputs, "output_bytes", lambda v, t: free + 2 ** 30)
    with pytest.raises(ValueError, match="MiB free"):
        write_outputs(sol, str(tmp_path / "new"))
    assert list(tmp_path.iterdir()) == []


def test_failed_hdf5_write_is_one_line(run, tmp_path, monkeypatch):
    """dolfinx reports a failed HDF5 write (a full disk) as RuntimeError: the same one-line
    ValueError as any failed write, nothing left behind."""
    from dolfinx.io import XDMFFile
    sol, _ = run

    def failing(self, *args, **kwargs):
        raise RuntimeError("Failed to write HDF5 local dataset into hyperslab.")

    monkeypatch.setattr(XDMFFile, "write_function", failing)
    with pytest.raises(ValueError, match=r"cannot be written into .*new: the HDF5 write "
                                         r"failed \(Failed to write HDF5"):
        write_outputs(sol, str(tmp_path / "new"))
    assert list(tmp_path.iterdir()) == []


def test_staged_folder_moves_only_on_success(tmp_path):
    with staged_folder(tmp_path / "a") as tmp:
        assert os.path.dirname(tmp) == str(tmp_path)            # beside a missing target
        (open(os.path.join(tmp, "x.txt"), "w")).write("x\n")
        assert not (tmp_path / "a").exists()
    assert (tmp_path / "a" / "x.txt").read_text() == "x\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]
    # an existing target holds the staging folder: writing it must not need its parent
    with staged_folder(tmp_path / "a") as tmp:
        assert os.path.dirname(tmp) == str(tmp_path / "a")
        (open(os.path.join(tmp, "y.txt"), "w")).write("y\n")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["x.txt", "y.txt"]


def _previous_run(out):
    """A folder `out` with an older run's files: the names of the outputs, and a note."""
    out.mkdir()
    for name in ("a.txt", "b.txt", "notes.txt"):
        (out / name).write_text(f"old {name}\n")


def _unchanged(out):
    return {p.name: p.read_text() for p in out.iterdir()} == {
        name: f"old {name}\n" for name in ("a.txt", "b.txt", "notes.txt")}


def test_move_refuses_a_folder_named_as_an_output(tmp_path):
    """An output name taken by a folder in the target: one line naming it, before anything
    moves (the older files stay as they were, no new file stands among them)."""
    out = tmp_path / "run"
    _previous_run(out)
    (out / "c.txt").mkdir()
    with pytest.raises(ValueError, match=r"into .*run: .*run/c.txt: a folder has the name of "
                                         r"an output; nothing was changed"):
        with staged_folder(out) as tmp:
            for name in ("a.txt", "b.txt", "c.txt"):
                (open(os.path.join(tmp, name), "w")).write("new\n")
    (out / "c.txt").rmdir()
    assert _unchanged(out)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]         # no staging folder left


def test_a_move_failing_midway_is_undone(tmp_path, monkeypatch):
    """A rename that fails after others have moved (planted at the second output): the
    outputs moved so far go back, the older files they replaced and the stale file of
    `replaces` are restored, and the staging folder goes."""
    out = tmp_path / "run"
    _previous_run(out)
    real, calls = os.replace, []

    def replace(src, dst):
        calls.append(dst)
        if os.fspath(dst) == str(out / "b.txt") and os.path.basename(src) == "b.txt" \
                and os.path.basename(os.path.dirname(src)) != "old":     # (not its restore)
            raise OSError(28, "No space left on device (planted)", str(dst))
        real(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace)
    with pytest.raises(ValueError, match=r"b.txt: No space left on device .planted.; nothing "
                                         r"was changed"):
        with staged_folder(out, replaces=("notes.txt",)) as tmp:
            for name in ("a.txt", "b.txt"):
                (open(os.path.join(tmp, name), "w")).write("new\n")
    assert str(out / "a.txt") in map(os.fspath, calls)                # a.txt had moved in
    assert _unchanged(out)
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def fail_renames_onto(monkeypatch, path, errno, message):
    """Every `os.replace` of the outputs module onto `path` raises OSError(errno, message);
    the others rename."""
    real = os.replace

    def replace(src, dst):
        if os.fspath(dst) == str(path):
            raise OSError(errno, message, str(dst))
        real(src, dst)

    monkeypatch.setattr(outputs.os, "replace", replace)


def test_a_move_that_cannot_be_undone_keeps_the_older_files(tmp_path, monkeypatch):
    """Where the filesystem refuses the undo too (every rename onto run/b.txt fails), the
    older b.txt is not deleted with the staging folder: the folder stays, and the message
    says where the older files are."""
    import re
    out = tmp_path / "run"
    _previous_run(out)
    fail_renames_onto(monkeypatch, out / "b.txt", 5, "Input/output error (planted)")
    with pytest.raises(ValueError, match="could not be undone in full: the older files are "
                                         "in ") as e:
        with staged_folder(out) as tmp:
            for name in ("a.txt", "b.txt"):
                (open(os.path.join(tmp, name), "w")).write("new\n")
    kept = re.search(r"are in (\S+)$", str(e.value))[1]
    assert open(os.path.join(kept, "b.txt")).read() == "old b.txt\n"
    assert (out / "a.txt").read_text() == "old a.txt\n"          # the rest was undone


def test_staged_folder_replaces_files_it_did_not_make(tmp_path):
    """A file of `replaces` the block did not make goes from the target (an older run's copy
    would stand beside the new files as if it were theirs); the files the block made replace
    theirs, and every other file, or a folder of such a name, stays."""
    out = tmp_path / "a"
    (out / "kept").mkdir(parents=True)
    for name in ("old.png", "new.png", "notes.txt"):
        (out / name).write_text("old\n")
    with staged_folder(out, replaces=("old.png", "new.png", "kept", "absent.png")) as tmp:
        (open(os.path.join(tmp, "new.png"), "w")).write("new\n")
    assert sorted(p.name for p in out.iterdir()) == ["kept", "new.png", "notes.txt"]
    assert (out / "new.png").read_text() == "new\n"
    assert (out / "notes.txt").read_text() == "old\n"


def test_staged_folder_removes_links_named_in_replaces(tmp_path):
    """A link named in `replaces` is an older output too (a file the target held through a
    link, or a link left dangling): it goes, whether it points to a file, to a folder or to
    nothing; the file it pointed to stays."""
    out = tmp_path / "a"
    out.mkdir()
    (tmp_path / "elsewhere.png").write_text("theirs\n")
    (tmp_path / "folder").mkdir()
    os.symlink(tmp_path / "elsewhere.png", out / "file.png")
    os.symlink(tmp_path / "folder", out / "folder.png")
    os.symlink(tmp_path / "nowhere.png", out / "dangling.png")
    with staged_folder(out, replaces=("file.png", "folder.png", "dangling.png")) as tmp:
        (open(os.path.join(tmp, "new.txt"), "w")).write("new\n")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert (tmp_path / "elsewhere.png").read_text() == "theirs\n"


def test_a_move_failing_midway_restores_links_and_removes_new_names(tmp_path, monkeypatch):
    """The undo of a move that fails midway (planted at the last output) leaves the target as
    it was: an output moved in under a name the target did not hold goes again, and one
    that replaced a dangling link puts the link back (a link counts as an older file whether
    or not it points anywhere)."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("old notes.txt\n")
    os.symlink("nowhere.txt", out / "b.txt")
    fail_renames_onto(monkeypatch, out / "c.txt", 28, "No space left on device (planted)")
    with pytest.raises(ValueError, match=r"c.txt: No space left on device .planted.; nothing "
                                         r"was changed"):
        with staged_folder(out) as tmp:
            for name in ("a.txt", "b.txt", "c.txt"):
                (open(os.path.join(tmp, name), "w")).write("new\n")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt", "notes.txt"]
    assert os.readlink(out / "b.txt") == "nowhere.txt"
    assert (out / "notes.txt").read_text() == "old notes.txt\n"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


ROOM_OF_A_DISTRIBUTED_MESH = """
from mpi4py import MPI
from membranes.app.outputs import room_for
from membranes.fem.meshes import unit_disk
from membranes.model.folders import output_bytes
comm = MPI.COMM_WORLD
mesh = unit_disk(0.3, comm)
maps = [mesh.topology.index_map(d) for d in (0, 2)]
owned = [m.size_local for m in maps]
total = [comm.allreduce(n, op=MPI.SUM) for n in owned]
said = comm.gather((room_for(mesh) == output_bytes(*total), owned[0] < total[0]), root=0)
print(repr(said) if comm.rank == 0 else "", flush=True)
"""


def test_room_for_counts_the_whole_distributed_mesh():
    """The room the outputs need (checked before the collective HDF5 write) is that of the
    whole mesh on every process, not of the process's own part: vertices and cells owned
    by each, summed here over the processes (exact: integer counts)."""
    import ast
    proc = mpirun(["-c", ROOM_OF_A_DISTRIBUTED_MESH], timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert ast.literal_eval(proc.stdout.strip().splitlines()[-1]) == [(True, True)] * 2


def test_an_error_in_the_block_passes_on_as_itself(tmp_path):
    """An error of the block that is no failed write (a bug, a bad value) reaches the caller
    as it was raised, not as another process's failure, and nothing is written."""
    out = tmp_path / "a"
    with pytest.raises(KeyError, match="mine"):
        with staged_folder(out) as tmp:
            (open(os.path.join(tmp, "x.txt"), "w")).write("x\n")
            raise KeyError("mine")
    assert list(tmp_path.iterdir()) == []


def test_json_safe():
    value = {"a": np.float64(np.nan), "b": [np.int32(3), np.inf], "c": np.array([1.5]),
             "d": np.bool_(True)}
    assert outputs.json_safe(value) == {"a": None, "b": [3, None], "c": [1.5], "d": True}


def test_json_safe_gives_python_scalars():
    """numpy scalars become the Python ones, not values that only compare equal to them:
    json.dump refuses np.int64, np.bool_ and np.float32 (a count or a flag taken from a numpy
    array would make write_summary fail after the run). Exact: no arithmetic."""
    value = outputs.json_safe({"n": np.int64(3), "ok": np.bool_(True), "x": np.float32(0.5),
                               "inf": np.float64(-np.inf)})
    assert value == {"n": 3, "ok": True, "x": 0.5, "inf": None}
    assert (type(value["n"]), type(value["ok"]), type(value["x"])) == (int, bool, float)
    assert json.loads(json.dumps(value)) == value


def test_json_safe_inside_tuples():
    """Tuples (a pair of figures, a record of several) are made safe as lists are: a nan or
    a numpy scalar inside one reached json.dump as it was, which writes NaN (no JSON) or
    refuses np.int64. Exact: no arithmetic."""
    value = outputs.json_safe({"pair": (np.float64(np.nan), np.int64(2)),
                               "nested": [(np.inf, (np.float32(0.5),))]})
    assert value == {"pair": [None, 2], "nested": [[None, [0.5]]]}
    assert type(value["pair"][1]) is int
    assert json.loads(json.dumps(value, allow_nan=False)) == value


def test_per_level_counts_add_up_to_the_totals(run):
    """summary.json's per_level: each level's own Newton and Krylov steps (not running totals),
    counted independently from the history (its Newton rows on that level and their
    linear_it), and adding up to the run's totals. Integers: exact."""
    sol, _ = run
    assert len(sol.per_level) == 2
    for level in sol.per_level:
        rows = [r for r in sol.history if r["level"] == level["level"] and r["kind"] == "newton"]
        assert level["newton_iterations"] == len(rows)
        assert level["linear_iterations"] == sum(r["linear_it"] for r in rows)
    assert sol.per_level[0]["linear_iterations"] > 0        # (else a running total is the same)
    assert sum(p["newton_iterations"] for p in sol.per_level) == sol.newton_iterations
    assert sum(p["linear_iterations"] for p in sol.per_level) == sol.linear_iterations


def test_returned_iterate_is_the_certified_one(run):
    """The X that `solve` returns (and writes) is the iterate whose energy error and η the
    summary reports: the error measured anew at sol.X by an EnergyError of its own is the
    reported one. The same assembly on the same vector: equal to round-off (1e-12 relative;
    in practice equal); the prolonged start X⁰ of T_J has about twice the error."""
    from membranes.estimation.energy_error import EnergyError
    sol, _ = run
    assert EnergyError(sol.disc)(sol.X) == pytest.approx(sol.energy_error, rel=1e-12)


def test_estimator_times_add_up_over_the_levels(monkeypatch):
    """estimator_setup_s and estimator_time_s: the set-up times and the evaluation times of
    every level that estimates (coarse='estimated': both levels), each summed over the levels,
    in that order. Recorded from the LevelEstimates objects the run made: the same float
    additions in the same order, so exact."""
    from membranes.app import driver
    made = []

    class Recording(driver.LevelEstimates):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(driver, "LevelEstimates", Recording)
    sol = solve(scenes.disk(h=0.4, levels=1), coarse="estimated", errors="none")
    assert len(made) == 2 and all(e.time > 0 for e in made)
    setup, evaluations = 0.0, 0.0
    for e in made:
        setup += e.setup_time
        evaluations += e.time
    assert sol.estimator_times == (setup, evaluations)
    s = sol.summary()
    assert (s["estimator_setup_s"], s["estimator_time_s"]) == (setup, evaluations)


# ## Several processes

@serial_only
@pytest.mark.parametrize("procs", [2, 3])
def test_parallel_write(tmp_path, procs):
    """Every process writes its part of the one HDF5 file: read back serially, the values
    at every vertex and cell are those of the owning process; a failure on one process
    raises on all and leaves nothing."""
    done = mpirun([os.path.join(ROOT, "tests", "core", "mpi_outputs.py"), tmp_path],
                  processes=procs, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    r = json.loads(done.stdout.strip().splitlines()[-1])
    assert r["processes"] == r["summary_processes"] == procs and r["converged"]
    assert r["files"] == sorted(outputs.FILES)
    assert r["left"] == ["run"]                       # no 'failed', no staging folder
    assert r["raised"][-1] == "planted failure"
    assert all("failed on another process" in m for m in r["raised"][:-1])
    # a write that fails on one process (ENOSPC on process 0): one message, the same on all
    # (it was that process's OSError traceback and the others' "failed on another process")
    assert len(set(r["full"])) == 1 and "No space left on device" in r["full"][0]
    assert "cannot be written" in r["full"][0]
    for name in ("u1", "u2", "lambda", "eta"):
        assert r[name]["points"], name
        assert r[name]["max_diff"] <= POINT_VALUES * r[name]["size"], (name, r[name])


def test_by_coordinates_sorts_points():
    x = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    px, pv = by_coordinates(x, np.array([1.0, 2.0, 3.0]))
    assert np.array_equal(pv, [3.0, 2.0, 1.0])         # sorted by x, then y


def test_history_errors_belong_to_their_iterates():
    """errors='iterates': a record estimated with the ν flux of §6 is the iterate handed over
    before (here X^{k,0} = X^{k-1}, linear_it 0: γ_alg = 0.01 makes the first ν steps fall
    short); its energy error is that iterate's, i.e. exactly the previous Newton record's."""
    sol = solve(scenes.disk(h=0.3, levels=1), solver="paper", nested=False, gamma_alg=0.01,
                errors="iterates")
    assert sol.converged
    h = sol.history
    earlier = [k for k, r in enumerate(h) if r["kind"] == "krylov" and r["linear_it"] == 0]
    assert earlier                                     # the case this test is about
    for k in earlier:
        before = next(r for r in reversed(h[:k]) if r["kind"] in ("newton", "initial"))
        assert h[k]["energy_error"] == before["energy_error"]
        assert h[k]["eta"] >= h[k]["energy_error"]
    assert all(r["energy_error"] is not None for r in h)


def test_the_final_record_is_timed_after_its_certificate(monkeypatch):
    """Exact Newton estimates only its final iterate, after Newton ends: that record's
    wall_time_s is taken after the certificate (the certificate is part of X^k), so the run
    ends a moment of bookkeeping after it. The evaluation is slowed by 0.4 s here, so a record
    stamped before the certificate would lie at least 0.4 s before the run's end, whatever
    the machine's load; the bookkeeping takes some 1e-5 s, so the margin 0.2 s is wide."""
    import time

    from membranes.estimation.estimators import Estimators
    evaluate = Estimators.evaluate

    def slow(self, *args, **kwargs):
        out = evaluate(self, *args, **kwargs)
        time.sleep(0.4)
        return out

    monkeypatch.setattr(Estimators, "evaluate", slow)
    sol = solve(scenes.disk(h=0.3), newton="exact", solver="amg", errors="none")
    assert sol.final_record is sol.history[-1] and sol.estimates["bound"]
    assert sol.estimator_times[1] >= 0.4
    assert 0.0 <= sol.wall_time_s - sol.final_record["wall_time_s"] < 0.2


# ## The Solution's own figures

def test_summary_h_coarse_is_the_coarse_mesh_size(run):
    """summary.json's h is T_J's mesh size and h_coarse T_0's, which one refinement of the
    disk roughly halves (the boundary midpoints moved onto the circle: not exactly)."""
    from membranes.fem.meshes import mesh_size
    sol, _ = run
    s, meshes = sol.summary(), sol.problem.hierarchy.meshes
    assert len(meshes) == 2
    assert s["h"] == mesh_size(meshes[-1]) and s["h_coarse"] == mesh_size(meshes[0])
    assert 0.4 < s["h"] / s["h_coarse"] < 0.6


def complementarity_by_hand(comm=MPI.COMM_WORLD):
    """Solution.complementarity_violation on iterates set by hand on the zero-load square (so
    u_data = g, λ_data = 0, and the λ scale is λ_u = g / ((1/μ1 + 1/μ2) (C_PF h_Ω)²) = g π²,
    C_PF h_Ω = 1/(π √2) on the unit square): u2 = 0, u1 = g and λ = 0 but for values set on
    process 0 only, at one interior and one boundary vertex (left out). Returns the pairs
    (violation, its value worked out here), the same on every process."""
    from dataclasses import replace
    sol = solve(scenes.user(domain="square", h=0.3, comm=comm), newton="exact",
                estimators=False)
    d = sol.disc
    g = d.g
    assert g == 0.05 and d.data_scales() == (g, 0.0)
    lam_u = g * np.pi ** 2
    inner, edge = np.flatnonzero(d.interior), np.flatnonzero(~d.interior)
    if comm.rank == 0:
        assert inner.size and edge.size
    i, b = (inner[0], edge[0]) if comm.rank == 0 else (None, None)

    def violation(u1_at, lam_at):
        u1, lam = np.full(d.n, g), np.zeros(d.n)
        if comm.rank == 0:
            for k, v in u1_at.items():
                u1[k] = v
            for k, v in lam_at.items():
                lam[k] = v
        X = d.vector3()
        X.array[:] = np.concatenate([u1, np.zeros(d.n), lam])
        return replace(sol, X=X).complementarity_violation()

    return [
        (violation({}, {}), 0.0),
        # w = -0.01 at an interior vertex (-0.04 on the boundary): 0.01 / u_scale, u_scale = g
        (violation({i: -0.01, b: -0.04}, {}), 0.01 / g),
        # λ = -0.1 λ_u at an interior vertex (-1 on the boundary): 0.1 against λ_u
        (violation({}, {i: -0.1 * lam_u, b: -1.0}), 0.1),
        # w = g/2 and λ = 3 λ_u at one interior vertex: w λ / (u_scale · |λ|∞) = 1/2
        (violation({i: g / 2}, {i: 3 * lam_u}), 0.5)]


def test_complementarity_violation_of_iterates_made_by_hand():
    """Each of the violation's three parts alone (`complementarity_by_hand`), a few float
    operations from the value worked out: 1e-12 relative."""
    for got, expected in complementarity_by_hand():
        assert got == pytest.approx(expected, rel=1e-12, abs=0)


def test_complementarity_violation_is_never_minus_zero():
    """Exact Newton-min on the disk (h = 0.2, J = 2) ends with w = u1 - u2 = 0 where the
    membranes touch and λ = 0 off contact: the maxima of -w, -λ were -0.0, and summary.json
    said "complementarity_violation": -0.0 (a probe's, 2026-12-03)."""
    sol = solve(scenes.disk(h=0.2, levels=2), newton="exact", errors="none")
    violation = sol.complementarity_violation()
    assert violation <= 1e-12 and np.copysign(1.0, violation) == 1.0


@serial_only
def test_complementarity_violation_on_two_processes():
    """The same on two processes, process 0 holding the values set by hand: the maxima
    are over all processes (MPI.MAX, not a sum of the processes' own)."""
    source = ("import json; from mpi4py import MPI; "
              "from tests.core.test_outputs import complementarity_by_hand as by_hand; "
              "pairs = MPI.COMM_WORLD.gather(by_hand()); "
              "MPI.COMM_WORLD.rank or print(json.dumps(pairs))")
    done = mpirun(["-c", source], processes=2)
    assert done.returncode == 0, done.stderr[-2000:]
    pairs = json.loads(done.stdout.strip().splitlines()[-1])
    assert pairs[0] == pairs[1]
    for got, expected in pairs[0]:
        assert got == pytest.approx(expected, rel=1e-12, abs=0)


def _slowed(monkeypatch, cls, name, seconds):
    """cls.name made `seconds` slower (a sleep after the call): a lower bound on its time
    that no machine load lowers."""
    import time
    original = getattr(cls, name)

    def slow(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        time.sleep(seconds)
        return out
    monkeypatch.setattr(cls, name, slow)


def test_adaptive_records_are_timed_after_their_estimates(monkeypatch):
    """The adaptive variant's final record is the Newton iterate whose estimate met the
    stopping test (no estimate after Newton): its wall_time_s is taken after that estimate,
    slowed by 0.4 s here, so the run ends a moment of bookkeeping after it (a record stamped
    before its estimate lies at least 0.4 s before the end; 0.2 s margin as above)."""
    from membranes.estimation.estimators import Estimators
    _slowed(monkeypatch, Estimators, "evaluate", 0.4)
    sol = solve(scenes.disk(h=0.3), newton="adaptive", errors="none")
    assert sol.converged and sol.final_record is sol.history[-1]
    assert sol.final_record["kind"] == "newton" and sol.estimates["bound"]
    assert 0.0 <= sol.wall_time_s - sol.final_record["wall_time_s"] < 0.2


def test_the_start_and_the_level_are_timed_with_the_estimators_set_up(monkeypatch):
    """The estimators' set-up is on the clock and comes before Newton: X⁰ (the adaptive
    variant's first record) is stamped when Newton starts, after it, and the level's
    wall_time_s spans it and every evaluation. The set-up is slowed by 0.5 s, so a stamp
    taken at the level's start, or a level time counted from Newton's start, falls short
    (the rest of the run takes some 0.1 s)."""
    from membranes.estimation.estimators import Estimators
    _slowed(monkeypatch, Estimators, "__init__", 0.5)
    sol = solve(scenes.disk(h=0.3), newton="adaptive", errors="none")
    setup, evaluations = sol.estimator_times
    assert setup >= 0.5
    assert sol.history[0]["kind"] == "initial"
    assert setup <= sol.history[0]["wall_time_s"] <= sol.history[1]["wall_time_s"]
    level = sol.per_level[0]["wall_time_s"]
    assert setup + evaluations <= level <= sol.wall_time_s


@pytest.mark.parametrize("errors", ["iterates", "final"])
def test_energy_errors_are_off_the_clock(errors, monkeypatch):
    """Energy errors are diagnostics, not part of the run's wall time: each evaluation,
    slowed by 0.3 s here, is taken off the clock, so the time measured around `solve`
    exceeds wall_time_s by at least 0.3 s per evaluation (every record's with 'iterates',
    the final iterate's with 'final'), whatever the machine's load."""
    import time

    from membranes.estimation.energy_error import EnergyError
    calls = []
    _slowed(monkeypatch, EnergyError, "__call__", 0.3)
    original = EnergyError.__call__
    monkeypatch.setattr(EnergyError, "__call__",
                        lambda self, X: calls.append(1) or original(self, X))
    started = time.perf_counter()
    sol = solve(scenes.disk(h=0.3), newton="exact", estimators=False, errors=errors)
    elapsed = time.perf_counter() - started
    assert sol.converged
    assert len(calls) == (len(sol.history) if errors == "iterates" else 1)
    assert len(sol.history) >= 3
    assert elapsed - sol.wall_time_s >= 0.3 * len(calls)
    assert all(r["wall_time_s"] <= sol.wall_time_s for r in sol.history)


def test_exact_newton_stops_at_the_default_tol():
    """Without `tol`, exact Newton stops at ‖R_lin‖/‖(F, 0)‖ ≤ 1e-10 (docs, `solve`): the
    summary says 1e-10, the returned iterate meets it and no Newton iterate before it did."""
    sol = solve(scenes.disk(h=0.3), newton="exact", estimators=False, errors="none")
    assert sol.converged and sol.summary()["tol"] == 1e-10
    residuals = [r["residual"] for r in sol.history if r["kind"] in ("initial", "newton")]
    assert residuals[-1] <= 1e-10 < min(residuals[:-1])


def test_history_errors_of_the_eliminated_steps_first_iterates(monkeypatch):
    """As above with the amg preset (the eliminated system, ν = 1): there X^{k,0} is the
    expansion of the solver's initial guess, whose eliminated unknowns follow the new
    linearisation, so it is not X^{k-1}. A record estimated with the ν flux from X^{k,0}
    (linear_it 0) carries the energy error of X^{k,0}, measured here anew at the iterate
    the estimators were handed as kind 'step' (the same assembly on a copy: 1e-12)."""
    from membranes.app import driver
    from membranes.estimation.energy_error import EnergyError
    starts = []

    class Recording(driver.LevelEstimates):
        def __call__(self, X, R, kind=None):
            if kind == "step":
                starts.append(X.copy())
            return super().__call__(X, R, kind)

    monkeypatch.setattr(driver, "LevelEstimates", Recording)
    sol = solve(scenes.disk(h=0.3, levels=1), nested=False, nu=1, gamma_alg=0.01,
                errors="iterates")
    assert sol.converged and sol.options["system"] == "eliminated"
    error = EnergyError(sol.disc)
    steps, moved = 0, 0
    for k, r in enumerate(sol.history):
        if r["kind"] == "newton":
            steps += 1
        elif r["kind"] == "krylov" and r["linear_it"] == 0:
            expected = error(starts[steps])
            assert r["energy_error"] == pytest.approx(expected, rel=1e-12)
            before = next(b for b in reversed(sol.history[:k]) if b["kind"] != "krylov")
            moved += abs(before["energy_error"] - expected) > 1e-3 * expected
    assert moved >= 1                                  # the case this test is about
    for X in starts:
        X.destroy()


@pytest.mark.parametrize("newton", ["adaptive", "exact"])
def test_the_certificate_is_made_once(newton, monkeypatch):
    """Lean runs: the adaptive variant's answer is certified by the full estimate its
    stopping test read, so `solve` estimates nothing after Newton; exact Newton estimates
    only after it, once (the certificate). Counted at the estimators' calls: the calls
    after Newton are those of no kind."""
    from membranes.app import driver
    kinds = []

    class Recording(driver.LevelEstimates):
        def __call__(self, X, R, kind=None):
            kinds.append(kind)
            return super().__call__(X, R, kind)

    monkeypatch.setattr(driver, "LevelEstimates", Recording)
    sol = solve(scenes.disk(h=0.3), newton=newton, errors="none")
    assert sol.converged and sol.final_record["bound"]
    if newton == "exact":                   # (Newton itself estimates nothing)
        assert kinds == [None]
    else:
        assert None not in kinds and kinds[-1] == "newton"


@pytest.mark.parametrize("make,errors", [(lambda: scenes.disk(h=0.3), "none"),
                                         (lambda: scenes.user(h=0.3), "final")])
def test_no_energy_error_no_kind(make, errors):
    """energy_error_kind says what energy_error measures: without an energy error (errors
    'none', or a scene without an exact solution) both are null."""
    sol = solve(make(), newton="exact", estimators=False, errors=errors)
    assert sol.converged and sol.energy_error is None
    assert sol.energy_error_kind is None and sol.summary()["energy_error_kind"] is None
