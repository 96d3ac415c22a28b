"""The checks made before a run (membranes.model.checks, issue 29): vertex estimates against the
meshes gmsh and the refinement make, the memory check (a run of about 1e6 vertices fits in
24 GiB; 1e10 does not), the output folder probe, PETSc option parsing and PETSc's record of
the options it used."""

import math
import os

import numpy as np
import pytest
from mpi4py import MPI

from membranes import scenes, solve
from membranes.fem.hierarchy import build_hierarchy
from membranes.fem.meshes import unit_disk, unit_square
from membranes.model import checks, folders, mesh_headers, petsc_options

from .conftest import mpirun, scene

GiB = 2.0 ** 30


def _counts(mesh):
    return (mesh.topology.index_map(0).size_global, mesh.topology.index_map(2).size_global)


# ## Vertex estimates

@pytest.mark.parametrize("domain,h", [("disk", 0.05), ("disk", 0.02), ("square", 0.02),
                                      ("square", 0.01)])
def test_coarse_estimate_against_gmsh(domain, h):
    """V_0 ≈ 1.16 A/h² + 0.75 L/h: the constants were fitted on these meshes and h = 0.005;
    the model leaves a few per cent (the boundary's share varies with h)."""
    mesh = (unit_disk if domain == "disk" else unit_square)(h)
    vertices, triangles = _counts(mesh)
    v0, t0 = checks.coarse_mesh_size(h, domain)
    assert abs(v0 / vertices - 1) < 0.03
    assert abs(t0 / triangles - 1) < 0.03


def test_refinement_recursion_is_exact():
    """V ← V + E, E = V + T - 1, T ← 4 T is Euler's formula on a simply connected
    triangulation: from the coarse mesh's own counts it gives every level's count exactly."""
    h = build_hierarchy(unit_disk(0.2), 3)
    v0, t0 = _counts(h.meshes[0])
    for j, mesh in enumerate(h.meshes):
        assert checks.refined_vertices(v0, t0, j) == _counts(mesh)[0]
    assert checks.hierarchy_vertices(v0, t0, 3) == sum(_counts(m)[0] for m in h.meshes)


def test_estimates_grow_with_the_levels_whatever_h():
    """A refinement adds vertices: the estimated V_J is positive and grows with J for any h
    and domain (area, boundary length). At a size h far above the domain's the coarse
    formula T_0 = 2 V_0 - L/h - 2 is negative (V_0 < 1 + L/(2h)); a triangulation has at
    least one triangle, and with T_0 < χ the recursion V ← 2 V + T - χ would shrink V and
    end below 0. Exact comparisons: the recursion is a few float additions of numbers >= 1."""
    for domain in ((1.0, 4.0), (math.pi, 2.0 * math.pi), (0.01, 0.4)):
        for h in (0.1, 10.0, 1e3):
            v0, t0 = checks.coarse_mesh_size(h, domain)
            assert v0 > 0 and t0 >= 1.0
            finest = [checks.estimate_vertices(h, j, domain)[0] for j in range(4)]
            assert finest[0] == v0
            assert all(0 < a < b for a, b in zip(finest, finest[1:])), (domain, h, finest)


def test_estimate_of_a_hierarchy():
    """disk, h = 0.2, J = 3: 6 913 vertices measured; the estimate from h alone within 8 %
    (the coarse estimate's error at this coarse h, carried through the refinement)."""
    finest, total = checks.estimate_vertices(0.2, 3, "disk")
    assert abs(finest / 6913 - 1) < 0.08
    assert finest < total < 4 / 3 * finest + 200
    assert checks.estimate_vertices(0.05, 12, "disk")[0] > 1e10       # the request


@pytest.mark.parametrize("version, binary", [(1, 0), (2.2, 0), (2.2, 1), (4, 0), (4.1, 0),
                                             (4.1, 1)])
