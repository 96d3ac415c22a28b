"""The exact energy error |||u - u_h||| for scenes with an exact solution (§1, §8, §9).

    |||u - u_h|||² = Σ_K (μ1 ‖∇(u1 - u1h)‖_K² + μ2 ‖∇(u2 - u2h)‖_K²)

with u the scene's exact solution (`problem.exact`: builders x ↦ UFL expression, evaluated on
the mesh's `ufl.SpatialCoordinate`). One assembly of `forms.estimators.energy_squared` tested
with DG0 gives the squares on every cell; the total is their sum over the owned cells, reduced
over the communicator. The integrals use the data measures of `membranes.fem.quadrature`: the
exact gradients are smooth on each cell except across the scene's interface (the disk's
u2 has a kink across r = 1/√2), where the composite rule integrates the cut cells.

The error is measured on the computational polygon Ω_h (the cells of the mesh), which is where
the estimators of §7 bound it.
"""

import numpy as np
import ufl

from ..fem.quadrature import over
from ..forms.estimators import energy_squared
from .cell_forms import CellForm, global_sums


class EnergyError:
    """|||u - u_h||| at an iterate X (the iterate layout of `Discretisation`), compiled once
    per mesh: `__call__(X)` gives the global value (the same on every process), `per_cell(X)`
    the values |||u - u_h|||_K on the owned cells (in the mesh's cell order)."""

    def __init__(self, disc):
        from dolfinx import fem
        from petsc4py import PETSc
        exact = disc.problem.exact
        if exact is None:
            raise ValueError("the energy error needs a scene with an exact solution")
        mesh = disc.mesh
        self.disc = disc
        x = ufl.SpatialCoordinate(mesh)
        u1, u2 = (ufl.as_ufl(b(x)) for b in (exact.u1, exact.u2))
        self.u = [fem.Function(disc.V) for _ in range(3)]
        mu1, mu2 = (fem.Constant(mesh, PETSc.ScalarType(m)) for m in (disc.mu1, disc.mu2))
        uh1, uh2 = self.u[0], self.u[1]
        self.cells_form = CellForm(mesh, 1, lambda w: over(disc.dx_data, lambda dx: (
            energy_squared(mu1, mu2, u1 - uh1, u2 - uh2, w[0], dx))))

    def squares(self, X):
        """|||u - u_h|||_K² on the owned cells."""
        self.disc.functions(X, out=self.u)
        return np.maximum(self.cells_form.cells()[:, 0], 0.0)

    def per_cell(self, X):
        """|||u - u_h|||_K on the owned cells."""
        return np.sqrt(self.squares(X))

    def __call__(self, X):
        """|||u - u_h||| on Ω_h (MPI-reduced)."""
        return float(np.sqrt(global_sums(self.disc.comm, self.squares(X)[:, None])[0]))
