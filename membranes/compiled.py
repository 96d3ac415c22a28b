"""Compiled loops: numba's `njit` (nopython mode, machine code cached on disk next to the
module), applied at a kernel's first call.

Some passes of the estimators' set-up and evaluation (DESIGN §5–§7) are loops over patches or
cells whose per-item work is a few dozen operations with table look-ups: as numpy passes they
make many temporaries of O(N) entries each, as one compiled loop they touch each item once.
These kernels are plain functions of arrays, in the modules of the mathematics they serve,
decorated with `kernel`; numba (Debian's python3-numba, installed with dolfinx's basix; the
dolfinx demos use it for their kernels) is imported only when a kernel first runs, and its
compiled code is cached in `__pycache__`, so a later process loads it in milliseconds.

A kernel is self-contained: numba compiles only the function itself, so it must not call
another `kernel` (its wrapper is a Python function); share code between kernels by writing
the common loop once in the kernel that needs it.
"""

import functools


def kernel(f):
    """`f` compiled by numba at its first call (`f.py_func`: the Python function)."""
    @functools.wraps(f)
    def call(*args):
        return _compiled(f)(*args)
    call.py_func = f
    return call


@functools.lru_cache(maxsize=None)
def _compiled(f):
    import numba
    return numba.njit(cache=True, nogil=True)(f)
