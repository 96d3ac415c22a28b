"""Conforming P1 discretisation with lumped contact, assembled by dolfinx into PETSc (§2, §12).

`discretise(problem)` assembles, once per mesh, from the UFL forms of `forms/membrane.py`:

    S_ab  = (∇ψ_b, ∇ψ_a)       stiffness            (membrane_bilinear with μ = 1)
    D_a   = (ψ_a, 1)           lumped contact term  (contact_term with λ = 1: the vertex rule
                                                     makes the matrix diagonal, D_a its entry)
    F_α,a = (f_α, ψ_a)         loads                (membrane_linear, data measures)

into distributed PETSc objects on the mesh's communicator, and finds the Dirichlet vertices
(u1 = g, u2 = 0, λ = 0 on ∂Ω). Membrane α's operator is μ_α S (§2).

**The iterate layout.** A Newton iterate X = (u1, u2, λ) is a PETSc Vec of local size 3n
(n owned P1 dofs), laid out per process as [u1 owned | u2 owned | λ owned]: the layout of
dolfinx's block assembly and of a PETSc MatNest converted to AIJ. `split` gives numpy views of
the three parts, `functions` the ghosted P1 Functions.
"""

from dataclasses import dataclass

import numpy as np
import ufl

from ..forms.membrane import contact_term, membrane_bilinear, membrane_linear
from .meshes import on_boundary
from .quadrature import data_measures, load, over


@dataclass
class Discretisation:
    problem: object
    V: object                 # P1 space on the computational mesh
    S: object                 # PETSc Mat: (∇ψ_b, ∇ψ_a), no boundary conditions
    D: object                 # PETSc Vec (owned): (ψ_a, 1)
    F1: object                # PETSc Vec (owned): (f1, ψ_a)
    F2: object                # PETSc Vec (owned): (f2, ψ_a)
    f1: object                # UFL expressions of the loads
    f2: object
    boundary: np.ndarray      # local dofs (owned and ghost) on ∂Ω, ascending (int32)
    dx_data: list             # data measures (quadrature.data_measures)

    @property
    def mesh(self):
        return self.V.mesh

    @property
    def comm(self):
        return self.V.mesh.comm

    @property
    def n(self):
        """Owned P1 dofs on this process."""
        return self.V.dofmap.index_map.size_local

    @property
    def n_global(self):
        return self.V.dofmap.index_map.size_global

    @property
    def boundary_owned(self):
        return self.boundary[self.boundary < self.n]

    @property
    def interior(self):
        """Mask of the owned dofs that are not on ∂Ω."""
        mask = np.ones(self.n, dtype=bool)
        mask[self.boundary_owned] = False
        return mask

    @property
    def mu1(self):
        return self.problem.mu1

    @property
    def mu2(self):
        return self.problem.mu2

    @property
    def g(self):
        return self.problem.g

    @property
    def poincare(self):
        """C_PF h_Ω (§7)."""
        return self.problem.poincare_constant()

    def vector3(self):
        """A new zero PETSc Vec in the iterate layout (local size 3n)."""
        from petsc4py import PETSc
        X = PETSc.Vec().createMPI((3 * self.n, 3 * self.n_global), comm=self.comm)
        X.set(0.0)
        return X

    def split(self, X):
        """(u1, u2, λ): numpy views of the owned parts of X (a Vec or an array of 3n)."""
        a = X.array if hasattr(X, "array") else X
        n = self.n
        return a[:n], a[n:2 * n], a[2 * n:3 * n]

    def functions(self, X, out=None):
        """Ghosted P1 Functions u1, u2, λ with the values of X (written into `out` if given)."""
        from dolfinx import fem
        if out is None:
            out = [fem.Function(self.V, name=name) for name in ("u1", "u2", "lambda")]
        for f, part in zip(out, self.split(X)):
            f.x.array[:self.n] = part
            f.x.scatter_forward()
        return out

    def destroy(self):
        """Free S, D, F1 and F2 now (the object is unusable afterwards) rather than when the
        garbage is next cleaned (membranes.app.garbage.release_garbage)."""
        for obj in (self.S, self.D, self.F1, self.F2):
            obj.destroy()

    def data_scales(self):
        """(u_data, λ_data): the sizes the data give a displacement and a pressure (§11):
        λ_data = max over interior vertices and α of |F_α,a| / D_a, u_data = max(g,
        (C_PF h_Ω)² max |F_α,a| / (μ_α D_a))."""
        from mpi4py import MPI
        inner = self.interior
        D = self.D.array[inner]
        F1, F2 = (np.abs(F.array[inner]) / D for F in (self.F1, self.F2))
        m1 = self.comm.allreduce(F1.max(initial=0.0), op=MPI.MAX)
        m2 = self.comm.allreduce(F2.max(initial=0.0), op=MPI.MAX)
        p = self.problem
        return max(p.g, self.poincare ** 2 * max(m1 / p.mu1, m2 / p.mu2)), max(m1, m2)