def test_mesh_file_vertices_from_the_header(version, binary, tmp_path):
    """The node count of every format gmsh 4.8 writes, ASCII and binary (MSH 1 and 4.0 in
    ASCII only), read from the header alone: MSH 1 has no $MeshFormat (its count was not
    read, and such a file not size-checked), MSH 4.0 counts its nodes in another place of
    the $Nodes line than 4.1."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("r")
        gmsh.model.occ.addRectangle(0, 0, 0, 2, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.05)
        gmsh.model.mesh.generate(2)
        nodes = len(gmsh.model.mesh.getNodes()[0])
        gmsh.option.setNumber("Mesh.MshFileVersion", version)
        gmsh.option.setNumber("Mesh.Binary", binary)
        path = str(tmp_path / "r.msh")
        gmsh.write(path)
    finally:
        gmsh.finalize()
    assert mesh_headers.mesh_file_vertices(path) == nodes
    finest, _ = checks.estimate_vertices(levels=2, mesh_file=path)
    assert finest == checks.refined_vertices(nodes, nodes - 2, 2)     # a lower bound


def test_mesh_file_that_is_not_one(tmp_path):
    """Not a gmsh file (or none at all): no estimate, so that the mesh reader says what is
    wrong with it."""
    garbage = tmp_path / "garbage.msh"
    garbage.write_text("this is not a mesh\n")
    for path in (garbage, tmp_path / "missing.msh", tmp_path):
        assert mesh_headers.mesh_file_vertices(str(path)) is None
        assert checks.check_request(levels=20, mesh_file=str(path)) is None


# ## Memory

def test_a_run_of_about_1e6_vertices_fits_in_24_GiB():
    """The issue's example: the default method (adaptive, the amg preset, the ν flux: about
    9.5 kB per vertex measured on the distributed core) and the other iterative ones are
    admitted at 1e6 vertices on a machine with 24 GiB. So is MUMPS, whose factors grow faster
    than N: exact Newton with MUMPS and no estimators peaked at 0.90, 3.97 and 9.58 GiB at
    1.1e5, 4.4e5 and 9.3e5 vertices (BENCHMARKS.md); its estimate lies above each, by less than
    1.6 (the 0.3 GiB base included), and at 2e6 vertices it is refused with what fits."""
    default = {"linear_solver": "gmres", "pc_type": "vertex_amg", "estimators": True,
               "alg_flux": "nu"}
    need = checks.check_size(1e6, 24 * GiB, **default)
    assert 8.6 * GiB < need < 11 * GiB       # 8.55 GiB measured at 9.3e5 vertices
    for method in ({"linear_solver": "gmres", "pc_type": "ilu", "alg_flux": "nu"},
                   {"linear_solver": "gmres", "pc_type": "vertex_amg",
                    "alg_flux": "multilevel"},
                   {"linear_solver": "gmres", "estimators": False},
                   {"linear_solver": None}):
        assert checks.check_size(1e6, 24 * GiB, **method) < 24 * GiB
    assert checks.largest_fitting(24 * GiB, **default) > 1.5e6
    direct = {"linear_solver": "direct", "estimators": False}
    for n, peak in ((109057, 0.898), (435201, 3.969), (931329, 9.581)):
        need = checks.check_size(n, 24 * GiB, **direct) / GiB
        assert peak < need < 1.6 * peak, (n, need, peak)
    with pytest.raises(ValueError, match="the largest run that fits has about 1.[0-9]e6"):
        checks.check_size(2e6, 24 * GiB, **direct)
    # h = 0.05 with 5 levels (~1.6e6 vertices): admitted through check_request as well
    assert checks.check_request(0.05, 5, "disk", available=24 * GiB, **default) > 1e6


def test_the_part_that_grows_with_the_mesh_is_shared_out():
    """A run on P processes needs BASE_BYTES plus the per-vertex part over P on each (module
    notes; `solve` on a distributed mesh, processes=P, replicated=False), and the whole part
    where every process holds the whole mesh (replicated, the default). The MPI test of
    `solve` above takes its figure from estimate_memory itself, so it cannot see the share;
    here the parts are compared with each other (exact up to the round-off of one division:
    relative 1e-12)."""
    base = checks.BASE_BYTES
    for method in ({"linear_solver": "gmres", "pc_type": "vertex_amg"},
                   {"linear_solver": "direct", "estimators": False}, {"linear_solver": None}):
        whole = checks.estimate_memory(1e6, **method) - base
        assert whole > 0
        for p in (2, 3, 8):
            shared = checks.estimate_memory(1e6, processes=p, replicated=False, **method)
            assert shared - base == pytest.approx(whole / p, rel=1e-12)
            assert checks.estimate_memory(1e6, processes=p, **method) - base == whole


def test_heaviest_is_the_method_that_needs_the_most():
    """`heaviest` (what `report` and `stability` check) is the method of the largest
    estimate, which depends on the size: MUMPS's c N^p (p > 1) lies below the amg preset's
    slope on small meshes and above it on large ones (130 N^1.35 = 1.5e6 bytes against 2.5e6
    at N = 1e3; 1.6e10 against 2.5e9 at N = 1e6), so neither order of the list decides."""
    amg = {"linear_solver": "gmres", "pc_type": "vertex_amg", "estimators": True}
    direct = {"linear_solver": "direct", "estimators": True}
    for methods in ([amg, direct], [direct, amg]):
        assert checks.heaviest(1e3, methods) is amg
        assert checks.heaviest(1e6, methods) is direct
        for n in (1e3, 1e6):
            assert checks.estimate_memory(n, **checks.heaviest(n, methods)) == \
                max(checks.estimate_memory(n, **m) for m in methods)


@pytest.mark.parametrize("method", [{"linear_solver": "gmres"}, {"linear_solver": "direct"},
                                    {"linear_solver": None}])
def test_largest_fitting_is_the_bound(method):
    for available in (0.5 * GiB, 24 * GiB, 1e15):
        n = checks.largest_fitting(available, **method)
        assert checks.estimate_memory(n, **method) <= available < \
            checks.estimate_memory(1.002 * n + 1, **method)
    assert checks.largest_fitting(0.1 * GiB, **method) == 0        # below the base


def test_vertex_counts_in_messages():
    """Counts below 1e4 are given whole ('9412'), larger ones to two digits ('2.5e10')."""
    assert [checks._count(n) for n in (71, 9412.4, 9999.4, 10000, 2.5e10)] == \
        ["71", "9412", "9999", "1.0e4", "2.5e10"]


def test_a_run_beyond_memory_is_refused_with_both_figures():
    with pytest.raises(ValueError) as e:
        checks.check_request(0.05, 12, "disk", available=24 * GiB)
    message = str(e.value)
    assert "\n" not in message
    assert "2.5e10 vertices" in message and "24 GiB is available" in message
    largest = checks.largest_fitting(24 * GiB, linear_solver=None)
    assert f"about {checks._count(largest)} vertices" in message
    fits = checks.largest_levels(largest, 0.05, "disk")
    assert f"at most {fits} levels at h = 0.05" in message
    assert checks.estimate_vertices(0.05, fits, "disk")[0] <= largest < \
        checks.estimate_vertices(0.05, fits + 1, "disk")[0]
    with pytest.raises(ValueError, match=r"h >= [0-9.e-]+ with 0 levels"):
        checks.check_request(1e-5, 0, "disk", available=24 * GiB)


def test_refusals_name_only_what_the_command_can_set():
    """A run beyond memory names solve's vertex limit, which `report` and `stability` do not
    have (they said `membranes solve --max-vertices N` all the same); a limit below gmsh's
    coarsest mesh of the disk (71 vertices) says so, where it said "no mesh with 0
    levels"."""
    with pytest.raises(ValueError, match=r"--max-vertices N`\) sets a vertex limit"):
        checks.check_request(0.16, 12, "disk", available=24 * GiB)
    from membranes.app.report import check_memory
    with pytest.raises(ValueError, match="available per process") as e:
        check_memory(0.16, 12, "disk", MPI.COMM_SELF)
    assert "max-vertices" not in str(e.value) and "max_vertices" not in str(e.value)
    for levels in (0, 2):
        with pytest.raises(ValueError, match="even gmsh's coarsest mesh of the disk has 71 "
                                             "vertices$"):
            checks.check_request(0.3, levels, "disk", max_vertices=50)


def test_smallest_h_is_the_bound():
    limit = 1e6
    h = checks.smallest_h(limit, 2, "square")
    assert checks.estimate_vertices(h, 2, "square")[0] <= limit
    assert checks.estimate_vertices(0.98 * h, 2, "square")[0] > limit
    assert checks.smallest_h(limit, 40, "disk") is None      # 4^40 > 1e6 whatever h


def test_max_vertices_raises_or_lowers_the_limit():
    with pytest.raises(ValueError, match="more than the limit --max-vertices 1000"):
        checks.check_request(0.05, 1, "disk", max_vertices=1000)
    # a size beyond the memory given passes with a limit above it
    assert checks.check_request(0.05, 6, "disk", available=1 * GiB,
                                max_vertices=10 ** 8) > 6e6
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="max_vertices"):
            checks.check_max_vertices(bad)


def test_a_run_of_exactly_max_vertices_is_accepted():
    """--max-vertices N is the most vertices a run may have (docs: "refuse ... more vertices
    than `max_vertices`"): a run of N vertices passes, one of N + 1 is refused, whatever the
    memory; and from a mesh's exact counts (V_0, T_0, χ) the refinement recursion gives the
    count compared (V_1 = V_0 + V_0 + T_0 - χ: 10 + 10 + 12 - 1 = 31)."""
    assert checks.check_size(1000, available=1.0, max_vertices=1000) > 0
    with pytest.raises(ValueError, match="about 1001 vertices, more than the limit"):
        checks.check_size(1001, available=1.0, max_vertices=1000)
    assert checks.check_request(levels=1, mesh_file="unused", max_vertices=31,
                                counts=(10, 12, 1)) == 31
    with pytest.raises(ValueError, match="more than the limit --max-vertices 30"):
        checks.check_request(levels=1, mesh_file="unused", max_vertices=30, counts=(10, 12, 1))


def test_the_hint_counts_a_level_of_exactly_the_limit():
    """A limit that the finest mesh of some level meets exactly admits that level: from a
    mesh's counts (V_0, T_0, χ) = (10, 12, 1), V_1 = 31 and V_2 = 109 (the exact recursion,
    test above), so --max-vertices 31 refuses 2 levels and names 1 as the most that fits,
    and 30 names 0."""
    for limit, fit in ((31, 1), (30, 0), (109, 2)):
        with pytest.raises(ValueError, match=f"at most {fit} levels on this mesh$"):
            checks.check_request(levels=3, max_vertices=limit, counts=(10, 12, 1))


def test_a_bad_limit_is_refused_with_a_mesh_file_it_cannot_size(tmp_path):
    """A mesh file whose size cannot be read is left to the mesh reader, but a bad
    max_vertices is still refused at once (the check of the value does not need the
    count)."""
    garbage = tmp_path / "garbage.msh"
    garbage.write_text("this is not a mesh\n")
    for bad in (0, -1, 2.5, True, "many"):
        with pytest.raises(ValueError, match="max_vertices must be a positive integer"):
            checks.check_request(levels=1, mesh_file=str(garbage), max_vertices=bad)
    assert checks.check_request(levels=1, mesh_file=str(garbage), max_vertices=5) is None


