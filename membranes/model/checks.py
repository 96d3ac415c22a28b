"""Checks made before a run starts, so that what cannot work is refused at once (issue 29).

Three kinds of request fail late or never if nobody looks at them first:

* **a size beyond memory.** ``--levels 12`` asks for ~1e10 vertices, ``--h 1e-5`` for ~3e10;
  gmsh or the refinement would run for minutes before anything fails. `check_size` estimates
  the vertex count of the requested mesh and hierarchy from the domain's area and boundary, h
  and the levels (or from a mesh file's header), the memory of the run from the measured
  bytes per vertex of its method, and refuses when that exceeds the memory available to each
  process. ``max_vertices`` (``--max-vertices N``) replaces the memory limit by a vertex count.
* **an output folder that cannot be written** (``--out /proc/x``):
  `membranes.model.folders`.
* **PETSc options that do nothing**: `membranes.model.petsc_options`.

Every check raises ValueError with a one-line message; the command line turns it into exit
code 2. The functions take plain values (sizes, dicts, a communicator) and import nothing
from the rest of the package but `mesh_headers` (plain Python too), so that any driver can
call them before it meshes.
"""

import math
import os
import sys

from .mesh_headers import mesh_file_vertices

# ## Underflow of squares at round-off
#
# The stopping tests and the estimators are roots of sums of squares. Below this size x the
# square of a round-off error on it, (ε x)², is no longer a normal double, and such squares
# read 0: the data's check (membranes.nonlinear.system, ‖W (F, 0)‖) and the estimators'
# (membranes.estimation.estimators, the forces μ u) refuse scales below it (theory §11: the
# problem is positively homogeneous, the data can be rescaled).
UNDERFLOW_SCALE = math.sqrt(sys.float_info.min) / sys.float_info.epsilon     # ≈ 6.7e-139


def check_force_scale(disc):
    """Refuse data whose forces and pressures underflow the estimators' squares (notes above
    and in membranes.estimation.estimators, §11). The forms square fluxes μ_α ∇u (size μ u /
    ℓ) and pressures λ, f_α (μ u / ℓ²), ℓ = C_PF h_Ω the domain's length; on a domain of unit
    size both are about the force μ u. ValueError when min(μ1, μ2) u_data / max(1, ℓ)² <
    UNDERFLOW_SCALE, u_data the data's displacement scale of the Discretisation `disc`
    (`data_scales`, nearly the same on every mesh of a hierarchy, so a certified nested run
    checks its coarsest level before any Newton step, and `Estimators` its own). Below ℓ = 1
    the force alone is checked: the fluxes and pressures are larger. Without the ℓ, a square
    of side 1e100 with loads 1e-200 (pressures 1e-200, squared to 0) ran adaptive Newton to
    an iterate with negative pressures whose η fell below the energy error (0.954 of it).
    Collective."""
    mu = (float(disc.mu1), float(disc.mu2))
    u_data = disc.data_scales()[0]
    ell = float(disc.poincare)
    size = min(mu) * u_data / max(1.0, ell) ** 2
    if size < UNDERFLOW_SCALE:
        raise ValueError(f"the estimators underflow double precision: forces and pressures "
                         f"of size min(mu1, mu2) u / max(1, l)^2 = {size:g} < "
                         f"{UNDERFLOW_SCALE:.1e} (mu1 = {mu[0]:g}, mu2 = {mu[1]:g}, "
                         f"displacements u = {u_data:g}, length l = C_PF h_Omega = {ell:g}); "
                         f"rescale the data: the solution scales with f / mu and g, and a "
                         f"mesh scaled by s with f by 1/s^2 (theory §11)")


