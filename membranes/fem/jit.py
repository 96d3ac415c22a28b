"""Compiled forms found in the JIT cache once per process.

dolfinx compiles every form and element through FFCx, which keeps the compiled modules in
one cache directory (``~/.cache/fenics``, shared by every FEniCS program of the user). At each
lookup FFCx's `get_cached_module` makes a new importlib finder and lists that whole directory
again, so each `dolfinx.fem.form` and each function space costs time in proportion to the
number of files in the cache (four per compiled module), however often the same form was
found before; a solve makes some fifty lookups. `cached_module` below keeps one finder per
cache directory, which lists the directory again only when it has changed (a module compiled
meanwhile, by this process or another), and the modules it has loaded, which are found again
without any listing. Whatever is not yet compiled and ready goes through FFCx's own function
unchanged (it creates the C file, compiles, or waits for another process to finish), so the
cache's protocol between processes stays FFCx's.

**Compilations a run left unfinished.** FFCx takes a C file without its `.c.cached` marker
for a compilation under way in another process, waits for it (`timeout`, 10 s) and then fails
with a TimeoutError. A run ended by a signal during its first compilations (Ctrl-C in a first
solve, a batch system's time limit) left such a file, and every later run needing that form
waited and failed, until the file was removed by hand. So the C files this process creates
are remembered until they are ready (`_compiling`), and removed if a signal ends the run
before (`abandon`, called by membranes.app.interrupts' handler); and a lookup that times out
drops the C file it waited for and compiles the form itself (a process killed outright, or a
compilation in another process slower than the wait; two processes may then both compile it).

A cache folder that cannot be written (a home folder that is read-only or missing, as on
some clusters' compute nodes and in containers) made the first compilation fail deep inside a
solve with three chained tracebacks. `check_cache` refuses it before any mesh is built, in one
line that says how to choose another (XDG_CACHE_HOME); a read-only cache that already holds
compiled forms (made beforehand, by `make warmup` in a container image) is accepted, since its
forms load without a write, and a form missing from it is refused in the same words where FFCx
would have to compile it, on every process (`_route_collective_errors`).
"""

import errno
import importlib.machinery
import importlib.util
import os

# the errors of a write into a folder that cannot take it (not FFCx's TimeoutError, also an
# OSError: a compilation that another process left unfinished)
UNWRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.ENOSPC,
              errno.EDQUOT)

_loaded = {}       # (cache directory, module name) -> module
_compiling = set()  # the C files this process created whose compilation it has not seen ready
_finders = {}      # cache directory -> importlib FileFinder (lists again when the dir changes)


def _finder(cache_dir):
    finder = _finders.get(cache_dir)
    if finder is None:
        finder = _finders[cache_dir] = importlib.machinery.FileFinder(
            cache_dir, (importlib.machinery.ExtensionFileLoader,
                        importlib.machinery.EXTENSION_SUFFIXES))
    return finder


def cached_module(module_name, object_names, cache_dir, timeout, *, ffcx_lookup):
    """FFCx's `get_cached_module(module_name, object_names, cache_dir, timeout)`, with the
    modules that are ready found by a kept finder and loaded once per process."""
    key = (str(cache_dir), module_name)
    module = _loaded.get(key)
    if module is None:
        if not os.path.exists(os.path.join(key[0], module_name + ".c.cached")):
            return _ffcx_lookup(module_name, object_names, cache_dir, timeout, ffcx_lookup)
        spec = _finder(key[0]).find_spec(module_name)
        if spec is None:          # written within the finder's last listing's mtime tick
            return _ffcx_lookup(module_name, object_names, cache_dir, timeout, ffcx_lookup)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        _loaded[key] = module
    return [getattr(module.lib, name) for name in object_names], module


def _ffcx_lookup(module_name, object_names, cache_dir, timeout, ffcx_lookup):
    """FFCx's lookup of a module not ready in the cache; once more, after dropping the C file
    it waited for, if it timed out (module notes). Remembers the C file this process then
    compiles (FFCx's answer (None, None): it created the file)."""
    c_file = os.path.join(str(cache_dir), module_name + ".c")
    _prune()
    try:
        found = ffcx_lookup(module_name, object_names, cache_dir, timeout)
    except TimeoutError:
        _remove(c_file)
        found = ffcx_lookup(module_name, object_names, cache_dir, timeout)
    if found[0] is None:
        _compiling.add(c_file)
    return found