def test_force_scale_check_is_where_round_off_squares_underflow():
    """UNDERFLOW_SCALE is the size x below which the square of a round-off error on x,
    (ε x)², is no longer a normal double (module notes, theory §11): (ε S)² is normal, (ε S/2)²
    is not. check_force_scale refuses forces min(μ1, μ2) u below it (μ u = 1e-145: round-off
    squares of the estimators' forces are subnormal there) and accepts them above (1e-130).
    (The exact threshold is a power of two apart from S's rounding: factors 2 on either side.)"""
    import sys
    from types import SimpleNamespace
    eps, tiny = sys.float_info.epsilon, sys.float_info.min
    scale = checks.UNDERFLOW_SCALE
    assert (eps * 2 * scale) ** 2 >= tiny and (eps * scale / 2) ** 2 < tiny

    def disc(u, mu=(1.0, 1.0), ell=1.0):
        return SimpleNamespace(mu1=mu[0], mu2=mu[1], data_scales=lambda: (u, 1.0),
                               poincare=ell)
    with pytest.raises(ValueError, match="the estimators underflow double precision"):
        checks.check_force_scale(disc(1e-145))
    with pytest.raises(ValueError, match="the estimators underflow double precision"):
        checks.check_force_scale(disc(1e-120, (1e-25, 1.0)))     # the smaller modulus counts
    checks.check_force_scale(disc(1e-130))
    checks.check_force_scale(disc(1e-130, (1.0, 1e3)))
    # on a domain of length ℓ = C_PF h_Ω > 1 the pressures μ u / ℓ² count (1e-145, 1e-130
    # as above), below 1 the forces alone (the fluxes μ u / ℓ and pressures are larger)
    with pytest.raises(ValueError, match="forces and pressures of size .* = 1e-145"):
        checks.check_force_scale(disc(1e-5, ell=1e70))
    checks.check_force_scale(disc(1e-10, ell=1e60))
    checks.check_force_scale(disc(1e-130, ell=1e-100))


def test_force_scale_check_is_at_the_underflow_scale():
    """The refusal is at UNDERFLOW_SCALE itself, not some orders of magnitude away from it:
    forces min(μ1, μ2) u = S/2 are refused and 2 S accepted (the factors 2 on either side of
    the test above: the threshold is exact up to S's rounding), with either modulus the
    smaller one."""
    from types import SimpleNamespace
    scale = checks.UNDERFLOW_SCALE

    def disc(u, mu):
        return SimpleNamespace(mu1=mu[0], mu2=mu[1], data_scales=lambda: (u, 1.0),
                               poincare=0.5)
    for mu in ((1.0, 1.0), (1e-3, 1.0), (1.0, 1e-3)):
        small = min(mu)
        with pytest.raises(ValueError, match="the estimators underflow double precision"):
            checks.check_force_scale(disc(scale / 2 / small, mu))
        checks.check_force_scale(disc(2 * scale / small, mu))


def test_available_memory_is_memavailable_per_process(monkeypatch):
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    monkeypatch.delenv("OMPI_COMM_WORLD_LOCAL_SIZE", raising=False)
    monkeypatch.delenv("MPI_LOCALNRANKS", raising=False)
    monkeypatch.delenv("SLURM_NTASKS_PER_NODE", raising=False)
    alone = checks.available_memory()
    assert 0 < alone <= total
    monkeypatch.setenv("OMPI_COMM_WORLD_LOCAL_SIZE", "4")
    assert checks.processes_on_node() == 4
    # a launcher's count that is no count is passed over; 0 counts as this process alone
    # (a share of the memory over 0 processes raised ZeroDivisionError)
    monkeypatch.setenv("OMPI_COMM_WORLD_LOCAL_SIZE", "four")
    monkeypatch.setenv("MPI_LOCALNRANKS", "0")
    assert checks.processes_on_node() == 1
    monkeypatch.setattr(checks, "_meminfo_available", lambda: 20 * GiB)
    monkeypatch.setattr(checks, "_cgroup_room", lambda: None)
    assert checks.available_memory() == 20 * GiB
    monkeypatch.delenv("MPI_LOCALNRANKS")
    monkeypatch.setenv("OMPI_COMM_WORLD_LOCAL_SIZE", "4")
    # the other three processes share the node (a fixed MemAvailable: it moves between reads)
    monkeypatch.setattr(checks, "_meminfo_available", lambda: 20 * GiB)
    monkeypatch.setattr(checks, "_cgroup_room", lambda: None)
    assert checks.available_memory() == 5 * GiB
    monkeypatch.setattr(checks, "_cgroup_room", lambda: 8 * GiB)    # a container's limit
    assert checks.available_memory() == 2 * GiB


UNEVEN_MEMORY = """
import os
from mpi4py import MPI
from membranes.model import checks
for name in ("OMPI_COMM_WORLD_LOCAL_SIZE", "MPI_LOCALNRANKS", "SLURM_NTASKS_PER_NODE"):
    os.environ.pop(name, None)             # (the communicator counts, not the launcher)
GiB = 2.0 ** 30
comm = MPI.COMM_WORLD
r = comm.rank
checks._cgroup_room = lambda: None
checks.resident_memory = lambda: (r + 1) * GiB
said = [checks.processes_on_node(comm)]
checks._meminfo_available = lambda: (r + 1) * 4 * GiB
said += [checks.available_memory(comm) / GiB, checks.room_for_run(comm) / GiB]
checks._meminfo_available = lambda: None if r == 1 else 4 * GiB
said += [checks.available_memory(comm) / GiB]
said = comm.gather(said, root=0)
print(repr(said) if r == 0 else "", flush=True)
"""


def test_uneven_memory_of_the_processes_gives_the_least(tmp_path):
    """`mpirun -n 2` on one node: both processes share the node (processes_on_node 2, from
    the communicator, without the launcher's variables) and each may use the least share of
    any process: MemAvailable of 4 and 8 GiB (as the node's memory moves between the reads)
    gives 4/2 = 2 GiB on both, and the room for a run adds the least memory held (1 and 2
    GiB held: 3 GiB), the same figure on every process so that all refuse or none. A process
    that cannot read its memory does not count (4/2 from the other): it took no part in the
    count of the node's processes, a collective, and both waited for ever. Exact: sums and
    halves of powers of two. (A timeout of a minute: the run takes seconds, and a wait for
    ever must fail the test.)"""
    import ast
    proc = mpirun(["-c", UNEVEN_MEMORY], timeout=60)
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert said == [[2, 2.0, 3.0, 2.0]] * 2, said


def test_a_run_counts_the_memory_its_process_holds(monkeypatch):
    """A run is checked against its whole peak (interpreter, dolfinx, mesh hierarchy
    included), and once the mesh is built the process already holds part of it, which
    MemAvailable no longer counts: the room is MemAvailable's share plus the process's
    resident memory. Without it a run whose estimate fitted before meshing was refused after
    (a report at 2.4e6 vertices: 22.23 GiB needed, 22.5 free before, 20.8 after)."""
    from membranes import solve
    problem = scenes.disk(h=0.5)
    n = problem.mesh.topology.index_map(0).size_global
    need = checks.estimate_memory(n, linear_solver="gmres", pc_type="vertex_amg",
                                  estimators=True, alg_flux="nu")
    assert 0 < checks.resident_memory() < 1024 * GiB
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: need - 2 ** 20)
    monkeypatch.setattr(checks, "resident_memory", lambda: 0.0)
    with pytest.raises(ValueError, match="needs .* of memory"):
        solve(problem)
    monkeypatch.setattr(checks, "resident_memory", lambda: 2.0 ** 21)    # holds 2 MiB
    assert solve(problem).converged
    assert checks.room_for_run(problem.mesh.comm) == need + 2 ** 20


