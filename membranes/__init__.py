"""membranes: contact of two elastic membranes, semismooth Newton, a posteriori error bounds.

The mathematics is in DESIGN.md (shared with the project); the modules are named after it:
problem (data), meshes and hierarchy, discretisation (P1, lumped contact), cfunctions,
newton_system, linear_solve, newton, scenes, decoupled (the SNES VI peer), driver (`solve`),
outputs and cli.
"""

from .driver import Solution, solve  # noqa: F401
from .problem import Problem  # noqa: F401
from . import scenes  # noqa: F401

__version__ = "0.1.0"