def _prune():
    """Forget the compilations of this process that are ready."""
    _compiling.difference_update([c for c in _compiling if os.path.exists(c + ".cached")])


def _remove(path):
    try:
        os.remove(path)
    except FileNotFoundError:
        pass


def abandon():
    """Remove the C files of this process's compilations that are not ready (a signal ends
    the run): else the next run would wait for them and fail (module notes)."""
    _prune()
    for c_file in list(_compiling):
        _remove(c_file)
    _compiling.clear()


def cache_folder():
    """The folder dolfinx compiles forms into: its JIT parameter `cache_dir` (its own rule:
    $XDG_CACHE_HOME/fenics, by default ~/.cache/fenics, the JSON parameter files of
    dolfinx.jit taking priority)."""
    from dolfinx import jit
    return str(jit.get_parameters()["cache_dir"])


UNWRITABLE_TEXT = "the JIT cache folder "     # how `_unwritable`'s message begins


def _unwritable(folder, reason):
    return ValueError(f"{UNWRITABLE_TEXT}{folder} cannot be written ({reason}): dolfinx "
                      f"compiles the forms there; set XDG_CACHE_HOME to a writable folder")


def _look_at_cache(folder):
    try:
        os.makedirs(folder, exist_ok=True)       # (as FFCx does before it compiles)
    except OSError as e:
        raise _unwritable(folder, e.strerror or str(e)) from None
    if not os.access(folder, os.W_OK | os.X_OK) and \
            not any(name.endswith(".c.cached") for name in os.listdir(folder)):
        raise _unwritable(folder, "no write permission")


def check_cache(comm=None):
    """ValueError (one line, on every process of `comm`) if forms cannot be compiled into
    the JIT cache folder: it cannot be created, or it is not writable and holds no compiled
    form (module notes). Process 0 looks: it compiles, the others load (dolfinx.jit)."""
    from ..model.folders import looked_at_on_rank0
    looked_at_on_rank0(lambda: _look_at_cache(cache_folder()), comm)


def install():
    """Route FFCx's cache lookups through `cached_module` (once; `membranes.fem` does it on
    import, before any form is compiled)."""
    import ffcx.codegeneration.jit as ffcx_jit
    original = ffcx_jit.get_cached_module
    if getattr(original, "membranes", False):
        return

    def get_cached_module(module_name, object_names, cache_dir, timeout):
        try:
            return cached_module(module_name, object_names, cache_dir, timeout,
                                 ffcx_lookup=original)
        except OSError as e:     # (a read-only cache without this form: module notes)
            if e.errno not in UNWRITABLE:
                raise
            raise _unwritable(cache_dir, e.strerror or str(e)) from None

    get_cached_module.membranes = True
    ffcx_jit.get_cached_module = get_cached_module
    _route_collective_errors()


COLLECTIVE = "Failed just-in-time compilation of form: "   # dolfinx.jit's text, every process


def _route_collective_errors():
    """On several processes dolfinx's JIT compiles on process 0 and raises an error met there
    on every process as a RuntimeError (COLLECTIVE), the others without its text. Where it
    is a cache folder that cannot be written (`_unwritable`), every process raises that
    ValueError instead, with process 0's text (one line and exit 2 from the command line,
    as serially, where FFCx's lookup raises it directly)."""
    import dolfinx.jit
    original = dolfinx.jit.ffcx_jit
    if getattr(original, "membranes", False):
        return

    def ffcx_jit(comm, *args, **kwargs):
        try:
            return original(comm, *args, **kwargs)
        except RuntimeError as e:
            if comm.size == 1 or not str(e).startswith(COLLECTIVE):
                raise
            said = comm.bcast(str(e)[len(COLLECTIVE):] if comm.rank == 0 else None, root=0)
            if not said.startswith(UNWRITABLE_TEXT):
                raise
            raise ValueError(said) from None

    ffcx_jit.membranes = True
    dolfinx.jit.ffcx_jit = ffcx_jit