@pytest.mark.parametrize("options,method", [
    ({}, dict(linear_solver="gmres", pc_type="vertex_amg", estimators=True, alg_flux="nu")),
    ({"solver": "direct"}, dict(linear_solver="direct", estimators=True, alg_flux="nu")),
    ({"estimators": False}, dict(linear_solver="gmres", pc_type="vertex_amg",
                                 estimators=False)),
    ({"alg_flux": "multilevel"}, dict(linear_solver="gmres", pc_type="vertex_amg",
                                      estimators=True, alg_flux="multilevel")),
])
def test_solve_checks_the_memory_of_its_own_method(options, method, monkeypatch):
    """solve() checks the computational mesh against the memory its method needs
    (checks.estimate_memory of its solver, estimators and algebraic flux): refused with a
    byte less than that, let through (to the assembly, stopped here) with exactly that. The
    four methods' figures differ on this mesh, so a check of another method's figure fails
    one side."""
    from membranes.app import driver
    problem = scenes.disk(h=0.5, levels=1)
    n = problem.mesh.topology.index_map(0).size_global
    figures = {checks.estimate_memory(n, **m) for m in (
        dict(linear_solver="gmres", pc_type="vertex_amg", estimators=True, alg_flux="nu"),
        dict(linear_solver="direct", estimators=True, alg_flux="nu"),
        dict(linear_solver="gmres", pc_type="vertex_amg", estimators=False),
        dict(linear_solver="gmres", pc_type="vertex_amg", estimators=True,
             alg_flux="multilevel"))}
    assert len(figures) == 4
    need = checks.estimate_memory(n, **method)

    class Assembled(Exception):
        pass

    def stop(*args, **kwargs):
        raise Assembled
    monkeypatch.setattr(driver, "discretise", stop)
    monkeypatch.setattr(checks, "resident_memory", lambda: 0.0)
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: need - 1.0)
    with pytest.raises(ValueError, match="needs .* of memory"):
        solve(problem, **options)
    monkeypatch.setattr(checks, "available_memory", lambda comm=None: need)
    with pytest.raises(Assembled):
        solve(problem, **options)


def test_scenes_refuse_before_gmsh(monkeypatch):
    """The size check runs before any meshing: with gmsh made to fail, an oversized scene is
    refused by the check (ValueError naming the size), a small one reaches gmsh."""
    from membranes.fem import meshes

    def no_gmsh(*args, **kwargs):
        raise AssertionError("gmsh was called")
    monkeypatch.setattr(meshes, "on_rank0", no_gmsh)
    for make in (lambda: scenes.disk(h=0.05, levels=12), lambda: scenes.disk(h=1e-5),
                 lambda: scenes.square(h=1e-5),
                 lambda: scenes.radial(h=0.05, levels=12),
                 lambda: scenes.user(domain="square", levels=13),
                 lambda: scenes.make("disk", h=0.1, levels=2, max_vertices=100)):
        with pytest.raises(ValueError, match="vertices"):
            make()
    with pytest.raises(AssertionError, match="gmsh was called"):
        scenes.disk(h=0.1)


def test_solve_checks_the_mesh_before_assembly(monkeypatch):
    """solve() refuses a mesh above max_vertices (the method's own check on the mesh built)
    before the discretisation is assembled."""
    from membranes.app import driver
    problem = scene("disk", 0.3)

    def no_assembly(*args, **kwargs):
        raise AssertionError("assembled")
    monkeypatch.setattr(driver, "discretise", no_assembly)
    with pytest.raises(ValueError, match="the computational mesh of 'disk' has about 71 "
                                         "vertices, more than the limit"):
        solve(problem, max_vertices=50)


# ## The output folder

def test_output_folder_probe_leaves_nothing(tmp_path):
    deep = tmp_path / "a" / "b" / "out"
    folders.check_output_folder(str(deep))
    assert not (tmp_path / "a").exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "old.txt").write_text("x")
    folders.check_output_folder(str(kept))
    assert sorted(os.listdir(kept)) == ["old.txt"]
    assert sorted(os.listdir(tmp_path)) == ["kept"]


def test_output_folder_with_a_folder_named_as_an_output(tmp_path):
    """A folder of an output's name in the target: refused before the run, with its name
    (the outputs could not move in at the end); a file of that name is an older output."""
    out = tmp_path / "out"
    (out / "summary.json").mkdir(parents=True)
    (out / "history.csv").write_text("old\n")
    folders.check_output_folder(str(out), names=("history.csv",))
    with pytest.raises(ValueError, match="out holds a folder named summary.json, the name of "
                                         "an output file"):
        folders.check_output_folder(str(out), names=("history.csv", "summary.json"))
    assert sorted(os.listdir(out)) == ["history.csv", "summary.json"]


def test_output_folder_accepts_a_link_named_as_an_output(tmp_path):
    """A symbolic link of an output's name, even one to a folder, is no obstacle: the outputs
    are moved in by renaming, which replaces the link itself (not the folder it points to).
    Only a real folder of that name is refused (test above); refusing the link refused a
    folder the run can write."""
    out = tmp_path / "out"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir()
    (out / "summary.json").symlink_to(elsewhere, target_is_directory=True)
    assert folders.folder_named_as_output(str(out), ("history.csv", "summary.json")) is None
    folders.check_output_folder(str(out), names=("history.csv", "summary.json"))
    assert sorted(os.listdir(out)) == ["summary.json"] and os.listdir(elsewhere) == []
    os.replace(tmp_path / "elsewhere", tmp_path / "kept")         # (the link now dangles)
    (tmp_path / "new.json").write_text("{}")
    os.replace(tmp_path / "new.json", out / "summary.json")         # as the writers move in
    assert (out / "summary.json").read_text() == "{}" and (tmp_path / "kept").is_dir()


FOLDER_ON_EVERY_PROCESS = """
import sys
from mpi4py import MPI
from membranes.model import folders
w = MPI.COMM_WORLD
touched = []
if w.rank != 0:          # only process 0 may touch the filesystem (the others would race it)
    import os, tempfile
    def refused(*args, **kwargs):
        touched.append(args)
        raise PermissionError(13, "Permission denied")
    os.mkdir = tempfile.mkdtemp = os.statvfs = refused
said = []
for check in (lambda: folders.check_output_folder("/proc/membranes-x", w),
              lambda: folders.check_output_room(sys.argv[1], 2 ** 62, w),
              lambda: folders.check_output_folder(sys.argv[1], w)):
    try:
        check()
        said.append(None)
    except ValueError as e:
        said.append(str(e))
said = w.gather(said + [len(touched)], root=0)
if w.rank == 0:
    print(repr(said), flush=True)
"""


def test_output_folder_answer_reaches_every_process(tmp_path):
    """On 2 processes process 0 looks at the output folder and both get its answer, the
    same message (a process left without it went on into the run while the other stopped,
    and waited for it in a collective): a folder that cannot be written, a filesystem
    without room (2^62 bytes asked for), and a folder that can be written (no error). Only
    process 0 looks: on the others the script makes mkdir, mkdtemp and statvfs fail and counts
    their calls, none (every process probing one folder would race to create and remove
    it)."""
    import ast
    proc = mpirun(["-c", FOLDER_ON_EVERY_PROCESS, str(tmp_path / "out")])
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert said[0] == said[1] and said[0][2] is None and said[1][3] == 0
    assert "cannot be written" in said[0][0] and "MiB free" in said[0][1]
    assert os.listdir(tmp_path) == []