# ## Vertex counts of a requested mesh and hierarchy
#
# gmsh meshes a domain of area A and boundary length L with target size h into
# V_0 ≈ c_A A/h² + c_L L/h vertices. Measured with the meshing of membranes.fem.meshes (disk and
# square, h = 0.1 … 0.005): V_0 h²/A → 1.15 as h → 0, and the boundary's share is ~0.6-0.75
# L/h (disk h = 0.005: 146 055 vertices against 145 200 + 940; square: 46 686 against
# 46 400 + 600). An equilateral triangulation of size h would have 2/√3 = 1.155 A/h².
# T_0 = 2 V_0 - V_b - 2 triangles (Euler's formula for a simply connected triangulation with
# V_b ≈ L/h boundary vertices). One uniform refinement adds a vertex on each edge,
# E = V + T - 1, and cuts every triangle into four: V ← V + E, T ← 4 T, so V_J ≈ 4^J V_0
# (the recursion is exact: disk h = 0.2, V_0 = 123, T_0 = 212 gives V_3 = 6 913 as measured).

VERTICES_PER_AREA = 1.16        # c_A: V_0 ≈ c_A A/h² + c_L L/h (gmsh, measured above)
VERTICES_PER_LENGTH = 0.75      # c_L
DOMAINS = {"disk": (math.pi, 2.0 * math.pi),    # (area, boundary length) of the unit disk
           "square": (1.0, 4.0)}                # and of the unit square
# The coarsest meshes gmsh makes of them, (vertices, triangles), whatever h: h ≥ 0.3 on the
# disk, h ≥ 0.14 on the square give these (measured up to h = 10).
COARSEST = {"disk": (71.0, 117.0), "square": (98.0, 162.0)}


def coarse_mesh_size(h, domain="disk"):
    """(V_0, T_0): the estimated vertices and triangles of a gmsh mesh of `domain` ('disk',
    'square' or (area, boundary length)) with target size h (module notes)."""
    area, length = DOMAINS[domain] if isinstance(domain, str) else domain
    h = float(h)
    if not (math.isfinite(h) and h > 0):
        raise ValueError(f"mesh size h must be a positive finite number, got {h}")
    boundary = length / h
    # (area / h / h: h ** 2 underflows to 0 for h < 1e-154; this overflows to inf instead)
    vertices = VERTICES_PER_AREA * area / h / h + VERTICES_PER_LENGTH * boundary
    triangles = 2.0 * vertices - boundary - 2.0
    coarsest = COARSEST.get(domain) if isinstance(domain, str) else None
    if coarsest is not None and vertices < coarsest[0]:
        return coarsest
    return vertices, max(triangles, 1.0)


def refined_vertices(vertices, triangles, levels, euler=1.0):
    """Vertices after `levels` uniform refinements of a triangulation with `vertices` and
    `triangles` (V ← V + E, E = V + T - χ, T ← 4 T; module notes) of Euler characteristic
    χ = `euler` (V - E + T: 1 for a simply connected domain, and refinement keeps it). Floats:
    no overflow for absurd requests, which end at inf (after ~500 levels, so --levels 1e20
    returns at once)."""
    return _level_vertices(vertices, triangles, levels, euler)[-1]


def _level_vertices(vertices, triangles, levels, euler=1.0):
    """[V_0, …, V_J] (module notes), cut short at the first inf (every later level is inf)."""
    v, t, chi = float(vertices), float(triangles), float(euler)
    out = [v]
    for _ in range(int(levels)):
        if math.isinf(v):
            break
        v, t = v + (v + t - chi), 4.0 * t
        out.append(v)
    return out


def hierarchy_vertices(vertices, triangles, levels, euler=1.0):
    """Vertices of every level T_0 … T_J (the hierarchy is kept whole): Σ_j V_j ≈ 4/3 V_J."""
    return sum(_level_vertices(vertices, triangles, levels, euler))


