"""The JIT cache lookups (membranes.fem.jit): a compiled form found once is found again
without listing the cache directory, and a module another process puts into the cache
meanwhile is found by the kept listing, which is made anew when the directory changes."""

import importlib.machinery
import os
import pathlib
import shutil
import signal
import time

import dolfinx.jit
import numpy as np
import pytest
import ufl
from dolfinx import fem, mesh
from mpi4py import MPI

import membranes.fem  # noqa: F401  (installs the lookups)
from membranes.fem import jit
from membranes.forms.membrane import contact_term, membrane_linear


@pytest.fixture
def listings(monkeypatch):
    """Counts the listings of any directory by importlib's FileFinder (FFCx's lookups made a
    new finder, and so one listing of the cache, per form and per function space)."""
    count = []
    fill = importlib.machinery.FileFinder._fill_cache

    def counted(self):
        count.append(self.path)
        return fill(self)
    monkeypatch.setattr(importlib.machinery.FileFinder, "_fill_cache", counted)
    return count


@pytest.fixture
def lookups(monkeypatch):
    """The (module name, whether FFCx's own lookup ran) of each cache lookup."""
    seen = []
    ours = jit.cached_module

    def recorded(name, objects, cache_dir, timeout, *, ffcx_lookup):
        def original(*args):
            seen[-1] = (name, True)
            return ffcx_lookup(*args)
        seen.append((name, False))
        return ours(name, objects, cache_dir, timeout, ffcx_lookup=original)
    monkeypatch.setattr(jit, "cached_module", recorded)
    return seen


def _load(n, cache_dir=None):
    """∫ v dx for the P1 hat functions v on an n × n unit square: the lumped masses, which
    sum to 1 (a form of forms/membrane.py, compiled by the warm-up)."""
    square = mesh.create_unit_square(MPI.COMM_SELF, n, n)
    V = fem.FunctionSpace(square, ("Lagrange", 1))
    params = {} if cache_dir is None else {"cache_dir": str(cache_dir)}
    form = fem.form(membrane_linear(ufl.as_ufl(1.0), ufl.TestFunction(V)), jit_params=params)
    return fem.assemble_vector(form).array.sum()


def test_found_again_without_listing_the_cache(listings, lookups):
    assert _load(3) == pytest.approx(1.0, rel=1e-14)
    first = len(lookups)
    assert first >= 2                                  # the space's element and the form
    listings.clear()
    assert _load(5) == pytest.approx(1.0, rel=1e-14)   # another mesh, the same modules
    assert len(lookups) == 2 * first and not listings
    assert lookups[first:] == lookups[:first]
    assert not any(ran for _, ran in lookups[first:])


def test_module_put_into_the_cache_meanwhile_is_found(tmp_path, lookups):
    """Two compiled modules put into an empty cache directory one after the other, as another
    process would (copied from the default cache): each is found by the kept finder, which
    lists the directory again once it has changed; FFCx's own lookup never runs."""
    V = fem.FunctionSpace(mesh.create_unit_square(MPI.COMM_SELF, 4, 4), ("Lagrange", 1))
    v = ufl.TestFunction(V)
    forms = [membrane_linear(ufl.as_ufl(1.0), v), contact_term(ufl.as_ufl(1.0), v)]
    lookups.clear()
    expected = [fem.assemble_vector(fem.form(L)).array for L in forms]
    names = [name for name, _ in lookups]
    assert len(set(names)) == 2
    home = pathlib.Path(dolfinx.jit.get_parameters()["cache_dir"])
    cache = tmp_path / "cache"
    cache.mkdir()
    lookups.clear()
    for name, L, b in zip(names, forms, expected):
        for path in home.glob(name + ".*"):
            shutil.copy2(path, cache / path.name)
        got = fem.assemble_vector(fem.form(L, jit_params={"cache_dir": str(cache)})).array
        assert np.array_equal(got, b)
    assert lookups == [(name, False) for name in names]


