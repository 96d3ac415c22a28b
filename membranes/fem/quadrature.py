"""Quadrature for the data f_α (§2, §7, §9).

Data integrals use a degree-6 Gauss rule, and on cells cut by the scene's interface (where the
data jump, e.g. the circle r = 1/√2 of the disk scene) a composite rule: the reference triangle
split into 16² sub-triangles, each with a degree-4 Gauss rule. The measures are handed to the UFL
forms of `forms/`; `over(measures, form_of)` sums one form per rule.
"""

import functools

import numpy as np
import ufl

from ..model.problem import as_builder

DATA_DEGREE = 6          # Gauss degree for data on cells the interface does not cut
CUT_SUBDIVISIONS = 16    # composite rule on cut cells: 16² sub-triangles …
CUT_DEGREE = 4           # … each with a degree-4 Gauss rule


@functools.lru_cache(maxsize=None)
def composite_rule(n=CUT_SUBDIVISIONS, degree=CUT_DEGREE):
    """Points and weights of a composite Gauss rule on the reference triangle (n² pieces),
    computed once per process (read-only arrays)."""
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
    pts, wts = np.vstack(pts), np.concatenate(wts)
    pts.flags.writeable = wts.flags.writeable = False     # one copy per process (cached)
    return pts, wts


def cut_cells(mesh, interface, samples=4, chunk=16384):
    """Local cells on which the level set `interface` changes sign (sampled on a grid: the
    points (v0 + s (v1 - v0)) + t (v2 - v0), s, t ∈ {0, 1/samples, …}, s + t ≤ 1), `chunk`
    cells at a time (their samples stay in cache). An interface that lies between the samples
    of one cell (a circle of radius below about h / samples, e.g. `scenes.radial(rho=0.01)`
    at h = 0.3) is not seen: that cell's data are integrated by the plain rule, so the
    discrete loads carry a quadrature error of the order of the data's jump times the
    enclosed area (4 g π ρ² there)."""
    x = mesh.geometry.x[:, :2].T.copy()                          # (2, vertices)
    ncells = mesh.topology.index_map(2).size_local
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells]
    cut = np.zeros(ncells, dtype=bool)
    for start in range(0, ncells, chunk):
        c = cells[start:start + chunk]
        v0 = x[:, c[:, 0]]
        e1, e2 = x[:, c[:, 1]] - v0, x[:, c[:, 2]] - v0
        lo = np.full(len(c), np.inf)
        hi = np.full(len(c), -np.inf)
        row, q = np.empty_like(v0), np.empty_like(v0)
        for i in range(samples + 1):
            np.add(v0, np.multiply(i / samples, e1, out=row), out=row)
            for j in range(samples + 1 - i):
                phi = interface(np.add(row, np.multiply(j / samples, e2, out=q), out=q))
                np.minimum(lo, phi, out=lo)
                np.maximum(hi, phi, out=hi)
        cut[start:start + chunk] = (lo < 0) & (hi > 0)
    return np.flatnonzero(cut).astype(np.int32)


@functools.lru_cache(maxsize=None)
def _composite_metadata():
    """The form metadata of the composite rule on cut cells (one dict per process)."""
    pts, wts = composite_rule()
    return {"quadrature_rule": "custom", "quadrature_degree": DATA_DEGREE,
            "quadrature_points": pts.tolist(), "quadrature_weights": wts.tolist()}


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
    return [dx(0, metadata=smooth), dx(1, metadata=_composite_metadata())]


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