def estimate_vertices(h=None, levels=0, domain="disk", mesh_file=None, counts=None):
    """(finest, all levels): the estimated vertices of T_J and of the whole hierarchy
    T_0 … T_J for a gmsh mesh of `domain` with size h, or of the mesh file `mesh_file`,
    refined `levels` times; exact from `counts` (V_0, T_0, χ) of a mesh read. From a file's
    header, a lower bound (its triangles are not counted: T_0 ≥ V_0 - 2, a strip, where a
    mesh has up to 2 V_0), so that no run within --max-vertices is refused; the exact count
    once the file is read decides. (None, None) for a file whose size cannot be read."""
    chi = 1.0
    if counts is not None:
        v0, t0, chi = counts
    elif mesh_file is not None:
        v0 = mesh_file_vertices(mesh_file)
        if v0 is None:
            return None, None
        t0 = max(v0 - 2.0, 1.0)
    else:
        v0, t0 = coarse_mesh_size(h, domain)
    return refined_vertices(v0, t0, levels, chi), hierarchy_vertices(v0, t0, levels, chi)


# ## Memory of a run
#
# Peak resident memory of one process of the distributed core: BASE_BYTES plus, per vertex of
# the finest mesh T_J (its hierarchy included), a slope for the discretisation and solver and
# one for the estimators. The slopes are upper bounds of the peaks measured on the disk (h0 =
# 0.2 refined 5 and 6 times, h0 = 0.132 six times; BENCHMARKS.md, "Memory per vertex"): the
# default method (adaptive, the amg preset, the ν flux, estimators on T_J only) stays below the
# 10 kB per vertex they add up to; what the nested SNES VI peer (the same discretisation and
# an AMG-preconditioned solve) needs is a small part of it, the rest is the estimators' (the
# coloured patch systems, their home layout and shared inverses, the RT_1 fluxes). The paper's
# GMRES + ILU(0) and the multilevel flux have the amg solver's figure and twice the ν flux's,
# upper bounds of their measured peaks too. MUMPS's factors grow faster than N: c N^p, above
# the peaks of exact Newton with MUMPS and no estimators at 1.1e5, 4.4e5 and 9.3e5 vertices by
# 1.3-1.5 (their own growth slows from N^1.31 to N^1.22 over that range; p is kept above it, so
# that larger meshes stay covered). A run on P processes needs about the per-vertex part over
# P on each.

BASE_BYTES = 0.30 * 2 ** 30       # interpreter, dolfinx, PETSc; fixed costs of levels
SOLVER_BYTES_PER_VERTEX = {       # discretisation, Newton systems and their Krylov solve
    "gmres": 2500.0,              # GMRES(30) + ILU(0) on the full 3N system
    "vertex_amg": 2500.0,         # the amg preset: FGMRES + mean/gap BoomerAMG, 2N system
}
DIRECT_COEFFICIENT, DIRECT_EXPONENT = 130.0, 1.35   # MUMPS LU of the full system: c N^p bytes
ESTIMATOR_BYTES_PER_VERTEX = {    # the a posteriori estimators (§7), by algebraic flux
    "nu": 7500.0,
    "multilevel": 15000.0,        # twice the ν flux's
}


def _solver_key(linear_solver="gmres", pc_type=None):
    if linear_solver == "direct":
        return "direct"
    return "vertex_amg" if pc_type == "vertex_amg" else "gmres"


def estimate_memory(vertices, linear_solver="gmres", pc_type=None, estimators=True,
                    alg_flux="nu", processes=1, replicated=True):
    """Bytes one process needs for a run on a finest mesh of `vertices` vertices (module
    notes): BASE_BYTES, the linear solver's part (`linear_solver` 'gmres' with `pc_type`
    'vertex_amg' or another PETSc PC, or 'direct') and, with `estimators`, the estimators'
    with algebraic flux `alg_flux` ('nu' or 'multilevel'); `linear_solver=None`: the leanest
    method (what any run needs). With `processes` > 1 and not `replicated` the part that
    grows with the mesh is shared out."""
    n = float(vertices)
    if linear_solver is None:
        grows = min(SOLVER_BYTES_PER_VERTEX.values()) * n
    else:
        key = _solver_key(linear_solver, pc_type)
        grows = DIRECT_COEFFICIENT * n ** DIRECT_EXPONENT if key == "direct" else \
            SOLVER_BYTES_PER_VERTEX[key] * n
        if estimators:
            grows += ESTIMATOR_BYTES_PER_VERTEX[alg_flux or "nu"] * n
    share = 1 if replicated else max(int(processes), 1)
    return BASE_BYTES + grows / share