def test_a_form_compiled_into_a_folder_that_cannot_be_written_says_so(tmp_path):
    """A form that must be compiled into a cache folder that cannot be written (here one under
    a file, NotADirectoryError; a read-only cache without the form, PermissionError, alike): a
    ValueError naming the folder and XDG_CACHE_HOME, instead of FFCx's chained tracebacks."""
    (tmp_path / "file").write_text("")
    cache = tmp_path / "file" / "fenics"
    V = fem.FunctionSpace(mesh.create_unit_square(MPI.COMM_SELF, 2, 2), ("Lagrange", 1))
    with pytest.raises(ValueError, match=rf"^the JIT cache folder {cache} cannot be written "
                                         r"\(Not a directory\): .* set XDG_CACHE_HOME"):
        fem.form(membrane_linear(ufl.as_ufl(1.0), ufl.TestFunction(V)),
                 jit_params={"cache_dir": str(cache)})


def test_an_unwritable_cache_is_refused_unless_it_holds_forms(tmp_path, monkeypatch):
    """`check_cache` on a folder without write permission (os.access patched: this may run as
    root, who may write anywhere): refused while it holds no compiled form, accepted once it
    holds one (a cache made beforehand, e.g. by `make warmup` in a container image, whose
    forms load without a write)."""
    cache = tmp_path / "fenics"
    monkeypatch.setattr(jit, "cache_folder", lambda: str(cache))
    monkeypatch.setattr(jit.os, "access", lambda path, mode: False)
    with pytest.raises(ValueError, match=r"cannot be written \(no write permission\)"):
        jit.check_cache(MPI.COMM_WORLD)
    (cache / "libffcx_forms_0.c.cached").write_text("")
    jit.check_cache(MPI.COMM_WORLD)


def _a_compiled_form(tmp_path, lookups):
    """A small linear form compiled in the usual cache: the form, its assembled vector, its
    module's name, the usual cache folder and an empty one made under tmp_path."""
    V = fem.FunctionSpace(mesh.create_unit_square(MPI.COMM_SELF, 3, 3), ("Lagrange", 1))
    L = membrane_linear(ufl.as_ufl(1.0), ufl.TestFunction(V))
    lookups.clear()
    expected = fem.assemble_vector(fem.form(L)).array
    name, = [name for name, _ in lookups if name.startswith("libffcx_forms_")]
    home = pathlib.Path(dolfinx.jit.get_parameters()["cache_dir"])
    cache = tmp_path / "cache"
    cache.mkdir()
    return L, expected, name, home, cache


def test_a_compilation_left_unfinished_is_made_again(tmp_path, lookups):
    """A C file without its `.c.cached` marker, as a run killed during its first compilation
    leaves (here the form's C file copied alone into an empty cache): FFCx waits for it and
    times out; the lookup then drops the file and compiles the form itself, which assembles
    as before. The later runs failed with FFCx's TimeoutError until the file was removed by
    hand."""
    L, expected, name, home, cache = _a_compiled_form(tmp_path, lookups)
    shutil.copy2(home / (name + ".c"), cache / (name + ".c"))
    params = {"cache_dir": str(cache), "timeout": 1}
    got = fem.assemble_vector(fem.form(L, jit_params=params)).array
    assert np.array_equal(got, expected)
    assert (cache / (name + ".c.cached")).exists()


def test_abandon_removes_the_compilations_not_ready(tmp_path, monkeypatch):
    """A signal's handler (membranes.app.interrupts) removes the C files of this process's
    compilations that are not ready, so that the next run does not wait for them; a ready
    one (its `.c.cached` written) is left."""
    from membranes.app import interrupts
    ready, unfinished = tmp_path / "a.c", tmp_path / "b.c"
    for path in (ready, unfinished, tmp_path / "a.c.cached"):
        path.write_text("")
    monkeypatch.setattr(jit, "_compiling", {str(ready), str(unfinished)})
    previous = interrupts.install()
    try:
        with pytest.raises(interrupts.Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5.0)
        interrupts.caught()
    finally:
        interrupts.restore(previous)
    assert ready.exists() and not unfinished.exists() and not jit._compiling


