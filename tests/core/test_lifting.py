"""The residual lifting of §4: (r_h, ψ_{a_l})_K = R_l / N_l on every cell, hence (r_h, ψ_l)_Ω = R_l.

Checked with dolfinx assemblies that do not use the lifting's algebra: (r_h, v) for P1 test
functions v gives R back; (r_h, w) for DG1 test functions w gives the cell-by-cell moments,
compared with R_l / N_l where N_l (cells at vertex l) is assembled independently as
Σ_K (3/|K|) (1, ψ_l)_K with the vertex quadrature rule ((1, ψ_l)_K = |K|/3 exactly).
"""

import os

import numpy as np
import pytest
import ufl
from mpi4py import MPI

from membranes.estimation.lifting import Lifting
from tests.conftest import mpirun

from .mpi_equilibration import assembled, boundary, disk, square

HERE = os.path.dirname(os.path.abspath(__file__))


@pytest.fixture(scope="module", params=["square", "disk"])
def space(request):
    from dolfinx import fem
    mesh = {"square": square, "disk": disk}[request.param](MPI.COMM_WORLD)
    return fem.FunctionSpace(mesh, ("Lagrange", 1))


def residual(V, seed=0):
    """A random R, zero at the dofs on ∂Ω (owned part)."""
    n = V.dofmap.index_map.size_local
    R = np.random.default_rng(seed + V.mesh.comm.rank).standard_normal(n)
    R[boundary(V)] = 0.0
    return R


def test_moments_against_every_hat_function(space):
    """(r_h, ψ_l)_Ω = R_l for every P1 dof, to round-off."""
    R = residual(space)
    r = Lifting(space)(R)
    back = assembled(r * ufl.TestFunction(space) * ufl.dx)
    comm = space.mesh.comm
    err = comm.allreduce(np.abs(back - R).max(initial=0.0), op=MPI.MAX)
    assert err <= 1e-13 * comm.allreduce(np.abs(R).max(), op=MPI.MAX)


def test_cell_moments(space):
    """(r_h, ψ_{a_l})_K = R_l / N_l on every cell K and vertex a_l of K."""
    from dolfinx import fem
    mesh = space.mesh
    lifting = Lifting(space)
    R = residual(space, seed=1)
    r = lifting(R)
    vertex_rule = ufl.dx(metadata={"quadrature_rule": "vertex", "quadrature_degree": 1})
    v = ufl.TestFunction(space)
    counts = fem.Function(space)
    counts.vector.array[:] = assembled(3.0 / ufl.CellVolume(mesh) * v * vertex_rule)
    counts.x.scatter_forward()
    assert np.allclose(counts.x.array, np.round(counts.x.array), rtol=0, atol=1e-12)
    assert np.array_equal(np.round(counts.x.array), lifting.count)
    Rg = fem.Function(space)
    Rg.vector.array[:] = R
    Rg.x.scatter_forward()
    moments = assembled(r * ufl.TestFunction(lifting.Q) * ufl.dx)
    nc = mesh.topology.index_map(2).size_local
    cells = space.dofmap.list.array.reshape(-1, 3)[:nc]
    dg = lifting.Q.dofmap.list.array.reshape(-1, 3)[:nc]
    expected = Rg.x.array[cells] / counts.x.array[cells]
    assert np.abs(moments[dg] - expected).max(initial=0.0) <= 1e-13 * max(np.abs(R).max(), 1)


def test_linear_and_reused(space):
    """The set-up is reused: lifting a + 2 b equals lift(a) + 2 lift(b); `out` is written."""
    from dolfinx import fem
    lifting = Lifting(space)
    a, b = residual(space, 2), residual(space, 3)
    out = fem.Function(lifting.Q)
    both = lifting(a + 2.0 * b, out=out)
    assert both is out
    expected = lifting(a).x.array + 2.0 * lifting(b).x.array
    assert np.allclose(both.x.array, expected, rtol=1e-14, atol=1e-14 * np.abs(expected).max())


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
@pytest.mark.parametrize("nproc", [2, 3])
def test_lifting_on_processes(nproc):
    """On P processes: (r_h, ψ_l) = R_l to 1e-13 relative and ‖r_h‖² equal to the serial one
    (the counts N_l add cells from several processes at vertices they share)."""
    out = mpirun([os.path.join(HERE, "mpi_equilibration.py"), "lifting"], processes=nproc,
                 timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    lines = [line for line in out.stdout.splitlines() if line.startswith("OK lifting")]
    assert len(lines) == 4 and all(f"P={nproc}" in line for line in lines), lines
