"""membranes: contact of two elastic membranes, adaptive inexact semismooth Newton with
guaranteed a posteriori error bounds, on dolfinx and PETSc (docs/theory.md).

Subpackages (docs/architecture.md): model (problem data, scenes), fem (meshes, hierarchy,
discretisation), nonlinear (C-functions, Newton systems, the Newton loop), linalg (Krylov
solvers), estimation (liftings, flux equilibration, algebraic fluxes, estimators), app
(`solve`, the SNES VI peer, outputs, report, command line).

The names below (`from membranes import scenes, solve`) are imported when first asked for:
`import membranes` alone, as the command line does before it reads its arguments
(`membranes --help`), imports neither dolfinx nor PETSc (lean runs).
"""

import importlib

__version__ = "0.2.0"

# name -> (module, attribute; None: the module itself)
_EXPORTS = {"solve": ("membranes.app.driver", "solve"),
            "Setups": ("membranes.app.setups", "Setups"),
            "Solution": ("membranes.app.solution", "Solution"),
            "scenes": ("membranes.model.scenes", None),
            "Problem": ("membranes.model.problem", "Problem")}
__all__ = list(_EXPORTS)


def __getattr__(name):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'membranes' has no attribute {name!r}")
    module, attribute = _EXPORTS[name]
    value = importlib.import_module(module)
    value = value if attribute is None else getattr(value, attribute)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
