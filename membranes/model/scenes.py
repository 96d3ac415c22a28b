"""Scenes: a domain, data, and what is known about the solution (§9).

A scene builds a :class:`membranes.model.problem.Problem` and declares what it needs: an exact
solution only where one is known (then the energy error is computed), an interface only where
the data jump. Nothing else is attached, so the driver computes nothing a scene does not use.

* ``disk``   — the paper's test case with its exact solution (§9).
* ``square`` — the unit square with a manufactured solution with a genuine contact zone.
* ``radial`` — the unit disk with exact radial solutions for any μ1, μ2, g, from no contact to
  near-total contact (API only, not on the command line).
* ``user``   — μ1, μ2, g, f1, f2 from the command line (f as formulas in x, y) on the unit disk,
  the unit square, a gmsh or XDMF mesh file, or a dolfinx mesh.
"""

from __future__ import annotations

import math
import numbers
import os
from typing import Any, Callable, Optional, Union

import dolfinx.mesh
import numpy as np
import ufl
from mpi4py import MPI

from ..fem import jit, mesh_files, meshes
from ..fem.hierarchy import build_hierarchy, onto_unit_circle
from .checks import check_request
from .expressions import Formula
from .problem import ExactSolution, Problem, positive_number, real_number

DEFAULT_H = 0.05
# every scene's `progress`: one line per refinement of T_0 (`build_hierarchy`), as `solve`'s:
# None or False, True for stderr, or a callable (model.progress)
Progress = Union[None, bool, Callable[[str], Any]]


def _projection(domain, mesh_file):
    """New boundary vertices go onto the circle on the unit disk (§9); other domains are
    polygons, whose refinements keep their boundary."""
    return onto_unit_circle if mesh_file is None and domain == "disk" else None


def _coarse_mesh(domain, h, mesh_file, comm):
    if mesh_file is not None:
        return mesh_files.read_mesh_file(mesh_file, comm)
    if domain == "disk":
        return meshes.unit_disk(h, comm)
    if domain == "square":
        return meshes.unit_square(h, comm)
    raise ValueError(f"unknown domain {domain!r} (choose from: disk, square)")


def _communicator(comm):
    """The scene's communicator: `comm`, MPI.COMM_WORLD for None; ValueError for anything
    that is no mpi4py communicator (it failed later with an AttributeError), for
    MPI.COMM_NULL (an mpi4py error) and for an intercommunicator (its two groups would wait
    for each other in the meshing, or crash)."""
    if comm is None:
        return MPI.COMM_WORLD
    if not isinstance(comm, MPI.Comm):
        raise ValueError(f"comm must be an mpi4py communicator, got {type(comm).__name__}")
    if comm == MPI.COMM_NULL:
        raise ValueError("comm is MPI.COMM_NULL, a communicator of no process: give that of "
                         "the processes that solve together")
    if comm.Is_inter():
        raise ValueError("comm is an intercommunicator: give an intracommunicator of the "
                         "processes that solve together (MPI.COMM_WORLD or a Split of it)")
    return comm


def _check_size(h, levels, domain, mesh_file, max_vertices, comm):
    """Refuse, before gmsh runs, a mesh and hierarchy that no run could hold in memory (or of
    more vertices than `max_vertices`): checks.check_request with the leanest method. Returns
    h as a float (a number given as text too) where gmsh meshes the domain."""
    if mesh_file is None:
        h = meshes.target_size(h)
    check_request(h, levels, domain, mesh_file, max_vertices, comm=comm)
    jit.check_cache(comm)
    return h


def _check_levels(levels):
    whole = None
    if isinstance(levels, numbers.Integral) and not isinstance(levels, (bool, np.bool_)):
        whole = int(levels)
    elif not isinstance(levels, (bool, np.bool_)):
        try:                                 # 2.0 and "2" are 2; 2.5, None and "x" are refused
            value = float(levels)
            whole = int(value) if value.is_integer() else None
        except (TypeError, ValueError):
            pass
    if whole is None or whole < 0:
        raise ValueError(f"levels must be a non-negative integer, got {levels!r}")
    return whole


