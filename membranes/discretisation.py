"""Conforming P1 discretisation with lumped contact (DESIGN §2).

`discretise(problem)` assembles, once per mesh, everything the Newton driver needs:

    S_α = μ_α (∇ψ_b, ∇ψ_a)      membrane stiffness matrices (forms.membrane.membrane_bilinear)
    D_a = (ψ_a, 1)              lumped contact weights       (forms.membrane.contact_weight)
    F_α,a = (f_α, ψ_a)          loads                        (forms.membrane.membrane_linear)

and the boundary vertices (Dirichlet: u1 = g, u2 = 0, λ = 0). The loads are integrated with a
degree-6 Gauss rule, and on cells cut by the scene's interface (where the data jump, e.g. the
circle r = 1/√2 of the disk scene, DESIGN §9) with a composite rule: the reference triangle split
into 16² sub-triangles, each with a degree-4 Gauss rule. The same measure integrates the exact
energy error.

Serial: the matrices are handed to the driver as scipy CSR (owned rows = all rows).
"""

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import ufl

from forms.membrane import (contact_weight, energy_norm_squared, membrane_bilinear,
                            membrane_linear)

from .problem import as_builder

DATA_DEGREE = 6          # Gauss degree for data on cells the interface does not cut
CUT_SUBDIVISIONS = 16    # composite rule on cut cells: 16² sub-triangles …
CUT_DEGREE = 4           # … each with a degree-4 Gauss rule


def composite_rule(n=CUT_SUBDIVISIONS, degree=CUT_DEGREE):
    """Points and weights of a composite Gauss rule on the reference triangle (n² pieces)."""
    import basix
    p, w = basix.make_quadrature(basix.CellType.triangle, degree)
    pts, wts = [], []
    for i in range(n):
        for j in range(n - i):
            tris = [((i, j), (i + 1, j), (i, j + 1))]
            if i + j < n - 1:
                tris.append(((i + 1, j), (i + 1, j + 1), (i, j + 1)))
            for a, b, c in tris:
                a, b, c = (np.array(v, dtype=float) / n for v in (a, b, c))
                pts.append(a + np.outer(p[:, 0], b - a) + np.outer(p[:, 1], c - a))
                wts.append(w / n**2)
    return np.vstack(pts), np.concatenate(wts)


def cut_cells(mesh, interface, samples=4):
    """Local cells on which the level set `interface` changes sign (sampled on a grid)."""
    x = mesh.geometry.x[:, :2]
    ncells = mesh.topology.index_map(2).size_local
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells]
    bary = np.array([(i / samples, j / samples) for i in range(samples + 1)
                     for j in range(samples + 1 - i)])
    v0, v1, v2 = x[cells[:, 0]], x[cells[:, 1]], x[cells[:, 2]]
    phi = np.empty((ncells, len(bary)))
    for k, (s, t) in enumerate(bary):
        q = v0 + s * (v1 - v0) + t * (v2 - v0)
        phi[:, k] = interface(q.T)
    return np.flatnonzero((phi.min(axis=1) < 0) & (phi.max(axis=1) > 0)).astype(np.int32)


def data_measures(mesh, interface=None):
    """Measures for data integrals, to be summed: Gauss degree 6, composite rule on cut cells."""
    smooth = {"quadrature_degree": DATA_DEGREE}
    if interface is None:
        return [ufl.dx(domain=mesh, metadata=smooth)]
    from dolfinx import mesh as dmesh
    ncells = mesh.topology.index_map(2).size_local
    marker = np.zeros(ncells, dtype=np.int32)
    marker[cut_cells(mesh, interface)] = 1
    tags = dmesh.meshtags(mesh, 2, np.arange(ncells, dtype=np.int32), marker)
    dx = ufl.Measure("dx", domain=mesh, subdomain_data=tags)
    pts, wts = composite_rule()
    composite = {"quadrature_rule": "custom", "quadrature_degree": DATA_DEGREE,
                 "quadrature_points": pts.tolist(), "quadrature_weights": wts.tolist()}
    return [dx(0, metadata=smooth), dx(1, metadata=composite)]


def over(measures, form_of):
    """Σ form_of(dx) over the data measures: one integral per quadrature rule."""
    forms = [form_of(dx) for dx in measures]
    total = forms[0]
    for f in forms[1:]:
        total = total + f
    return total


def load(data, mesh):
    """The UFL expression of a load f (a scene's builder or a Formula) on `mesh`; constant data
    as a dolfinx Constant: UFL would fold 0 * v * dx into an empty form, and a Constant keeps
    one compiled kernel for every value."""
    from dolfinx import fem
    expr = ufl.as_ufl(as_builder(data)(ufl.SpatialCoordinate(mesh)))
    if isinstance(expr, (ufl.constantvalue.Zero, ufl.constantvalue.ScalarValue)):
        return fem.Constant(mesh, float(expr))
    return expr


def assemble_matrix_csr(a):
    """Assemble a bilinear UFL form (no boundary conditions) into scipy CSR."""
    from dolfinx import fem
    import dolfinx.fem.petsc  # noqa: F401
    A = fem.petsc.assemble_matrix(fem.form(a))
    A.assemble()
    indptr, indices, data = A.getValuesCSR()
    out = sp.csr_matrix((data, indices, indptr), shape=A.getSize())
    A.destroy()
    release_memory()
    return out


def release_memory():
    """Hand freed heap memory back to the system (glibc malloc_trim), so that the transient
    PETSc and sparsity-pattern buffers of one assembly do not add to the next phase's peak."""
    import ctypes
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def assemble_vector_array(L):
    """Assemble a linear UFL form into a numpy array of the owned entries.

    """
    from dolfinx import fem
    from petsc4py import PETSc
    import dolfinx.fem.petsc  # noqa: F401
    b = fem.petsc.assemble_vector(fem.form(L))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    out = b.array.copy()
    b.destroy()
    return out


