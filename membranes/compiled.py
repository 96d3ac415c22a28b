"""Compiled loops: numba's `njit` (nopython mode, machine code cached on disk next to the
module), applied at a kernel's first call.

Some passes of the estimators' set-up and evaluation (DESIGN §5–§7) are loops over patches or
cells whose per-item work is a few dozen operations with table look-ups: as numpy passes they
make many temporaries of O(N) entries each, as one compiled loop they touch each item once.
These kernels are plain functions of arrays, in the modules of the mathematics they serve,
decorated with `kernel`; numba (Debian's python3-numba, installed with dolfinx's basix; the
dolfinx demos use it for their kernels) is imported only when a kernel first runs, and its
compiled code is cached in `__pycache__`, so a later process loads it in milliseconds.

A kernel calls no other kernel (its wrapper is a Python function). A small formula that
several kernels share is a `part`: a plain function of scalars, compiled into every kernel of
its module that calls it (the kernel is compiled with its module's globals, each part among
them replaced by its compiled form), and callable from Python as it is.
"""

import functools
import types


def kernel(f):
    """`f` compiled by numba at its first call (`f.py_func`: the Python function)."""
    @functools.wraps(f)
    def call(*args):
        return _compiled(f)(*args)
    call.py_func = f
    return call


def part(f):
    """`f`, marked as a formula that kernels of its module call (module notes)."""
    f.kernel_part = True
    return f


@functools.lru_cache(maxsize=None)
def _compiled(f):
    import numba
    parts = {name: _compiled_part(g) for name, g in f.__globals__.items()
             if getattr(g, "kernel_part", False)}
    if parts:
        f = types.FunctionType(f.__code__, {**f.__globals__, **parts}, f.__name__,
                               f.__defaults__, f.__closure__)
    return numba.njit(cache=True, nogil=True)(f)


@functools.lru_cache(maxsize=None)
def _compiled_part(f):
    import numba
    return numba.njit(nogil=True)(f)
