"""The software a run used, by version: `membranes --version`, the `software` key of
summary.json and the opening lines of report.md and stability.md (docs/outputs.md).

A bound, a time or an iteration count is reproducible only with the stack that made it:
dolfinx's assembly and FFCx's kernels (the forms of `forms/`), PETSc's solvers and hypre's
BoomerAMG (the Krylov counts), MPI. The Python packages are read from their installed
metadata, so `membranes --version` imports none of them (lean runs); PETSc's and MPI's
library versions are asked of the libraries, and only where a run has loaded them already.
"""

import functools
import platform
import sys
from importlib import metadata

from .. import __version__

# distribution name -> the name summary.json gives it (Debian's python3-dolfinx installs the
# FEniCSx packages under their PyPI names)
PACKAGES = (("fenics-dolfinx", "dolfinx"), ("fenics-basix", "basix"), ("fenics-ufl", "ufl"),
            ("fenics-ffcx", "ffcx"), ("petsc4py", "petsc4py"), ("mpi4py", "mpi4py"),
            ("numpy", "numpy"))


@functools.lru_cache(maxsize=None)     # (an installed version does not change in a run)
def _installed(distribution):
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def software(libraries=True):
    """{name: version} of membranes, Python, the FEniCSx packages, petsc4py, mpi4py and numpy
    (None: not installed), and with `libraries` the PETSc and MPI libraries that petsc4py and
    mpi4py load, where this process has imported them; the platform last."""
    out = {"membranes": __version__,
           "python": platform.python_version()}
    out.update({name: _installed(distribution) for distribution, name in PACKAGES})
    if libraries:
        if "petsc4py.PETSc" in sys.modules:
            out["PETSc"] = ".".join(map(str, sys.modules["petsc4py.PETSc"].Sys.getVersion()))
        if "mpi4py.MPI" in sys.modules:
            # the first line of MPI_Get_library_version ("Open MPI v4.1.4, ...")
            text = sys.modules["mpi4py.MPI"].Get_library_version().strip()
            out["MPI"] = text.splitlines()[0].split(",")[0] if text else None
    out["platform"] = platform.platform()
    return out


def one_line(versions):
    """`name version` pairs joined by commas (the platform in brackets at the end)."""
    parts = [f"{name} {value}" for name, value in versions.items()
             if name != "platform" and value is not None]
    return ", ".join(parts) + (f" ({versions['platform']})" if versions.get("platform") else "")