# ## The disk scene (§9)
#
# μ1 = μ2 = 1, g = 0.05 on the unit disk; the contact zone is the disk r ≤ 1/√2, where
# λ = 2g; outside, membrane 2 bends as c (1 - r)(2r² - 1), c = g √2/(√2 - 1).

DISK_G = 0.05
J01 = 2.404825557695773   # first zero of the Bessel function J_0


def disk(h: float = DEFAULT_H, levels: int = 0, comm: MPI.Comm = MPI.COMM_WORLD,
         max_vertices: Optional[int] = None, progress: Progress = None) -> Problem:
    """The paper's test case on the unit disk, with its exact solution (§9).
    `max_vertices`: refuse a larger mesh before meshing; `progress`: a callable given one line
    per refinement (every scene has both)."""
    comm = _communicator(comm)
    levels = _check_levels(levels)
    h = _check_size(h, levels, "disk", None, max_vertices, comm)
    g = DISK_G
    c = g * math.sqrt(2.0) / (math.sqrt(2.0) - 1.0)

    def r2(x):
        return x[0] ** 2 + x[1] ** 2

    def inside(x):
        return ufl.le(r2(x), 0.5)

    def u1(x):
        return g * (2 * r2(x) - 1)

    def u2(x):
        r = ufl.sqrt(r2(x))
        return ufl.conditional(inside(x), g * (2 * r2(x) - 1), c * (1 - r) * (2 * r2(x) - 1))

    def lam(x):
        return ufl.conditional(inside(x), 2 * g, 0.0)

    def f1(x):
        return ufl.conditional(inside(x), -10 * g, -8 * g)

    def f2(x):
        r = ufl.sqrt(r2(x))
        return ufl.conditional(inside(x), -6 * g, -c * (1 + 8 * r - 18 * r2(x)) / r)

    hierarchy = build_hierarchy(meshes.unit_disk(h, comm), levels, onto_unit_circle, "disk",
                                progress)
    return Problem("disk", hierarchy, 1.0, 1.0, g, f1, f2,
                   exact=ExactSolution(u1, u2, lam),
                   interface=lambda p: p[0] ** 2 + p[1] ** 2 - 0.5,
                   # the polygon lies inside the unit disk, whose λ_1 is j_{0,1}² (§7)
                   poincare=1.0 / J01,
                   description="unit disk, mu1 = mu2 = 1, g = 0.05, exact solution "
                               "(contact zone r <= 1/sqrt(2))",
                   domain="disk")


# ## The square scene (manufactured)
#
# s = 16 x(1-x) y(1-y) ∈ [0, 1] vanishes on ∂Ω; the contact zone is Z = {s ≥ s0}. The gap
# w = u1 - u2 = g ((s0 - s)/s0)² outside Z and 0 on Z is C¹, equals g on ∂Ω and is positive
# off Z; λ = λ0 (s - s0)/(1 - s0) on Z, 0 off Z. With u2 = (g/2) sin(πx) sin(πy), u1 = u2 + w,
# the loads are f1 = -μ1 Δu1 - λ and f2 = -μ2 Δu2 + λ (UFL differentiates the formulas).
# μ1 ≠ μ2 and f1 + f2 ≠ 0, so the decoupled check of §10 is not trivial here.

def _given(mesh, comm, levels, max_vertices, domain=None):
    """A dolfinx mesh given as T_0 (`meshes.given_mesh`), without ghost cells
    (`meshes.without_ghosts`: before dolfinx makes its edges, which on 3 processes waited for
    ever on a ghosted mesh of two squares touching at a corner), with the size check of its
    hierarchy; `comm`, if given, must be its communicator (the scene solves on mesh.comm);
    `domain`: as `meshes.given_mesh`'s. Collective."""
    if comm is not None and MPI.Comm.Compare(_communicator(comm), mesh.comm) not in \
            (MPI.IDENT, MPI.CONGRUENT):
        raise ValueError("comm is not the mesh's communicator: a scene on a given mesh "
                         "solves on mesh.comm (leave comm out)")
    mesh = meshes.without_ghosts(meshes.given_mesh(mesh, domain=domain))
    check_request(levels=levels, max_vertices=max_vertices, comm=mesh.comm,
                  counts=meshes.mesh_counts(mesh))
    jit.check_cache(mesh.comm)
    return mesh


