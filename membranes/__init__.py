"""membranes: contact of two elastic membranes, adaptive inexact semismooth Newton with
guaranteed a posteriori error bounds, on dolfinx and PETSc (docs/theory.md).

Subpackages (docs/architecture.md): model (problem data, scenes), fem (meshes, hierarchy,
discretisation), nonlinear (C-functions, Newton systems, the Newton loop), linalg (Krylov
solvers), estimation (liftings, flux equilibration, algebraic fluxes, estimators), app
(`solve`, the SNES VI peer, outputs, report, command line).
"""

from .app.driver import solve  # noqa: F401
from .app.setups import Setups  # noqa: F401
from .app.solution import Solution  # noqa: F401
from .model import scenes  # noqa: F401
from .model.problem import Problem  # noqa: F401

__version__ = "0.2.0"
