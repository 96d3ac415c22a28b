"""Problem data of the two-membrane contact problem (§1).

A :class:`Problem` holds the mesh hierarchy (the computational mesh is the finest level),
the moduli μ1, μ2 > 0, the boundary value g > 0 of membrane 1, the loads f1, f2, and what the
scene declares beyond that: an exact solution where one is known, and a level set across which
the data jump (so that cells it cuts are integrated with a composite rule, §7, §9).

Data are *builders*: callables taking the UFL spatial coordinate ``x`` and returning a UFL
expression, or :class:`membranes.model.expressions.Formula` objects (user formulas, which are also
checked to be finite on the mesh). Bad data raise ValueError with a one-line message.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable, Optional, Union

import numpy as np
import ufl
from dolfinx.mesh import Mesh
from mpi4py import MPI

from .expressions import Formula

if TYPE_CHECKING:          # problem imports nothing above model/ (docs/architecture.md)
    from ..fem.hierarchy import Hierarchy

# A data item: a number, a formula in x, y (str or Formula) or a builder x ↦ UFL expression.
Data = Union[float, str, Formula, Callable[[Any], Any]]


@dataclass
class ExactSolution:
    """u1, u2, λ as builders x ↦ UFL expression."""
    u1: Callable[[Any], Any]
    u2: Callable[[Any], Any]
    lam: Callable[[Any], Any]


def as_builder(data: Data) -> Callable[[Any], Any]:
    """A data item as a callable x ↦ UFL expression (numbers and Formulas accepted)."""
    if isinstance(data, Formula):
        return data.ufl
    if callable(data):
        return data
    value = float(data)
    return lambda x: value


def real_number(name: str, value: Any) -> float:
    """`value` as a float (a number given as text too), or a ValueError naming `name`: a bool
    is no number (False would pass for 0), and float('abc') names nothing."""
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None


def positive_number(name: str, value: Any) -> float:
    value = real_number(name, value)
    if not np.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    if value <= 0:
        raise ValueError(f"{name} must be positive, got {value}")
    return value


def _check_builder(name, builder, mesh):
    """A data builder must build a scalar UFL expression from the spatial coordinate: one
    that does not failed in the forms' construction, inside `solve`, with a TypeError or a
    UFL error naming neither the data nor the builder."""
    try:
        expr = ufl.as_ufl(builder(ufl.SpatialCoordinate(mesh)))
    except Exception as e:
        why = (str(e).strip().splitlines() or [""])[0]
        raise ValueError(f"{name}: the builder {getattr(builder, '__name__', builder)!r} "
                         f"does not build a UFL expression from the spatial coordinate x "
                         f"({type(e).__name__}: {why})") from e
    if expr.ufl_shape != () or expr.ufl_free_indices:
        raise ValueError(f"{name}: the builder {getattr(builder, '__name__', builder)!r} "
                         f"returns a value of shape {expr.ufl_shape}, not a scalar")


def _sample_points(mesh):
    """Vertices and cell midpoints of the local mesh, shape (2, n)."""
    x = mesh.geometry.x[:, :2]
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)
    return np.vstack([x, x[cells].mean(axis=1)]).T


def _set(problem, name, value):
    """A field of the frozen `Problem` as its checks in `__post_init__` made it."""
    object.__setattr__(problem, name, value)


@dataclass(frozen=True)
class Problem:
    """A contact problem on a mesh hierarchy (§1, §9): the moduli, g, the loads, the exact
    solution where one is known. Immutable: a changed problem is made with
    `dataclasses.replace`, which checks it as on construction (and refuses an exact solution
    of other data); an assignment, `problem.mu2 = 5.0`, raises FrozenInstanceError. It used to
    pass unchecked where the solved level is the problem itself (J = 0 or nested=False): the
    old exact solution then measured the error of the new data (a probe's: effectivity 0.158
    where η was a bound)."""
    name: str
    # the meshes T_0, …, T_J; T_J is the computational mesh (not in repr: its arrays are long)
    hierarchy: Hierarchy = field(repr=False)
    mu1: float
    mu2: float
    g: float
    f1: Data
    f2: Data
    exact: Optional[ExactSolution] = None
    # numpy level set φ(points (2, n)); the data jump at φ = 0
    interface: Optional[Callable[[np.ndarray], np.ndarray]] = None
    description: str = ""
    domain: str = ""
    poincare: Optional[float] = None       # C_PF h_Ω where the scene knows a sharper value
    # the data (μ1, μ2, g, f1, f2) and exact solution that `description` was written for:
    # set on construction, carried over by dataclasses.replace (`_other_data`)
    described: Optional[tuple] = field(default=None, repr=False, compare=False)

    def poincare_constant(self) -> float:
        """C_PF h_Ω ≥ 1/sqrt(λ_1(Ω)) (§7): the scene's value, else the guaranteed bound
        1/(π sqrt(1/a² + 1/b²)) of the bounding box a × b of the computational mesh."""
        if self.poincare is not None:
            return float(self.poincare)
        x = self.mesh.geometry.x[:, :2]
        comm = self.mesh.comm
        lo = [comm.allreduce(x[:, k].min(initial=np.inf), op=MPI.MIN) for k in (0, 1)]
        hi = [comm.allreduce(x[:, k].max(initial=-np.inf), op=MPI.MAX) for k in (0, 1)]
        a, b = hi[0] - lo[0], hi[1] - lo[1]
        return float(1.0 / (np.pi * np.sqrt(1.0 / a ** 2 + 1.0 / b ** 2)))

    def __post_init__(self) -> None:
        # (a field given to dataclasses.replace is checked as on construction: a hierarchy,
        # exact solution or level set of the wrong kind failed deep inside `solve`, and a
        # non-positive C_PF h_Ω gave a smaller η that was no bound, §7)
        if not isinstance(getattr(self.hierarchy, "finest", None), Mesh):
            raise ValueError(f"hierarchy must be a mesh hierarchy (membranes.fem.hierarchy."
                             f"build_hierarchy), got {type(self.hierarchy).__name__}")
        _set(self, "mu1", positive_number("mu1", self.mu1))
        _set(self, "mu2", positive_number("mu2", self.mu2))
        _set(self, "g", positive_number("g", self.g))
        if self.poincare is not None:
            _set(self, "poincare", positive_number("poincare", self.poincare))
        if self.exact is not None and not isinstance(self.exact, ExactSolution):
            raise ValueError(f"exact must be an ExactSolution or None, got "
                             f"{type(self.exact).__name__}")
        for name in ("name", "description"):
            if not isinstance(getattr(self, name), str):
                raise ValueError(f"{name} must be a str, got "
                                 f"{type(getattr(self, name)).__name__}")
        points = None
        if self.interface is not None:
            # (a function returning one number, not one per point, was taken for no interface;
            # collective, with the same message on every process: the first wrong answer)
            points, shape = _sample_points(self.mesh), None
            if callable(self.interface):
                try:
                    shape = f"shape {np.shape(self.interface(points))}"
                except Exception as e:          # (on every process alike, below)
                    shape = f"{type(e).__name__}: {e}"
            wrong = [shape] if shape != f"shape {(points.shape[1],)}" else None
            wrong = next((w for w in self.mesh.comm.allgather(wrong) if w is not None), None)
            if wrong is not None:
                raise ValueError(f"interface must be a level set, a function of points "
                                 f"(2, n) returning n values, or None, got "
                                 f"{type(self.interface).__name__}"
                                 + (f" giving {wrong[0]}" if wrong[0] else ""))
        for name in ("f1", "f2"):
            data = getattr(self, name)
            if isinstance(data, str):
                data = Formula(data, name)
                _set(self, name, data)
            if isinstance(data, Formula):
                points = _sample_points(self.mesh) if points is None else points
                bad = ~np.isfinite(data.numpy(points))
                # collective: a process whose part of the mesh misses the bad points must
                # raise too, or it would go on alone into the solve's collectives
                p = points[:, np.argmax(bad)] if bad.any() else None
                p = next((q for q in self.mesh.comm.allgather(p) if q is not None), None)
                if p is not None:
                    raise ValueError(f"{name} = {data.shown!r} is not finite on the mesh "
                                     f"(e.g. at x = {p[0]:.6g}, y = {p[1]:.6g})")
            elif isinstance(data, ufl.core.expr.Expr):
                # (callable in UFL's sense, x ↦ its value at a point: taken for a builder, a
                # dolfinx Constant logged warnings for ever, a Function of x raised TypeError)
                raise ValueError(f"{name} is a UFL expression ({type(data).__name__}): give a "
                                 f"number, a formula in x, y, or a builder, a function of the "
                                 f"spatial coordinate x returning one (lambda x: ...), which "
                                 f"is built on every mesh of the hierarchy")
            elif callable(data):
                _check_builder(name, data, self.mesh)
            else:
                v = real_number(name, data)
                if not np.isfinite(v):
                    raise ValueError(f"{name} must be finite, got {v}")
                _set(self, name, v)          # (numpy's and 0-d arrays too: one float)
        self._other_data()

    def _other_data(self) -> None:
        """A copy with other data (`dataclasses.replace(problem, mu2=5, exact=None)`, a
        parameter study; README): the scene's exact solution solves the scene's data only,
        so keeping it would report the error against the wrong solution (ValueError), and
        the scene's description is rewritten from the new data (summary.json's
        `description`, docs/outputs.md). A copy on a hierarchy of another domain keeps
        neither the exact solution nor the scene's C_PF h_Ω (§7: a constant of a smaller
        domain would make η no bound) unless they are given anew (ValueError)."""
        data = (self.mu1, self.mu2, self.g, self.f1, self.f2)
        domain = self._domain()
        if self.described is not None:
            old, exact, poincare, old_domain = self.described
            moved = domain != old_domain        # (a name, or T_0 itself: meshes by identity)
            kept = [k for k, ours, theirs in (("exact", self.exact, exact),
                                              ("poincare", self.poincare, poincare))
                    if ours is not None and ours is theirs]
            if moved and kept:
                what = {"exact": "exact solution", "poincare": "C_PF h_Ω (poincare)"}
                raise ValueError(f"scene {self.name!r}: its {' and '.join(what[k] for k in kept)}"
                                 f" {'hold' if len(kept) > 1 else 'holds'} on its own domain "
                                 f"only; with a hierarchy of another "
                                 f"domain give {', '.join(k + '=None' for k in kept)} (or "
                                 f"values for the new domain)")
            same = all(a is b or (isinstance(a, float) and a == b) for a, b in zip(old, data))
            if same and not moved and self.exact is exact:
                return
            if self.exact is not None and self.exact is exact and not same:
                raise ValueError(f"the exact solution of scene {self.name!r} does not solve "
                                 f"other data: give exact=None with new mu1, mu2, g, f1 or f2")
            words = [f"{k} = {v:g}" for k, v in zip(("mu1", "mu2", "g"), data)]
            words += [f"{k} = {v.text if isinstance(v, Formula) else f'{v:g}'}"
                      if isinstance(v, (Formula, float, int)) else f"{k} of scene {self.name}"
                      for k, v in zip(("f1", "f2"), data[3:])]
            if moved:
                _set(self, "domain", domain if isinstance(domain, str) else "")
            where = {"disk": "unit disk", "square": "unit square"}.get(
                self.domain, f"mesh {self.domain}" if self.domain else "")
            _set(self, "description", ", ".join(([where] if where else []) + words)
                 + (", exact solution given" if self.exact is not None else ""))
        _set(self, "described", (data, self.exact, self.poincare, domain))

    def _domain(self):
        """What the hierarchy meshes: the scene's domain name, else its coarse mesh T_0."""
        return getattr(self.hierarchy, "domain", None) or self.hierarchy.meshes[0]

    @property
    def mesh(self) -> Mesh:
        """The computational mesh T_J."""
        return self.hierarchy.finest

    @property
    def levels(self) -> int:
        return self.hierarchy.levels

    def on_level(self, j: int) -> "Problem":
        """The problem on T_j (nested iteration, §8; docs/choices.md): a shallow copy whose
        hierarchy stops at level j (the same meshes and maps), or the problem itself on its
        finest level."""
        if j == self.levels:
            return self
        return replace(self, hierarchy=self.hierarchy.up_to(j))