@dataclass
class Discretisation:
    problem: object
    V: object                 # P1 space on the computational mesh
    S1: sp.csr_matrix         # μ1 S
    S2: sp.csr_matrix         # μ2 S
    D: np.ndarray             # (ψ_a, 1)
    F1: np.ndarray            # (f1, ψ_a)
    F2: np.ndarray            # (f2, ψ_a)
    boundary: np.ndarray      # indices of boundary vertices (dofs)
    dx_data: list             # data measures (data_measures), integrals summed with over()

    @property
    def n(self):
        return self.D.size

    @property
    def interior(self):
        mask = np.ones(self.n, dtype=bool)
        mask[self.boundary] = False
        return mask

    def data_scales(self):
        """(u_data, λ_data): the sizes the data give a displacement and a pressure (DESIGN
        §11, tolerances relative to the data): λ_data = max_a,α |F_α,a| / D_a over interior
        vertices (a nodal load density), u_data = max(g, (C_PF h_Ω)² max_a,α |F_α,a| /
        (μ_α D_a)), the displacement those loads can make on their own."""
        p, inner = self.problem, self.interior
        F1, F2 = (np.abs(F)[inner] / self.D[inner] for F in (self.F1, self.F2))
        lam_data = max(F1.max(initial=0.0), F2.max(initial=0.0))
        u_data = max(p.g, p.poincare_constant() ** 2 * max(F1.max(initial=0.0) / p.mu1,
                                                           F2.max(initial=0.0) / p.mu2))
        return u_data, lam_data

    def functions(self, X):
        """P1 functions u1, u2, lambda from X = (X1, X2, X3) ∈ R^{3N}."""
        from dolfinx import fem
        out = []
        for k, name in enumerate(("u1", "u2", "lambda")):
            f = fem.Function(self.V, name=name)
            f.x.array[:self.n] = X[k * self.n:(k + 1) * self.n]
            f.x.scatter_forward()
            out.append(f)
        return out


def boundary_dofs(V):
    """The dofs of the P1 space V on the boundary facets of its mesh (Dirichlet vertices)."""
    from dolfinx import fem, mesh as dmesh
    mesh = V.mesh
    mesh.topology.create_connectivity(1, 2)
    return fem.locate_dofs_topological(V, 1, dmesh.exterior_facet_indices(mesh.topology))


def discretise(problem):
    """Assemble S1, S2, D, F1, F2 and the boundary vertices of `problem` (DESIGN §2)."""
    from dolfinx import fem
    mesh = problem.mesh
    V = fem.FunctionSpace(mesh, ("Lagrange", 1))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    mu1, mu2 = fem.Constant(mesh, problem.mu1), fem.Constant(mesh, problem.mu2)
    S1 = assemble_matrix_csr(membrane_bilinear(mu1, u, v))
    S2 = assemble_matrix_csr(membrane_bilinear(mu2, u, v))
    D = assemble_vector_array(contact_weight(v))
    dxd = data_measures(mesh, problem.interface)
    f1, f2 = (load(f, mesh) for f in (problem.f1, problem.f2))
    F1 = assemble_vector_array(over(dxd, lambda dx: membrane_linear(f1, v, dx)))
    F2 = assemble_vector_array(over(dxd, lambda dx: membrane_linear(f2, v, dx)))
    boundary = boundary_dofs(V)
    n = V.dofmap.index_map.size_local
    return Discretisation(problem, V, S1[:n], S2[:n], D[:n], F1[:n], F2[:n],
                          np.asarray(boundary[boundary < n], dtype=np.int32), dxd)


class EnergyError:
    """|||u - u_h||| against the scene's exact solution (DESIGN §1), the form compiled once.

    Integrated with the data measures (the exact gradients are piecewise smooth across the
    scene's interface), on the computational polygon.
    """

    def __init__(self, disc):
        from dolfinx import fem
        problem = disc.problem
        x = ufl.SpatialCoordinate(problem.mesh)
        self.disc = disc
        self.u1h, self.u2h = fem.Function(disc.V), fem.Function(disc.V)
        e1 = problem.exact.u1(x) - self.u1h
        e2 = problem.exact.u2(x) - self.u2h
        mu1 = fem.Constant(problem.mesh, problem.mu1)
        mu2 = fem.Constant(problem.mesh, problem.mu2)
        self.form = fem.form(over(disc.dx_data,
                                  lambda dx: energy_norm_squared(mu1, mu2, e1, e2, dx)))
        self._cell_form = lambda w: over(disc.dx_data, lambda dx: energy_norm_squared(
            mu1, mu2, e1, e2, dx, w))

    def _set(self, X):
        n = self.disc.n
        for k, f in enumerate((self.u1h, self.u2h)):
            f.x.array[:n] = X[k * n:(k + 1) * n]
            f.x.scatter_forward()

    def __call__(self, X):
        from dolfinx import fem
        from mpi4py import MPI
        self._set(X)
        value = self.disc.V.mesh.comm.allreduce(fem.assemble_scalar(self.form), op=MPI.SUM)
        return float(np.sqrt(max(value, 0.0)))

    def per_cell(self, X):
        """|||u - u_h|||_K for every local cell K (the actual error distribution)."""
        from dolfinx import fem
        mesh = self.disc.problem.mesh
        DG0 = fem.FunctionSpace(mesh, ("DG", 0))
        self._set(X)
        values = assemble_vector_array(self._cell_form(ufl.TestFunction(DG0)))
        ncells = mesh.topology.index_map(2).size_local
        return np.sqrt(np.maximum(values[DG0.dofmap.list.array[:ncells]], 0.0))
