"""Set-ups kept between solves on one mesh (§5, §12): `Setups`.

The patch systems of the flux equilibration — the colouring of the vertices, the patch blocks
checked against dolfinx's assembly of forms.equilibration.patch_system, their inverses and
the routes between owners and homes — depend on the mesh only: the patch system has no data
in it. (DESIGN.md §5 says "the mesh and μ"; in its mixed form μ_α enters only the right-hand
side, -(ψ_a μ_α ∇u_αh, τ), so problems with other moduli share them too.) On a fine mesh
they are most of what a certificate costs (docs/performance.md). A parameter study solves
many problems on one hierarchy (other loads, moduli, g, Newton variants or solvers); with

    kept = Setups()
    for mu2 in (1.0, 2.0, 5.0):
        sol = solve(replace(problem, mu2=mu2, exact=None), setups=kept)
    kept.clear()

the flux equilibration of each mesh that gets estimators is set up by the first solve on it
and taken again by the next ones. Only the data parts are made anew: the loads -(ψ_a f_α, q)
of §5, integrated with the new problem's data measures (the quadrature that assembled its
F_α, so that the interior patches stay compatible; made at the solve's first full evaluation,
as in a fresh run), and the estimators' own forms.

With alg_flux='multilevel' the algebraic flux's own set-up on the hierarchy (§6) is still
made at every solve; only the equilibration of T_J is kept.

Nothing else changes: a kept equilibration is the one a fresh set-up builds, so a run's
iterates, η and counts are those of a run without it (tests/test_setups.py). What it costs is
memory: the kept systems stay alive between solves, until `clear()`.
"""

import contextlib

import numpy as np
from mpi4py import MPI


class Setups:
    """The flux equilibrations (`membranes.estimation.equilibration.FluxEquilibration`) of the
    meshes solved on, kept for the next `solve(..., setups=...)` on the same mesh object
    (with its vertices where they were: a mesh moved in place is set up anew).

    Use one `Setups` for the solves of one communicator, every process making the same calls
    (lookups and `clear` are collective)."""

    def __init__(self):
        # id(mesh) → (mesh, FluxEquilibration, the vertex coordinates it was set up on)
        self._kept = {}
        self.hits = 0                            # set-ups taken again, for the caller
        self._busy = False                       # a solve with this store is running

    def __len__(self):
        return len(self._kept)

    def equilibration(self, disc):
        """The flux equilibration on the mesh of `disc` (a Discretisation), bound to its data
        measures: the kept one if there is one for this mesh object whose P1 numbering is
        that of disc.V (the equilibration copies nodal values by index) and whose vertices
        have not moved since (mesh.geometry.x is writable, and the patch blocks and their
        inverses are integrals over the cells: a kept one gave another σ_disc, and η, than
        a fresh set-up on the moved mesh), else a new one, which is kept. Collective."""
        # (imported here: a run that estimates nothing imports no estimator)
        from ..estimation.equilibration import FluxEquilibration, same_numbering
        mesh = disc.mesh
        entry = self._kept.get(id(mesh))
        usable = entry is not None and entry[0] is mesh and \
            same_numbering(entry[1].V, disc.V) and np.array_equal(entry[2], mesh.geometry.x)
        if disc.comm.allreduce(bool(usable), op=MPI.LAND):
            equilibration = entry[1]
            equilibration.use_data_measures(disc.dx_data)
            self.hits += 1
            return equilibration
        if entry is not None:
            del self._kept[id(mesh)]
            entry[1].destroy()
        equilibration = FluxEquilibration(disc.V, disc.dx_data)
        self._kept[id(mesh)] = (mesh, equilibration, mesh.geometry.x.copy())
        return equilibration

    @contextlib.contextmanager
    def in_use(self):
        """Around a solve with this store: a second solve with it before the first has ended
        (one called from the first's progress callback) is refused. It would bind the kept
        equilibration to its own data measures under the first solve, whose next σ_disc
        would then integrate the loads of §5 with the wrong quadrature and fail its
        divergence check (a RuntimeError)."""
        if self._busy:
            raise ValueError("setups is in use by a solve that has not ended (a solve called "
                             "from its progress callback?): give this solve a Setups of its "
                             "own")
        self._busy = True
        try:
            yield self
        finally:
            self._busy = False

    def clear(self):
        """Free every kept set-up (collective)."""
        for _, equilibration, _ in self._kept.values():
            equilibration.destroy()
        self._kept.clear()