def _off_the_unit_square(x, cells, edges):
    """What keeps the triangles `cells` on the nodes x, with boundary edges `edges`, from
    being a mesh of (0, 1)², whose exact solution the square scene gives (None: nothing):
    each boundary edge must lie on one of the square's sides and the cells cover an area of
    1, to round-off (nodes within tol of the sides, the area within the 4 tol that allows
    along the perimeter). A hole, a slit, another domain would leave the exact solution
    another problem's (`meshes.given_mesh` runs it on the gathered T_0)."""
    tol = 1e-12
    a, b = x[edges[:, 0]], x[edges[:, 1]]
    inside = np.all((x[edges] >= -tol) & (x[edges] <= 1.0 + tol), axis=(1, 2))
    along = (np.abs(a - b) <= tol) & ((np.abs(a) <= tol) | (np.abs(a - 1.0) <= tol))
    off = np.count_nonzero(~(inside & along.any(axis=1)))
    area = meshes.triangle_areas(x[cells]).sum()
    if off or abs(area - 1.0) > 5 * tol:
        return (f"the square scene's mesh must be a mesh of the unit square (0, 1)^2: its "
                f"cells cover an area of {area:.15g}, {off} of its {len(edges)} boundary "
                f"edges lie off the square's sides (a hole, a slit, another domain, or cells "
                f"not joined)")
    return None


SQUARE = {"mu1": 1.0, "mu2": 2.0, "g": 0.1, "s0": 0.5, "lam0": 0.8}


def square(h: Optional[float] = None, levels: int = 0, comm: Optional[MPI.Comm] = None,
           mesh: Optional[dolfinx.mesh.Mesh] = None,
           max_vertices: Optional[int] = None, progress: Progress = None) -> Problem:
    """Unit square, μ1 = 1, μ2 = 2, g = 0.1, manufactured solution with a contact zone.

    On gmsh's mesh at size h (default DEFAULT_H) on `comm` (default MPI.COMM_WORLD), or on
    `mesh`, a dolfinx mesh of (0, 1)² (API only: the anisotropic, graded and tiny meshes of
    §11, meshes.structured_square; your own), on its communicator: h and another `comm` are
    refused with it, as they cannot apply."""
    levels = _check_levels(levels)
    if mesh is None:
        comm = _communicator(comm)
        h = _check_size(DEFAULT_H if h is None else h, levels, "square", None, max_vertices,
                        comm)
    else:
        if not isinstance(mesh, dolfinx.mesh.Mesh):
            raise ValueError(f"mesh must be a dolfinx Mesh of the unit square, got "
                             f"{type(mesh).__name__} (a mesh file goes to scenes.user(mesh=...))")
        if h is not None:
            raise ValueError("give mesh or h, not both: the mesh is the coarse mesh")
        mesh = _given(mesh, comm, levels, max_vertices, _off_the_unit_square)
    mu1, mu2, g, s0, lam0 = (SQUARE[k] for k in ("mu1", "mu2", "g", "s0", "lam0"))

    def s(x):
        return 16 * x[0] * (1 - x[0]) * x[1] * (1 - x[1])

    def u2(x):
        return 0.5 * g * ufl.sin(ufl.pi * x[0]) * ufl.sin(ufl.pi * x[1])

    def u1(x):
        gap = ufl.conditional(ufl.lt(s(x), s0), g * ((s0 - s(x)) / s0) ** 2, 0.0)
        return u2(x) + gap

    def lam(x):
        return ufl.conditional(ufl.gt(s(x), s0), lam0 * (s(x) - s0) / (1 - s0), 0.0)

    def f1(x):
        return -mu1 * ufl.div(ufl.grad(u1(x))) - lam(x)

    def f2(x):
        return -mu2 * ufl.div(ufl.grad(u2(x))) + lam(x)

    def interface(p):
        return 16 * p[0] * (1 - p[0]) * p[1] * (1 - p[1]) - s0

    coarse = meshes.unit_square(h, comm) if mesh is None else mesh
    hierarchy = build_hierarchy(coarse, levels, domain="square", progress=progress)
    return Problem("square", hierarchy, mu1, mu2, g, f1, f2,
                   exact=ExactSolution(u1, u2, lam), interface=interface,
                   description="unit square, mu1 = 1, mu2 = 2, g = 0.1, manufactured solution "
                               "(contact zone 16x(1-x)y(1-y) >= 1/2)",
                   domain="square")


