"""Compiled loops: numba's `njit` (nopython mode), its machine code kept on disk as an
extension module per kernel and argument types, which a later process imports without numba.

Some passes of the estimators' set-up and evaluation (DESIGN §5–§7) are loops over patches or
cells whose per-item work is a few dozen operations with table look-ups: as numpy passes they
make many temporaries of O(N) entries each, as one compiled loop they touch each item once.
These kernels are plain functions of arrays, in the modules of the mathematics they serve,
decorated with `kernel`; numba (Debian's python3-numba, installed with dolfinx's basix; the
dolfinx demos use it for their kernels) compiles a kernel at its first call for the types of
its arguments.

**Kept on disk.** numba's own cache (`cache=True`) loads a kernel's machine code in ~3 ms, but
only after numba's import and the set-up of its CPU target and typing context: 0.25 s, the
largest fixed cost of a fresh process's solve (benchmarks/bench_fixed_costs.py). So a kernel
compiled for argument types it had not met is also compiled ahead of time (numba.pycc, the same
nopython code for this machine's CPU) into an extension module in `__pycache__/kernels` next
to its module, named after the kernel, its types and its source file's size and time (as
numba's cache keys on them: an edited module is compiled again); a later process imports that
module (a fraction of a millisecond) and never imports numba. Building a module takes a few
seconds, once per kernel, argument types and edit of its source file. Where the types are not
plain (arrays, Python and numpy scalars: `_type_key`) or the module cannot be built, the
kernel runs as numba's njit (a failed build leaves a marker next to where the module would
be, so that later processes go straight to njit instead of trying again for seconds).

A kept module releases the GIL while its kernel runs (numba's compiler flag release_gil, which
njit's nogil sets too; pycc's modules keep the GIL otherwise), so that two threads run kernels
at once (membranes.pipeline: the estimator process uses process 0's core while it waits).

A kernel calls no other kernel (its wrapper is a Python function). A small formula that
several kernels share is a `part`: a plain function of scalars, compiled into every kernel
that has it among its module's globals, defined there or imported (the kernel is compiled with
its module's globals, each part among them replaced by its compiled form; a kept module is
keyed on the part's source file too), and callable from Python as it is.
"""

import functools
import hashlib
import importlib.machinery
import importlib.util
import os
import sys
import tempfile
import types

import numpy as np


def kernel(f):
    """`f` compiled for the types of its arguments at its first call with them (`f.py_func`:
    the Python function)."""
    entries = {}

    @functools.wraps(f)
    def call(*args):
        key = tuple(map(_type_key, args))
        entry = entries.get(key)
        if entry is None:
            entry = entries[key] = _entry(f, key, args)
        return entry(*args)
    call.py_func = f
    return call


def part(f):
    """`f`, marked as a formula that kernels of its module call (module notes)."""
    f.kernel_part = True
    return f


_SCALARS = {bool: ("scalar", "|b1"), int: ("scalar", "<i8"), float: ("scalar", "<f8")}


def _type_key(a):
    """numba's type of an argument (numba.typeof), for arrays and scalars: an array's dtype,
    dimension, layout (C, F or A) and whether it is read-only; a scalar's dtype (a Python bool,
    int, float as numba types them: boolean, int64, float64); None for anything else."""
    if isinstance(a, np.ndarray):
        flags = a.flags
        layout = "C" if flags.c_contiguous else "F" if flags.f_contiguous else "A"
        return ("array", a.dtype.str, a.ndim, layout, not flags.writeable)
    if isinstance(a, np.generic):
        return ("scalar", a.dtype.str)
    return _SCALARS.get(type(a))


def _entry(f, key, args):
    """The callable that runs `f` on arguments of types `key`: the kernel's extension module
    (imported, or built by numba.pycc first), else numba's njit dispatcher."""
    if None in key:
        return _compiled(f)
    path = _module_path(f, key)
    name = os.path.basename(path).split(".")[0]
    failed = path + ".failed"           # a build that failed is not tried again by every process
    if os.path.exists(failed):
        return _compiled(f)
    if not os.path.exists(path):
        try:
            _build(f, args, path)
        except Exception:       # not compilable ahead of time: numba's njit, as before
            try:
                os.makedirs(os.path.dirname(failed), exist_ok=True)
                open(failed, "w").close()
            except OSError:
                pass
            return _compiled(f)
    try:
        spec = importlib.util.spec_from_file_location(
            name, path, loader=importlib.machinery.ExtensionFileLoader(name, path))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return getattr(module, f.__name__)
    except (ImportError, AttributeError):     # a damaged module: numba's njit
        return _compiled(f)