def heaviest(vertices, methods):
    """The one of `methods` (dicts of `estimate_memory`'s arguments) that needs the most
    memory on a finest mesh of `vertices` vertices: what a command that runs all of them one
    after another (`membranes report`, `membranes stability`) must check, not the leanest
    (MUMPS's c N^p grows faster than any of the iterative solvers' slopes)."""
    return max(methods, key=lambda method: estimate_memory(vertices, **method))


def largest_fitting(available, **method):
    """The most vertices whose run (`estimate_memory` with `method`) fits in `available`
    bytes, to 0.1 % (0 if not even the base does): bisection, the estimate grows with N."""
    if estimate_memory(1.0, **method) > available:
        return 0
    low, high = 1.0, 2.0
    while estimate_memory(high, **method) <= available:
        low, high = high, 2.0 * high
    while high > 1.001 * low:
        mid = math.sqrt(low * high)
        low, high = (mid, high) if estimate_memory(mid, **method) <= available else (low, mid)
    return int(low)


# ## Memory available to each process

def _meminfo_available():
    """MemAvailable of /proc/meminfo (the kernel's estimate of what can be allocated without
    swapping), in bytes; None where there is no such file."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _cgroup_room():
    """What the process's memory cgroup still allows (limit - usage, v2 or v1), or None."""
    for limit, usage in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                         ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                          "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            with open(limit) as f:
                text = f.read().strip()
            if text == "max" or float(text) >= 2.0 ** 60:
                return None
            with open(usage) as f:
                return float(text) - float(f.read())
        except (OSError, ValueError):
            continue
    return None


def own_limits():
    """The process's own limits on its memory (`ulimit -v`, RLIMIT_AS; `ulimit -d`,
    RLIMIT_DATA), as text for a message ('ulimit -v: 977 MiB'), or '' without one. The size
    checks do not count them: their estimates are upper bounds, 2.2-2.6 times the default
    method's measured peaks (1.1e5-9.3e5 vertices), and would refuse runs that fit under a
    limit; a run that meets one ends with one line (membranes.app.cli)."""
    try:
        import resource
        limits = [(resource.getrlimit(resource.RLIMIT_AS)[0], "ulimit -v"),
                  (resource.getrlimit(resource.RLIMIT_DATA)[0], "ulimit -d")]
    except (ImportError, OSError, ValueError):
        return ""
    return ", ".join(f"{name}: {_bytes(limit)}" for limit, name in limits
                     if limit != resource.RLIM_INFINITY)


def processes_on_node(comm=None):
    """How many processes of the run share this node: those of `comm` on it (collective on
    `comm`), or without one those the MPI launcher says it started here (Open MPI, MPICH,
    Slurm), 1 if none says."""
    if comm is not None and comm.size > 1:
        from mpi4py import MPI
        node = comm.Split_type(MPI.COMM_TYPE_SHARED)
        try:
            return node.size
        finally:
            node.Free()
    for name in ("OMPI_COMM_WORLD_LOCAL_SIZE", "MPI_LOCALNRANKS", "SLURM_NTASKS_PER_NODE"):
        try:
            return max(int(os.environ[name]), 1)
        except (KeyError, ValueError):
            continue
    return 1


def available_memory(comm=None):
    """Bytes each process of the run may use: the node's MemAvailable (or its cgroup's room,
    if smaller) over the processes on the node (`processes_on_node`), the least over `comm`
    (collective on `comm` when given with several processes). None where it cannot be read."""
    room = _meminfo_available()
    cgroup = _cgroup_room()
    if room is None or (cgroup is not None and cgroup < room):
        room = cgroup
    on_node = processes_on_node(comm)   # (collective: also where room is None)
    share = None if room is None else room / on_node
    if comm is not None and comm.size > 1:
        shares = [s for s in comm.allgather(share) if s is not None]
        share = min(shares) if shares else None
    return share