# ## The radial family (stiff and extreme cases, §11)
#
# On the unit disk, for any μ1, μ2 > 0, g > 0: membrane 2 is u2 = (g/2)(r² - 1); the gap
# w = u1 - u2 vanishes on the contact disk r ≤ ρ and is g ((r² - ρ²)/(1 - ρ²))² outside (C¹,
# = g on ∂Ω); λ = 4g on r < ρ, 0 outside. ρ = 0: w and λ vanish together at the origin only
# (grazing contact, Fischer–Burmeister's kink); ρ close to 1: near-total contact;
# contact=False: w = g (1 + r²)/2 > 0 and λ = 0 (no contact). The loads follow from the
# equations (UFL differentiates), so every choice has its exact solution.


def radial(h: float = DEFAULT_H, levels: int = 0, rho: float = 0.5, mu1: float = 1.0,
           mu2: float = 1.0, g: float = 0.05, contact: bool = True,
           comm: MPI.Comm = MPI.COMM_WORLD, max_vertices: Optional[int] = None,
           progress: Progress = None) -> Problem:
    """Unit disk, exact radial solution with contact disk r <= rho (any mu1, mu2, g)."""
    comm = _communicator(comm)
    levels = _check_levels(levels)
    h = _check_size(h, levels, "disk", None, max_vertices, comm)
    mu1, mu2, g = (positive_number(k, v) for k, v in (("mu1", mu1), ("mu2", mu2), ("g", g)))
    rho = real_number("rho", rho)                  # (False is not ρ = 0)
    if not (0.0 <= rho < 1.0):
        raise ValueError(f"rho must lie in [0, 1), got {rho}")
    if not isinstance(contact, (bool, np.bool_)):
        raise ValueError(f"contact must be True or False, got {contact!r}")

    def r2(x):
        return x[0] ** 2 + x[1] ** 2

    def u2(x):
        return 0.5 * g * (r2(x) - 1)

    def gap(x):
        if not contact:
            return 0.5 * g * (1 + r2(x))
        t = (r2(x) - rho ** 2) / (1 - rho ** 2)
        return ufl.conditional(ufl.gt(r2(x), rho ** 2), g * t ** 2, 0.0)

    def u1(x):
        return u2(x) + gap(x)

    def lam(x):
        if not contact or rho == 0.0:
            return 0.0 * r2(x)
        return ufl.conditional(ufl.lt(r2(x), rho ** 2), 4 * g, 0.0)

    def f1(x):
        return -mu1 * ufl.div(ufl.grad(u1(x))) - lam(x)

    def f2(x):
        return -mu2 * ufl.div(ufl.grad(u2(x))) + lam(x)

    jump = contact and rho > 0.0
    hierarchy = build_hierarchy(meshes.unit_disk(h, comm), levels, onto_unit_circle, "disk",
                                progress)
    kind = "no contact" if not contact else ("grazing contact at the origin" if rho == 0.0
                                             else f"contact disk r <= {rho}")
    return Problem("radial", hierarchy, mu1, mu2, g, f1, f2,
                   exact=ExactSolution(u1, u2, lam),
                   interface=(lambda p: p[0] ** 2 + p[1] ** 2 - rho ** 2) if jump else None,
                   poincare=1.0 / J01,
                   description=f"unit disk, mu1 = {mu1}, mu2 = {mu2}, g = {g}, exact radial "
                               f"solution, {kind}",
                   domain="disk")