def _module_path(f, key):
    """Where the extension module of `f` for argument types `key` is kept: named after the
    kernel's module and name, a digest of its types and one of the path, size and time of its
    source file and of the files of the parts it calls (`_sources`), and of `_toolchain` (a
    module built for an edited source replaces the one before it)."""
    source = f.__code__.co_filename
    types_digest = hashlib.sha1(repr((f.__module__, f.__qualname__, key)).encode()
                                ).hexdigest()[:12]
    files = [(s, os.stat(s).st_size, os.stat(s).st_mtime_ns) for s in _sources(f)]
    stamp = hashlib.sha1(repr((files, _toolchain())).encode()).hexdigest()[:12]
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return os.path.join(os.path.dirname(source), "__pycache__", "kernels",
                        f"{f.__module__.rpartition('.')[2]}_{f.__name__.lstrip('_')}_"
                        f"{types_digest}_{stamp}{suffix}")


@functools.lru_cache(maxsize=None)
def _toolchain():
    """What else a kept module depends on: numba's installation (its time), Python's version,
    and the machine (its code is for this host's CPU)."""
    numba = importlib.util.find_spec("numba")
    return (numba and os.stat(numba.origin).st_mtime_ns, sys.version, os.uname().machine,
            os.uname().nodename, "gil released")


def _build(f, args, path):
    """Compile `f` for the types of `args` ahead of time (numba.pycc, for this machine's CPU)
    into the extension module `path`: built in a temporary directory, then moved in place (a
    process that builds the same module meanwhile moves the same file)."""
    import warnings
    if not _told and sys.stderr.isatty():
        print("membranes: compiling kernels for later runs (once per installation and edit of "
              "their modules; a few seconds each)", file=sys.stderr, flush=True)
        _told.append(True)
    with warnings.catch_warnings():     # numba.pycc imports numpy.distutils (deprecated)
        warnings.simplefilter("ignore", DeprecationWarning)
        _build_module(f, args, path)


_told = []      # whether this process has said that it builds kernels (`_build`)


def _build_module(f, args, path):
    """`_build` without the notice."""
    from numba.pycc import CC, compiler
    dispatcher = _compiled(f)
    signature = _signature(dispatcher, args)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    name = os.path.basename(path).split(".")[0]
    with tempfile.TemporaryDirectory(dir=os.path.dirname(path)) as tmp:
        cc = CC(name)
        cc.output_dir = tmp
        cc.target_cpu = "host"
        cc.verbose = False
        cc.export(f.__name__, signature)(dispatcher.py_func)
        plain = compiler.Flags
        compiler.Flags = _GilFreeFlags(plain)
        try:
            cc.compile()
        finally:
            compiler.Flags = plain
        built, = (os.path.join(tmp, p) for p in os.listdir(tmp) if p.startswith(name + "."))
        os.replace(built, path)
    folder, kept = os.path.split(path)
    stem = kept.split(".")[0]                    # without the suffix (x86_64 has a "_")
    earlier = stem[:stem.rindex("_") + 1]        # the same kernel and types, an older source
    for p in os.listdir(folder):
        if p.startswith(earlier) and p != kept:
            try:
                os.remove(os.path.join(folder, p))
            except OSError:
                pass


def _GilFreeFlags(plain):
    """numba's compiler Flags with release_gil set: pycc's modules keep the GIL otherwise."""
    class Flags(plain):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True
    return Flags


def _signature(dispatcher, args):
    """numba's signature (return and argument types) of the dispatcher for `args`."""
    import numba
    argtypes = tuple(numba.typeof(a) for a in args)
    dispatcher.compile(argtypes)
    return dispatcher.overloads[argtypes].signature


def _parts(f):
    """The parts among the globals of `f`: {name: part}."""
    return {name: g for name, g in f.__globals__.items() if getattr(g, "kernel_part", False)}


def _sources(f):
    """The source files of `f` and of the parts it may call, sorted (the kernel's first)."""
    own = f.__code__.co_filename
    return [own] + sorted({g.__code__.co_filename for g in _parts(f).values()} - {own})


@functools.lru_cache(maxsize=None)
def _compiled(f):
    """numba's njit of `f` with its parts compiled in; cached on disk by numba unless a part
    comes from another module (numba's cache checks the kernel's own file only: an edit of
    the part's file would go unseen)."""
    import numba
    parts = {name: _compiled_part(g) for name, g in _parts(f).items()}
    cache = len(_sources(f)) == 1
    if parts:
        f = types.FunctionType(f.__code__, {**f.__globals__, **parts}, f.__name__,
                               f.__defaults__, f.__closure__)
    return numba.njit(cache=cache, nogil=True)(f)


@functools.lru_cache(maxsize=None)
def _compiled_part(f):
    import numba
    return numba.njit(nogil=True)(f)