def resident_memory():
    """This process's resident memory now, in bytes (/proc/self/statm); 0 where unknown."""
    try:
        with open("/proc/self/statm") as f:
            return float(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0


def room_for_run(comm):
    """Bytes each process may use for a run whose mesh it already holds: `available_memory`
    plus what the process holds now (the least over `comm`). The estimate a run is checked
    against is its whole peak, interpreter, dolfinx and mesh hierarchy included, and what
    the process already holds of it is no longer in MemAvailable: without it a run that
    fitted at the scene's check would be refused once its mesh was built. Collective."""
    available = available_memory(comm)
    if available is None:
        return None
    held = resident_memory()
    if comm is not None and comm.size > 1:
        from mpi4py import MPI
        held = comm.allreduce(held, op=MPI.MIN)
    return available + held


# ## The size check

def _about(n, show, unit=""):
    """'about 2.5e10' (`show` formats n), or for an estimate that overflowed (h = 1e-300,
    --levels 1000) what it exceeds."""
    return f"about {show(n)}" if math.isfinite(n) else f"more than 1e308{unit}"


def _bytes(n):
    for unit, scale in (("TiB", 2 ** 40), ("GiB", 2 ** 30), ("MiB", 2 ** 20)):
        if n >= scale or unit == "MiB":
            return f"{n / scale:.3g} {unit}"


def _count(n):
    """2.5e10, 4.3e6, 9412: a vertex count to two digits, or whole below 1e4."""
    if n < 1e4:
        return str(round(n))
    mantissa, exponent = f"{n:.1e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def positive_integer(name, value):
    """`value` as a positive int: an integer (numpy's too), not a bool and not a float (2.5
    would be cut to 2 without a word); ValueError naming `name` otherwise."""
    import numbers
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def check_max_vertices(max_vertices):
    """`max_vertices` as a positive int (None stays None); ValueError otherwise."""
    if max_vertices is None:
        return None
    try:                                 # (text too, as every number of the API: '1e6')
        value = float(max_vertices)
    except (TypeError, ValueError):
        value = math.nan
    if isinstance(max_vertices, bool) or not value.is_integer() or value < 1:
        raise ValueError(f"max_vertices must be a positive integer, got {max_vertices}")
    return int(value)


def describe_request(h=None, levels=0, domain="disk", mesh_file=None):
    """'h = 0.05 and 12 levels on the unit disk' (the words of the size check's message)."""
    size = ""
    if mesh_file is not None:
        where = f"mesh file {mesh_file}"
    elif h is None:
        where = "the given mesh"
    else:
        size = f"h = {h:g}, "
        where = f"the unit {domain}" if isinstance(domain, str) else "the domain"
    return f"{size}{int(levels)} level{'s' if int(levels) != 1 else ''} on {where}"


def check_size(vertices, available=None, max_vertices=None, what="the run", hint=None,
               limit_option=True, **method):
    """Refuse a run on a finest mesh of about `vertices` vertices that will not fit: the
    memory `estimate_memory(vertices, **method)` needs against `available` bytes per process
    (None: not known, no memory check), or, when `max_vertices` is given, `vertices` against
    it instead. ValueError with one line: both figures and the largest size that fits
    (`hint(largest)`, if given, adds how to ask for it), and, where the caller can set one
    (`limit_option`: `solve` and the scenes, not `report` or `stability`), that a vertex
    limit can replace the memory check. Returns the bytes needed."""
    limit = check_max_vertices(max_vertices)
    need = estimate_memory(vertices, **method)
    if limit is not None:
        if vertices > limit:
            extra = f"; {hint(limit)}" if hint is not None else ""
            # (in full: near the limit, two digits would show the two numbers alike)
            raise ValueError(f"{what} has {_about(vertices, lambda n: str(round(n)))} "
                             f"vertices, more than the limit --max-vertices {limit} "
                             f"(max_vertices){extra}")
        return need
    if available is None or need <= available:
        return need
    largest = largest_fitting(available, **method)
    extra = f" ({hint(largest)})" if hint is not None else ""
    option = ("; max_vertices=N (`membranes solve --max-vertices N`) sets a vertex limit "
              "instead") if limit_option else ""
    raise ValueError(f"{what} has {_about(vertices, _count)} vertices and needs "
                     f"{_about(need, _bytes, ' bytes')} of memory, but {_bytes(available)} is "
                     f"available per process: the largest run that fits has about "
                     f"{_count(largest)} vertices{extra}{option}")


def largest_levels(limit, h=None, domain="disk", mesh_file=None, counts=None):
    """The most uniform refinements whose finest mesh keeps within `limit` vertices, or -1."""
    levels = -1
    while levels < 64 and \
            estimate_vertices(h, levels + 1, domain, mesh_file, counts)[0] <= limit:
        levels += 1
    return levels


def smallest_h(limit, levels=0, domain="disk"):
    """The smallest gmsh size h, rounded up to two digits, whose mesh refined `levels` times
    keeps within `limit` vertices (the estimate falls as h grows: bisection on log h); None
    if even the coarsest mesh, refined so often, has more."""
    low, high = 1e-12, 1e6                 # too many vertices at low, few enough at high
    if estimate_vertices(high, levels, domain)[0] > limit:
        return None
    for _ in range(100):
        mid = math.sqrt(low * high)
        if estimate_vertices(mid, levels, domain)[0] <= limit:
            high = mid
        else:
            low = mid
    unit = 10.0 ** (math.floor(math.log10(high)) - 1)
    return math.ceil(high / unit * (1 - 1e-12)) * unit


def check_request(h=None, levels=0, domain="disk", mesh_file=None, max_vertices=None,
                  available=None, comm=None, counts=None, limit_option=True, **method):
    """The size check before meshing (issue 29): the estimated finest mesh of a gmsh mesh of
    `domain` ('disk', 'square' or (area, boundary length)) at size h, or of `mesh_file`,
    refined `levels` times (`counts`: the file's mesh read, `estimate_vertices`; a mesh given
    through the API, `counts` without a file or h), against
    the memory of `method` (`estimate_memory`'s arguments;
    none: the leanest method) on `available` bytes per process (default
    `available_memory(comm)`), or against `max_vertices`. ValueError as `check_size`;
    returns the estimated vertex count (None for a file that cannot be read: the mesh reader
    reports it)."""
    vertices, _ = estimate_vertices(h, levels, domain, mesh_file, counts)
    if vertices is None:
        check_max_vertices(max_vertices)
        return None
    if max_vertices is None and available is None:
        available = available_memory(comm)
    method = method or {"linear_solver": None}

    def hint(largest):
        fit = largest_levels(largest, h, domain, mesh_file, counts)
        if mesh_file is not None or h is None:
            this = "this file" if mesh_file is not None else "this mesh"
            return f"at most {fit} levels on {this}" if fit >= 0 else f"not {this}"
        h_min = smallest_h(largest, levels, domain)
        ways = [] if h_min is None else [f"h >= {h_min:g} with {int(levels)} levels"]
        if fit >= 0 and fit != int(levels):
            ways.append(f"at most {fit} levels at h = {h:g}")
        if ways:
            return " or ".join(ways)
        if isinstance(domain, str) and domain in COARSEST:
            return (f"even gmsh's coarsest mesh of the {domain} has {COARSEST[domain][0]:.0f} "
                    f"vertices")
        return f"no gmsh mesh of this domain with {int(levels)} levels is that small"

    check_size(vertices, available, max_vertices,
               what=describe_request(h, levels, domain, mesh_file), hint=hint,
               limit_option=limit_option, **method)
    return vertices