def test_output_room_without_statvfs_is_left_to_the_writers(tmp_path, monkeypatch):
    """Where the filesystem's free space cannot be read (os.statvfs fails), the room check
    says nothing: the writers report a failed write in their own line (folders: 'no
    statvfs here: the writers report a failure'); it is no reason to refuse the run."""
    def no_statvfs(path):
        raise OSError(38, "Function not implemented")
    monkeypatch.setattr(os, "statvfs", no_statvfs)
    folders.check_output_room(tmp_path / "out", 2 ** 62)


@pytest.mark.parametrize("where", ["proc", "under a file", "a file", "a dangling link"])
def test_output_folder_that_cannot_be_written(where, tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    if where == "a dangling link":
        (tmp_path / "link").symlink_to(tmp_path / "nothing")
    path = {"proc": "/proc/membranes-x", "under a file": str(a_file / "out"),
            "a file": str(a_file), "a dangling link": str(tmp_path / "link")}[where]
    with pytest.raises(ValueError, match="output folder") as e:
        folders.check_output_folder(path)
    assert "\n" not in str(e.value)
    if where == "a dangling link":
        assert "is a link to nothing" in str(e.value)
    assert sorted(os.listdir(tmp_path)) == ["file"] + (["link"] if "link" in where else []) \
        and not os.path.exists("/proc/membranes-x")


def test_write_outputs_refuses_an_unwritable_folder():
    from membranes.app.outputs import write_outputs

    from .conftest import solved
    with pytest.raises(ValueError, match="output folder /proc/x cannot be written"):
        write_outputs(solved("disk", 0.3), "/proc/x")


# ## PETSc options

def test_parse_petsc_options():
    assert petsc_options.parse_petsc_options(
        "-ksp_type gmres -ksp_monitor -pc_factor_shift_amount -1e-3 -pc_type ilu") == \
        {"ksp_type": "gmres", "ksp_monitor": None, "pc_factor_shift_amount": "-1e-3",
         "pc_type": "ilu"}
    assert petsc_options.parse_petsc_options({"-ksp_gmres_restart": 50, "pc_type": "jacobi"}) == \
        {"ksp_gmres_restart": 50, "pc_type": "jacobi"}
    assert petsc_options.parse_petsc_options(None) == {}
    assert petsc_options.parse_petsc_options("") == {}


@pytest.mark.parametrize("bad,message", [
    ("-pc_type=vertex_amg", "write '-pc_type vertex_amg'"),
    ("pc_type", "follows no option"),
    ("-ksp_type gmres ilu", "follows no option"),
    ("-ksp_monitor pc_type=ilu", "write '-pc_type ilu'"),
    ("-pc_type 'ilu", "quotation"),
    ("-pc.type ilu", "is not -name"),
    ({"pc type": "ilu"}, "not a valid option name"),
    ({"pc_type=ilu": None}, "not a valid option name"),
    ({"ksp_gmres_restart": [30]}, "not a string or number"),
    ("-ksp_gmres_restart 50 -KSP_GMRES_RESTART 40", "-ksp_gmres_restart is given more than "
                                                    "once"),
    ({"-pc_type": "ilu", "PC_TYPE": "lu"}, "-pc_type is given more than once"),
])
def test_malformed_petsc_options(bad, message):
    with pytest.raises(ValueError, match=message) as e:
        petsc_options.parse_petsc_options(bad)
    assert "\n" not in str(e.value)


def test_petsc_record_of_used_options_until_the_end_of_a_solve():
    """PETSc marks an option used when an object reads it; -ksp_converged_reason is read by
    KSPSolve itself, so it is unused after setFromOptions and used at the end of the run; a
    misspelt name stays unused."""
    from petsc4py import PETSc
    options = {"ksp_type": "gmres", "ksp_gmres_restart": "40", "ksp_gmres_restartt": "50",
               "ksp_converged_reason": "ascii:/dev/null"}
    prefix = "membranes_test_used_"
    database = PETSc.Options()
    for name, value in options.items():
        database[prefix + name] = value
    A = PETSc.Mat().createAIJ((2, 2), nnz=1, comm=PETSc.COMM_SELF)
    A.setValue(0, 0, 1.0)
    A.setValue(1, 1, 2.0)
    A.assemble()
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    try:
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(A)
        ksp.setFromOptions()
        assert petsc_options.unused_petsc_options(options, prefix) == ["ksp_gmres_restartt",
                                                               "ksp_converged_reason"]
        # a name the database does not hold under the prefix is no unused option of it
        assert petsc_options.unused_petsc_options({"ksp_rtol": "1e-3", "pc_type": None},
                                                  prefix) == []
        b, x = A.createVecs()
        b.set(1.0)
        ksp.solve(b, x)
        assert petsc_options.unused_petsc_options(options, prefix) == ["ksp_gmres_restartt"]
    finally:
        ksp.destroy()
        A.destroy()
        for name in options:
            database.delValue(prefix + name)


def test_unused_options_refused_up_front():
    ilu = {"ksp_type": "gmres", "pc_type": "ilu"}
    petsc_options.check_petsc_options_used({"ksp_gmres_restart": "50"},
                                    {**ilu, "ksp_gmres_restart": "50"})
    with pytest.raises(ValueError, match="-ksp_gmres_restartt is not used"):
        petsc_options.check_petsc_options_used({"ksp_gmres_restartt": "50"},
                                        {**ilu, "ksp_gmres_restartt": "50"})
    with pytest.raises(ValueError, match=r"-ksp_gmres_restart is not used .*-ksp_type cg"):
        petsc_options.check_petsc_options_used({"ksp_gmres_restart": "50", "ksp_type": "cg"},
                                        {**ilu, "ksp_type": "cg", "ksp_gmres_restart": "50"})
    amg = {"pc_type": "hypre", "pc_hypre_type": "boomeramg"}
    petsc_options.check_petsc_options_used(
        {"inner_pc_hypre_boomeramg_strong_threshold": "0.5"}, {**ilu, "pc_type": "none"},
        {"inner_": {**amg, "pc_hypre_boomeramg_strong_threshold": "0.5"}})
    with pytest.raises(ValueError, match="-inner_pc_hypre_boomeramg_strong_treshold"):
        petsc_options.check_petsc_options_used(
            {"inner_pc_hypre_boomeramg_strong_treshold": "0.5"}, {**ilu, "pc_type": "none"},
            {"inner_": {**amg, "pc_hypre_boomeramg_strong_treshold": "0.5"}})
    from petsc4py import PETSc
    assert not [k for k in PETSc.Options().getAll() if k.startswith("membranes_check_")]


@pytest.mark.parametrize("options,message", [
    ({"ksp_gmres_restartt": 50}, "-ksp_gmres_restartt is not used"),
    ("-ksp_gmres_restartt 50", "-ksp_gmres_restartt is not used"),
    ("-pc_type=vertex_amg", "is not -name"),
    ({"pc_type": "vertex_amg"}, "Unable to find requested PC type vertex_amg"),
    ({"pc_type": "hypre", "pc_hypre_boomeramg_strong_treshold": 0.5},
     "-pc_hypre_boomeramg_strong_treshold is not used"),
    ({"gap_pc_hypre_boomeramg_strong_treshold": 0.5},
     r"-gap_pc_hypre_boomeramg_strong_treshold is not used by the inner preconditioner "
     r"'gap_' of this run \(-gap_pc_type hypre\)"),
    ({"mean_pc_type": "lu", "mean_pc_factor_mat_solver_typ": "mumps"},
     r"-mean_pc_factor_mat_solver_typ is not used by the inner preconditioner 'mean_' of this "
     r"run \(-mean_pc_type lu\)"),
])
def test_api_refuses_options_petsc_would_not_use(options, message):
    with pytest.raises(ValueError, match=message):
        solve(scene("disk", 0.3), petsc_options=options, system="eliminated")


def test_api_accepts_options_petsc_uses():
    run = solve(scene("disk", 0.3), newton="exact", solver="paper",
                petsc_options="-ksp_gmres_restart 50 -pc_type jacobi", estimators=False)
    assert run.converged
    assert run.summary()["petsc_options"]["ksp_gmres_restart"] == "50"
    assert math.isfinite(run.energy_error)


def test_an_inner_preconditioner_is_checked_for_the_users_options_only():
    """check_petsc_options_used refuses the user's options that PETSc would not read: of an
    inner PC's complete options (`inner`, defaults included) only those the user gave count.
    Here the inner PC's own default -pc_factor_levels, which Jacobi does not read, is not
    the user's doing and passes; the user's -mean_pc_factor_levels is refused, naming the
    inner PC."""
    inner = {"mean_": {"pc_type": "jacobi", "pc_factor_levels": "2"}}
    outer = {"ksp_type": "fgmres", "pc_type": "none"}
    petsc_options.check_petsc_options_used(["mean_pc_type"], outer, inner)
    with pytest.raises(ValueError, match="-mean_pc_factor_levels is not used by the inner "
                                         "preconditioner 'mean_'"):
        petsc_options.check_petsc_options_used(["mean_pc_factor_levels"], outer, inner)


def test_api_accepts_options_of_the_mean_and_gap_preconditioners():
    """The amg preset's inner PCs read the options under 'mean_' and 'gap_' (documented in
    membranes.linalg.preconditioners); the check up front sends them to those PCs, not to the
    outer KSP, which would refuse them. With LU on both the split is the exact inverse: one
    FGMRES iteration per Newton step."""
    run = solve(scene("disk", 0.3), newton="exact", estimators=False,
                petsc_options={"gap_pc_hypre_boomeramg_strong_threshold": 0.5,
                               "mean_pc_hypre_boomeramg_strong_threshold": 0.5})
    assert run.converged
    exact = solve(scene("disk", 0.3), newton="exact", estimators=False,
                  petsc_options={"mean_pc_type": "lu", "gap_pc_type": "lu"})
    assert exact.converged
    steps = [h for h in exact.history if h["kind"] == "newton"]
    assert steps and all(h["linear_it"] == 1 for h in steps), steps
    assert abs(run.energy_error - exact.energy_error) <= 1e-8 * exact.energy_error


def test_option_names_ignore_case():
    """PETSc reads -KSP_RTOL as -ksp_rtol: the refusals and the inner prefixes must too."""
    from membranes.linalg.krylov import Krylov
    assert petsc_options.parse_petsc_options("-KSP_Type gmres -Mean_PC_Type lu") == \
        {"ksp_type": "gmres", "mean_pc_type": "lu"}
    assert petsc_options.parse_petsc_options({"-KSP_MAX_IT": 1}) == {"ksp_max_it": 1}
    for options in ("-KSP_RTOL 0.5", "-Ksp_Max_It 1"):
        with pytest.raises(ValueError, match="is not accepted"):
            solve(scene("disk", 0.3), petsc_options=options)
    with pytest.raises(ValueError, match="-ksp_atol is not accepted"):
        Krylov("paper", {"KSP_ATOL": 1.0})
    assert Krylov("amg", {"MEAN_PC_TYPE": "lu"}).inner()["mean_"]["pc_type"] == "lu"


@pytest.mark.parametrize("options", [{"_ksp_type": "gmres"}, {"-1ksp_rtol": "1e-3"},
                                     {"pc_typé": "ilu"}, "-pc_typé ilu",
                                     "-ksp_rtol 1e-3 -ksp_ŧype cg"])
def test_option_names_are_a_letter_then_ascii_letters_digits_and_underscores(options):
    """An option name starts with a letter and has only ASCII letters, digits and '_' (PETSc's
    names): a leading '_' or digit, or a non-ASCII letter (which str.isalnum accepts), is
    refused when the options are parsed, naming the option, and not passed on to PETSc."""
    with pytest.raises(ValueError, match="not a valid option name|is not -name") as e:
        petsc_options.parse_petsc_options(options)
    assert "\n" not in str(e.value)


def test_trial_set_up_refuses_a_norm_type_the_krylov_solver_lacks():
    """The up-front check (`unused_by_trial`, before any mesh or solve) asks PETSc for the
    KSP's norm type, where PETSc compares it with the KSP type and the PC side: CG
    preconditioned on the right, or with a norm type CG lacks, is refused there in one line
    as ValueError, not left to the configuration of the run's solver."""
    for options in ({"ksp_type": "cg", "ksp_pc_side": "right", "pc_type": "jacobi"},
                    {"ksp_type": "gmres", "ksp_norm_type": "natural", "pc_type": "jacobi"}):
        with pytest.raises(ValueError, match="PETSc options: .*does not support") as e:
            petsc_options.unused_by_trial(options)
        assert "\n" not in str(e.value)
    assert petsc_options.unused_by_trial({"ksp_type": "cg", "ksp_pc_side": "left",
                                          "pc_type": "jacobi"}) == []


@pytest.mark.parametrize("solver,options", [("paper", "-ksp_type cg"),
                                            ("paper", "-ksp_pc_side left"),
                                            ("paper", "-ksp_norm_type preconditioned"),
                                            ("amg", "-ksp_norm_type preconditioned")])
def test_norm_type_the_krylov_solver_lacks_is_bad_input(solver, options):
    """PETSc checks the KSP's norm type against its type and PC side only when asked for it:
    the solve used to stop in a traceback (PETSc error 56 from KSPGetNormType in the
    clean-up of the first linear solve); now the check up front and the configuration of the
    solver refuse it in one line."""
    from mpi4py import MPI

    from membranes.linalg.krylov import Krylov, LinearSolver
    with pytest.raises(ValueError, match="does not support norm type") as e:
        solve(scene("disk", 0.3), solver=solver, petsc_options=options)
    assert "\n" not in str(e.value)
    krylov = Krylov(solver, petsc_options.parse_petsc_options(options))
    with pytest.raises(ValueError, match="does not support norm type"):
        LinearSolver(krylov, MPI.COMM_SELF)


@pytest.mark.parametrize("solver,options", [("amg", {"ksp_type": "preonly"}),
                                            ("paper", {"ksp_type": "preonly"}),
                                            ("direct", {"pc_type": "none"}),
                                            ("direct", {"pc_type": "jacobi"})])
def test_preonly_without_a_factorisation_is_bad_input(solver, options):
    """-ksp_type preonly applies the PC once: with the mean/gap split, ILU or no PC the
    'exact' solves were taken as exact and Newton ran its 100 steps to exit 3."""
    with pytest.raises(ValueError, match="only as a factorisation"):
        solve(scene("disk", 0.3), solver=solver, petsc_options=options)


def test_preonly_preset_is_named_in_the_variant_refusal():
    """A preset made direct by -ksp_type preonly -pc_type lu is not called 'paper' when the
    inexact or adaptive variant is refused for it (it was: "..., not 'paper'")."""
    for newton in ("inexact", "adaptive"):
        with pytest.raises(ValueError, match="not 'paper' with -ksp_type preonly"):
            solve(scene("disk", 0.3), solver="paper", newton=newton,
                  petsc_options="-ksp_type preonly -pc_type lu")


@pytest.mark.parametrize("solver,options", [("paper", "-sub_pc_factor_levels 1"),
                                            ("direct", "-mat_mumps_icntl_14 200"),
                                            ("direct", "-mat_mumps_icntl_24 1")])
def test_options_read_at_set_up_are_accepted(solver, options):
    """The options of the block Jacobi sub-solvers and of MUMPS are read when the PC is set
    up, not when the KSP is configured: they were refused as 'not used', even
    -mat_mumps_icntl_14, which the direct preset sets itself."""
    run = solve(scene("disk", 0.3), solver=solver, newton="exact", estimators=False,
                petsc_options=options)
    assert run.converged


@pytest.mark.parametrize("solver,options,name", [
    ("paper", "-sub_pc_factor_levelz 1", "-sub_pc_factor_levelz"),
    ("direct", "-mat_mumps_icntl_244 1", "-mat_mumps_icntl_244"),
    ("amg", "-pc_factor_levels 1", "-pc_factor_levels")])
def test_options_nothing_reads_are_still_refused(solver, options, name):
    """A misspelt set-up option is still refused; so is an option of PETSc's default PC that
    the mean/gap split (a Python PC) does not read."""
    with pytest.raises(ValueError, match=f"{name} is not used"):
        solve(scene("disk", 0.3), solver=solver, petsc_options=options)


def test_two_processes_share_the_node_and_refuse_together(tmp_path):
    """`mpirun -n 2 membranes solve --levels 12`: both processes refuse (exit 2), process 0
    says it once, with the memory of the node shared between the two."""
    import re

    out = tmp_path / "out"
    proc = mpirun(["-m", "membranes.app.cli", "solve", "--quiet", "--levels", "12", "--out",
                   str(out)])
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.startswith("membranes:")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    shared = float(re.search(r"but ([0-9.]+) GiB is available per process", lines[0])[1])
    total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    assert 0 < shared * GiB <= total / 2 * 1.001       # (the message's 3 digits)
    assert not out.exists()


SHARED_MESH_MEMORY = """
from mpi4py import MPI
from membranes import scenes, solve
from membranes.app import driver
from membranes.model import checks
comm = MPI.COMM_WORLD
problem = scenes.disk(h=0.5)
n = problem.mesh.topology.index_map(0).size_global
need = checks.estimate_memory(n, linear_solver="gmres", pc_type="vertex_amg",
                              estimators=True, alg_flux="nu", processes=comm.size,
                              replicated=False)


class Assembled(Exception):
    pass


def stop(*args, **kwargs):
    raise Assembled


driver.discretise = stop
checks.resident_memory = lambda: 0.0
said = []
for room in (need - 1.0, need):
    checks.available_memory = lambda comm=None, room=room: room
    try:
        solve(problem)
        said.append("ran")
    except ValueError as e:
        said.append("refused" if "of memory" in str(e) else str(e))
    except Assembled:
        said.append("assembled")
said = comm.gather(said, root=0)
print(repr(said) if comm.rank == 0 else "", flush=True)
"""


def test_solve_checks_each_process_for_its_share_of_the_mesh():
    """Under mpirun -n 2 the computational mesh is distributed: each process needs its
    share of the part of the run that grows with the mesh (estimate_memory with processes=2,
    not replicated), the figure `solve` checks against: refused with a byte less on every
    process, let through (to the assembly, stopped here) with exactly that."""
    import ast

    proc = mpirun(["-c", SHARED_MESH_MEMORY])
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert said == [["refused", "assembled"]] * 2, said


LOCAL_ERROR = """
import sys
from mpi4py import MPI
from membranes.model import scenes
make = scenes.make
def failing(*args, **kwargs):
    if MPI.COMM_WORLD.rank == 1:
        raise ValueError("only process 1 meets this")
    return make(*args, **kwargs)
scenes.make = failing
from membranes.app.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_an_error_of_one_process_ends_the_run(tmp_path):
    """An error met by one process only (simulated: process 1 refuses its data while process
    0 goes on meshing, a collective) used to leave the run waiting for ever: the process
    that failed waited in MPI_Finalize, the other in the collective. The processes that met
    an error now wait cli.AGREE_SECONDS for the others to meet it too, then the one that
    failed says why and ends itself; mpirun ends the rest. Exit 2, one error line."""
    import time

    from membranes.app.cli import AGREE_SECONDS

    out = tmp_path / "out"
    t = time.monotonic()
    proc = mpirun(["-c", LOCAL_ERROR, "solve", "--quiet", "--h", "0.3", "--out", str(out)])
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("membranes:")]
    assert lines == ["membranes: error: only process 1 meets this"], proc.stderr
    assert AGREE_SECONDS <= time.monotonic() - t < AGREE_SECONDS + 60
    assert not out.exists()


PART_OF_THE_MESH = """
import numpy as np
from mpi4py import MPI
from membranes import scenes
comm = MPI.COMM_WORLD
problem = scenes.square(h=0.3)          # the same mesh as the user scene's below
x = problem.mesh.geometry.x
near = bool(np.any(x[:, 0] == 0.0))     # this process holds vertices on the line x = 0
try:
    scenes.user(domain="square", h=0.3, f1="1/x")
    said = None
except ValueError as e:
    said = str(e)
ranks = comm.gather((near, said), root=0)
print(repr(ranks) if comm.rank == 0 else "", flush=True)
"""


def test_data_not_finite_on_part_of_the_mesh_are_refused_by_every_process(tmp_path):
    """f1 = 1/x on the unit square on 3 processes: only the processes that hold vertices on
    x = 0 found the formula not finite; the others went on alone (the API returned them a
    problem, their solve would wait for ever; the command line printed the error once per
    process that met it, after AGREE_SECONDS). The check is collective: every process raises
    the same ValueError at once, and the command line says it once, without the wait."""
    import ast
    import time

    from membranes.app.cli import AGREE_SECONDS

    proc = mpirun(["-c", PART_OF_THE_MESH], processes=3)
    assert proc.returncode == 0, proc.stderr
    ranks = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert not all(near for near, _ in ranks)          # the case this test is about
    said = {message for _, message in ranks}
    assert len(said) == 1 and None not in said, ranks
    assert said.pop().startswith("f1 = '1/x' is not finite on the mesh (e.g. at x = 0, ")
    out = tmp_path / "out"
    t = time.monotonic()
    proc = mpirun(["-m", "membranes.app.cli", "solve", "--quiet", "--domain", "square", "--h",
                   "0.3", "--f1", "1/x", "--out", str(out)], processes=3)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("membranes:")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("membranes: error: f1 = '1/x' is not finite on the mesh")
    assert time.monotonic() - t < AGREE_SECONDS
    assert not out.exists()


@pytest.mark.parametrize("options,name", [("-ksp_divtol 10", "-ksp_divtol"),
                                          ("-ksp_initial_guess_nonzero 0",
                                           "-ksp_initial_guess_nonzero"),
                                          ("-pc_type mg -pc_mg_levels 2", "-pc_type mg"),
                                          ("-gap_pc_type MG", "-gap_pc_type mg"),
                                          ("-ksp_knoll", "-ksp_knoll"),
                                          ("-ksp_guess_type fischer", "-ksp_guess_type"),
                                          ("-ksp_converged_maxits", "-ksp_converged_maxits"),
                                          ("-ksp_converged_use_initial_residual_norm",
                                           "-ksp_converged_use_initial_residual_norm"),
                                          ("-ksp_reuse_preconditioner",
                                           "-ksp_reuse_preconditioner"),
                                          ("-ksp_type chebyshev", "-ksp_type chebyshev")])
def test_options_the_method_overrides_or_that_crash_are_refused(options, name):
    """-ksp_divtol and -ksp_initial_guess_nonzero were accepted and did nothing (the method's
    tests and Newton's guess override them); -pc_type mg with 2 levels made PETSc crash with a
    segmentation fault in its set-up (no interpolations are supplied). -ksp_knoll and
    -ksp_guess_type replaced Newton's guess (inexact Newton on the disk at h = 0.3, J = 2 ran
    its 100 steps without converging); the default test's options and
    -ksp_reuse_preconditioner did nothing; -ksp_type chebyshev, which diverges on the Newton
    systems (paper preset, -pc_type jacobi), crashed PETSc in the KSP's reset."""
    from membranes.linalg.krylov import Krylov
    with pytest.raises(ValueError, match=name):
        Krylov("paper" if "gap" not in options else "amg",
               petsc_options.parse_petsc_options(options))


@pytest.mark.parametrize("preset, options", [("direct", "-pc_type cholesky"),
                                             ("paper", "-sub_pc_type ICC"),
                                             ("amg", "-mean_pc_type cholesky"),
                                             ("amg", "-pc_type icc")])
def test_symmetric_factorisations_are_refused(preset, options):
    """Cholesky and ICC factorise a symmetric matrix's upper triangle, and no matrix solved
    here is symmetric (S_D keeps its boundary columns): `--solver direct --petsc-options
    "-pc_type cholesky"` on the disk at h = 0.2, J = 1 ran 100 Newton steps on T_0 without
    converging, with an energy error of 7.99 (0.034 with LU). Refused, naming the option and
    the cure."""
    from membranes.linalg.krylov import Krylov
    name = options.split()[0].lower()
    with pytest.raises(ValueError, match=f"PETSc option {name} .* not symmetric: use i?lu"):
        Krylov(preset, petsc_options.parse_petsc_options(options))
    Krylov(preset, petsc_options.parse_petsc_options(
        options.replace("cholesky", "lu").replace("ICC", "ilu").replace("icc", "ilu")))


def test_converged_reason_is_read_in_the_solve(capfd):
    """-ksp_converged_reason is read by KSPSolve only (no trial set-up reads it): it was refused
    as unused, although the run's solvers keep their options while they live. Now accepted, and
    PETSc prints its line for every Krylov solve."""
    run = solve(scenes.disk(h=0.3), newton="exact", petsc_options="-ksp_converged_reason",
                nested=False, progress=False)
    assert run.converged, run.reason
    printed = capfd.readouterr().out
    assert printed.count("solve converged due to") == run.summary()["newton_iterations"]


PARALLEL_ILU = """
from mpi4py import MPI
from membranes.app.driver import check_method
said = None
try:
    check_method(1, solver="amg", petsc_options="-pc_type ilu", comm=MPI.COMM_WORLD)
except ValueError as e:
    said = str(e)
said = MPI.COMM_WORLD.gather(said, root=0)
print(repr(said) if MPI.COMM_WORLD.rank == 0 else "", flush=True)
"""


def test_a_factorisation_petsc_cannot_distribute_is_refused_up_front():
    """-pc_type ilu (PETSc's own, sequential only) on 2 processes: the trial set-up ran on one
    process and let it through; the run failed after meshing (exit 3, outputs written). The
    trial now runs on the run's communicator: every process refuses it, naming the way out.
    On one process it is a valid option."""
    import ast

    from membranes.app.driver import check_method

    check_method(1, solver="amg", petsc_options="-pc_type ilu")
    proc = mpirun(["-c", PARALLEL_ILU])
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    assert len(said) == 2 and all(m is not None and "matrix type mpiaij" in m
                                  and "-sub_pc_type ilu" in m for m in said), said


def test_data_scales_against_their_formula():
    """(u_data, λ_data) of §11 recomputed from the assembled vectors: λ_data = max over the
    interior vertices and α of |F_α,a| / D_a, u_data = max(g, (C_PF h_Ω)² max_α λ_α / μ_α),
    on the square (μ1 = 1, μ2 = 2, so a swap of the moduli shows). The same arithmetic on
    the same arrays: equal to round-off (1e-14)."""
    from membranes.fem.discretisation import discretise
    problem = scenes.square(h=0.2)
    assert problem.mu1 != problem.mu2
    disc = discretise(problem)
    inner = disc.interior
    lam = [np.abs(F.array[inner] / disc.D.array[inner]).max() for F in (disc.F1, disc.F2)]
    c = problem.poincare_constant()
    u = max(problem.g, c * c * max(lam[0] / problem.mu1, lam[1] / problem.mu2))
    assert disc.data_scales() == pytest.approx((u, max(lam)), rel=1e-14)
    assert u > problem.g                   # (the loads' term is the one compared)


# ## From a mutation round of the checks (BENCHMARKS.md, "Robustness"): what no test pinned

def test_cgroup_v1_without_a_limit_is_no_limit(monkeypatch):
    """cgroup v1 writes "no limit" as 2^63 rounded down to a page (9223372036854771712): no
    room figure then, as on v2's "max"; a real limit gives limit − usage."""
    import io
    files = {"/sys/fs/cgroup/memory/memory.limit_in_bytes": "9223372036854771712\n",
             "/sys/fs/cgroup/memory/memory.usage_in_bytes": "1000000\n"}

    def fake_open(path, *args, **kwargs):
        if path in files:
            return io.StringIO(files[path])
        raise FileNotFoundError(path)

    monkeypatch.setattr(checks, "open", fake_open, raising=False)
    assert checks._cgroup_room() is None
    files["/sys/fs/cgroup/memory/memory.limit_in_bytes"] = str(2 ** 30)
    assert checks._cgroup_room() == 2 ** 30 - 1e6


def test_sizes_of_exactly_one_unit_are_said_in_that_unit():
    assert checks._bytes(2 ** 30) == "1 GiB" and checks._bytes(2 ** 40) == "1 TiB"


def test_the_level_hint_counts_beyond_twenty_levels():
    """The hint's largest level count is searched up to 64 levels, not cut lower."""
    vertices = checks.estimate_vertices(1.0, 25)[0]
    assert checks.largest_levels(vertices, h=1.0) == 25


@pytest.mark.parametrize("text", ["z + 1", "x + e", "min(x, nan)"])
def test_an_unknown_name_in_a_formula_is_named_as_such(text):
    """Not "'z' is not finite" (an unknown name evaluated to NaN): the message lists the
    names allowed."""
    from membranes.model.expressions import Formula
    with pytest.raises(ValueError, match="unknown name"):
        Formula(text, "f1")


def test_a_formula_of_80_characters_is_shown_whole():
    from membranes.model.expressions import Formula
    text = "x + " + "1" * 76
    assert len(text) == 80 and Formula(text).shown == text
    assert Formula(text + "1").shown.endswith("...")


def test_numpy_option_values_become_python_values():
    """The API's options may come from numpy arrays; the parsed options are Python values,
    which json.dumps writes."""
    import json
    out = petsc_options.parse_petsc_options({"ksp_gmres_restart": np.int64(50),
                                             "ksp_rtol": np.float64(1e-8)})
    assert type(out["ksp_gmres_restart"]) is int and type(out["ksp_rtol"]) is float
    json.dumps(out)