# ## User data

def user(mu1: float = 1.0, mu2: float = 1.0, g: float = 0.05, f1: Union[str, float] = "0",
         f2: Union[str, float] = "0",
         mesh: Union[None, str, os.PathLike, dolfinx.mesh.Mesh] = None,
         domain: Optional[str] = None,
         h: Optional[float] = None, levels: int = 0, comm: Optional[MPI.Comm] = None,
         max_vertices: Optional[int] = None, progress: Progress = None) -> Problem:
    """User data: f1, f2 formulas in x, y; on the unit disk/square or your mesh.

    `mesh`: a gmsh .msh or XDMF file (`fem.mesh_files`), or a dolfinx mesh (on its
    communicator, checked as a file's mesh is: `meshes.given_mesh`). `domain` ('disk' by
    default) and `h` (DEFAULT_H) apply without `mesh` only; `comm` (default
    MPI.COMM_WORLD) must be a dolfinx mesh's own."""
    if mesh is not None and (h is not None or domain is not None):  # (as the command line)
        raise ValueError(f"give mesh or {'h' if h is not None else 'domain'}, not both: the "
                         f"mesh is the coarse mesh")
    levels = _check_levels(levels)
    f1, f2 = Formula(f1, "f1"), Formula(f2, "f2")   # fail on bad input before any meshing
    mu1, mu2, g = (positive_number(k, v) for k, v in (("mu1", mu1), ("mu2", mu2), ("g", g)))
    if isinstance(mesh, dolfinx.mesh.Mesh):
        hierarchy = build_hierarchy(_given(mesh, comm, levels, max_vertices), levels,
                                    progress=progress)
        return Problem("user", hierarchy, mu1, mu2, g, f1, f2,
                       description=f"given mesh, mu1 = {mu1}, mu2 = {mu2}, g = {g}, "
                                   f"f1 = {f1.text}, f2 = {f2.text}")
    comm = _communicator(comm)
    h = DEFAULT_H if h is None else h
    domain = "disk" if domain is None else domain
    if mesh is None and domain not in ("disk", "square"):
        raise ValueError(f"unknown domain {domain!r} (choose from: disk, square)")
    if mesh is not None:
        mesh = mesh_files.check_mesh_path(mesh)
    h = _check_size(h, levels, domain, mesh, max_vertices, comm)
    coarse = _coarse_mesh(domain, h, mesh, comm)
    if mesh is not None and levels:     # the header's estimate was a lower bound: now exact
        check_request(levels=levels, mesh_file=mesh, max_vertices=max_vertices, comm=comm,
                      counts=meshes.mesh_counts(coarse))
    hierarchy = build_hierarchy(coarse, levels, _projection(domain, mesh),
                                None if mesh is not None else domain, progress)
    where = f"mesh {mesh}" if mesh is not None else f"unit {domain}"
    # on the unit disk its own constant, as for the disk scene (§7); else the bounding box's
    poincare = 1.0 / J01 if mesh is None and domain == "disk" else None
    return Problem("user", hierarchy, mu1, mu2, g, f1, f2, poincare=poincare,
                   description=f"{where}, mu1 = {mu1}, mu2 = {mu2}, g = {g}, "
                               f"f1 = {f1.text}, f2 = {f2.text}",
                   domain=str(mesh) if mesh is not None else domain)


SCENES = {"disk": disk, "square": square, "radial": radial, "user": user}

NEEDS = {"disk": "exact solution -> energy error; data jump across r = 1/sqrt(2)",
         "square": "exact solution -> energy error; data jump across s = 1/2",
         "radial": "exact solution -> energy error; parameters rho, mu1, mu2, g, contact "
                   "(API only)",
         "user": "data only (no exact solution, no energy error)"}


def make(name: str, **kwargs: Any) -> Problem:
    """Build scene `name` with keyword arguments of its function."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r} (choose from: {', '.join(SCENES)})")
    return SCENES[name](**kwargs)
