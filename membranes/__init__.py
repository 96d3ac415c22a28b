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
import importlib.util
import os
import sys

__version__ = "0.2.0"


def _forms_beside():
    """The UFL forms, `forms/` (UFL only), are imported as `membranes.forms`: an install holds
    them there (pyproject.toml), the source tree beside this package, where they are loaded
    under that name here. Not as a top-level `forms`, which a user's own forms.py beside
    their script would shadow (`from membranes import solve` failed in such a folder)."""
    here = os.path.dirname(os.path.abspath(__file__))
    root = os.path.join(os.path.dirname(here), "forms")
    if os.path.isdir(os.path.join(here, "forms")) or "membranes.forms" in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(
        "membranes.forms", os.path.join(root, "__init__.py"), submodule_search_locations=[root])
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    globals()["forms"] = module          # (as the import system sets a loaded submodule)


_forms_beside()

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