def test_a_form_that_cannot_be_compiled_into_the_cache_on_two_processes(tmp_path):
    """On two processes dolfinx compiles on process 0 and raised an error met there as its
    own RuntimeError on both, the other without its text: a form that must be compiled into
    a cache folder that cannot be written is refused with the same ValueError on both (one
    line from the command line, as serially). Each process's error is gathered on process
    0, which prints them as one JSON line (lines printed by two processes may interleave)."""
    import json

    from tests.conftest import mpirun
    (tmp_path / "file").write_text("")
    cache = tmp_path / "file" / "fenics"
    source = "\n".join([
        "import json, sys", "import ufl", "from dolfinx import fem, mesh",
        "from mpi4py import MPI", "import membranes.fem",
        "from membranes.forms.membrane import membrane_linear", "comm = MPI.COMM_WORLD",
        "V = fem.FunctionSpace(mesh.create_unit_square(comm, 2, 2), ('Lagrange', 1))",
        "try:",
        "    fem.form(membrane_linear(ufl.as_ufl(1.0), ufl.TestFunction(V)),",
        "             jit_params={'cache_dir': sys.argv[1]})",
        "    said = 'compiled'",
        "except Exception as e:",
        "    said = f'{type(e).__name__}: {e}'",
        "said = comm.gather(said, root=0)",
        "if comm.rank == 0:",
        "    print(json.dumps(said), flush=True)"])
    proc = mpirun(["-c", source, cache], processes=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    said = (f"ValueError: the JIT cache folder {cache} cannot be written (Not a directory): "
            f"dolfinx compiles the forms there; set XDG_CACHE_HOME to a writable folder")
    assert json.loads(proc.stdout) == [said, said]


def test_a_module_without_its_marker_is_not_loaded(tmp_path, lookups):
    """A compiled module whose `.c.cached` marker is missing (a compilation killed between
    its link and the marker, or still linking in another process: the library may be half
    written) is not loaded from the cache: FFCx's lookup takes it as a compilation under
    way, waits for it, and the form is compiled again, marker and all."""
    L, expected, name, home, cache = _a_compiled_form(tmp_path, lookups)
    copied = [path for path in home.glob(name + ".*") if not path.name.endswith(".cached")]
    assert {p.suffix for p in copied} >= {".c", ".so"}
    for path in copied:
        shutil.copy2(path, cache / path.name)
    lookups.clear()
    params = {"cache_dir": str(cache), "timeout": 1}
    got = fem.assemble_vector(fem.form(L, jit_params=params)).array
    assert np.array_equal(got, expected)
    assert lookups == [(name, True)] and (cache / (name + ".c.cached")).exists()


def test_the_compilations_ffcx_starts_are_remembered_until_ready(tmp_path, monkeypatch):
    """FFCx's lookup answers (None, None) when it created the C file and this process must
    compile it: that file is remembered (`abandon` removes it while its `.c.cached` is
    missing); a module FFCx found, or whose compilation another process finished, is not
    (its C file is left)."""
    monkeypatch.setattr(jit, "_compiling", set())

    def ffcx(created):
        def lookup(name, object_names, cache_dir, timeout):
            (pathlib.Path(cache_dir) / (name + ".c")).write_text("")
            return (None, None) if created else (["compiled"], "module")
        return lookup
    assert jit.cached_module("mine", [], tmp_path, 1, ffcx_lookup=ffcx(True)) == (None, None)
    assert jit.cached_module("theirs", [], tmp_path, 1, ffcx_lookup=ffcx(False)) == \
        (["compiled"], "module")
    assert jit._compiling == {str(tmp_path / "mine.c")}
    jit.abandon()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["theirs.c"] and not jit._compiling


def test_a_cache_without_write_permission_is_refused(tmp_path, monkeypatch):
    """`check_cache` asks for the permissions a compilation needs in the folder, writing and
    entering (os.access patched as the permissions of a read-only folder: this may run as
    root); a folder that may be read and entered but not written, without compiled forms,
    is refused."""
    cache = tmp_path / "fenics"
    monkeypatch.setattr(jit, "cache_folder", lambda: str(cache))
    monkeypatch.setattr(jit.os, "access", lambda path, mode: not mode & os.W_OK)
    with pytest.raises(ValueError, match=r"cannot be written \(no write permission\)"):
        jit.check_cache(MPI.COMM_WORLD)
