"""Meshes, the hierarchy, the discretisation (theory §2, §12), and the JIT cache lookups of
the compiled forms (`jit`, installed here, before any form is compiled).

Every module that assembles, refines or reads a mesh comes through here, so here the dolfinx
found is checked first: the code is written against dolfinx 0.5's API (Debian bookworm's
python3-dolfinx 0.5.2, README "Set-up"), which later releases changed (function spaces,
refinement, gmshio, the PETSc assemblers). Another release would fail deep inside a solve
with an AttributeError or a TypeError; `require_dolfinx` says at once what is wrong."""

import re

import dolfinx

from . import jit

DOLFINX = (0, 5)        # the dolfinx release (major, minor) this package is written for


def require_dolfinx(version):
    """ImportError (with `name` 'dolfinx') unless `version` (dolfinx.__version__) is a
    release of `DOLFINX`."""
    found = tuple(int(part) for part in re.findall(r"\d+", version)[:2])
    if found != DOLFINX:
        raise ImportError(f"membranes needs dolfinx {'.'.join(map(str, DOLFINX))}.x (Debian "
                          f"bookworm's python3-dolfinx 0.5.2), found dolfinx {version} "
                          f"(README, Set-up)", name="dolfinx")


require_dolfinx(dolfinx.__version__)
jit.install()