def boundary_dofs(V):
    """Bool over the local P1 dofs (owned and ghost): the vertex lies on ∂Ω, where §2 puts the
    Dirichlet rows u1 = g, u2 = 0, λ = 0 and §5, §6 the boundary patches
    (`membranes.fem.meshes.on_boundary`). Collective."""
    return on_boundary(V.mesh, V.dofmap.list.array.reshape(-1, 3), V.dofmap.index_map)


def assemble_vector(L):
    """Assemble the linear form L into a PETSc Vec of the owned entries (contributions from
    other processes summed)."""
    from dolfinx import fem
    from dolfinx.fem import petsc
    from petsc4py import PETSc
    form = fem.form(L)
    b = petsc.assemble_vector(form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    # the owned entries in a Vec of petsc4py's own: dolfinx 0.5's Vec is freed only by an
    # explicit destroy(), and a Discretisation's vectors live as long as the user keeps it.
    # On the mesh's communicator (not b's, PETSc's inner one), where `release_garbage`
    # cleans what Python drops
    out = PETSc.Vec().createMPI((b.getLocalSize(), b.getSize()), comm=form.mesh.comm)
    b.copy(out)
    b.destroy()
    return out


def ghosted_vector(V):
    """A ghosted PETSc Vec of the dofs of the space V (owned entries and V's ghosts, the layout
    of dolfinx.fem.petsc.create_vector), made by petsc4py: dolfinx 0.5's is freed only by an
    explicit destroy(), so one that Python drops stays allocated for the life of the process,
    whereas petsc4py's is parked on V's mesh communicator until `release_garbage` frees it."""
    from petsc4py import PETSc
    imap, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    return PETSc.Vec().createGhost(np.asarray(imap.ghosts, dtype=PETSc.IntType),
                                   (imap.size_local * bs, imap.size_global * bs), bsize=bs,
                                   comm=V.mesh.comm)


def assemble_matrix(a):
    from dolfinx import fem
    from dolfinx.fem import petsc
    A = petsc.assemble_matrix(fem.form(a))
    A.assemble()
    return A


def p1_space(mesh):
    """The conforming P1 space of §2 on `mesh` (each level's own, for the hierarchy's maps)."""
    from dolfinx import fem
    return fem.FunctionSpace(mesh, ("Lagrange", 1))


def discretise(problem):
    """Assemble S, D, F1, F2 and find the boundary vertices of `problem` (§2)."""
    mesh = problem.mesh
    V = p1_space(mesh)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    S = assemble_matrix(membrane_bilinear(1.0, u, v))
    # the lumped contact matrix is diagonal: its diagonal is the form's action on λ = 1
    D = assemble_vector(contact_term(ufl.as_ufl(1.0), v))
    dx_data = data_measures(mesh, problem.interface)
    f1, f2 = load(problem.f1, mesh), load(problem.f2, mesh)
    F1 = assemble_vector(over(dx_data, lambda dx: membrane_linear(f1, v, dx)))
    F2 = assemble_vector(over(dx_data, lambda dx: membrane_linear(f2, v, dx)))
    boundary = np.flatnonzero(boundary_dofs(V)).astype(np.int32)
    return Discretisation(problem, V, S, D, F1, F2, f1, f2, boundary, dx_data)
