"""Several MPI processes: a replicated mesh, and the vertex patches shared out (issue 6).

Under ``mpirun -n P membranes solve ...`` every process builds the whole problem on
``MPI.COMM_SELF``: the mesh and its hierarchy are *replicated*, not distributed
(`check_replicated`). Process 0 runs Newton and GMRES, the others evaluate the estimators
(membranes.pipeline). With P ≥ 3 the estimator processes share the work that dominates an
estimate, the patch problems:

* the flux equilibration (DESIGN §5) solves one mixed problem per vertex patch ω_a, and
  σ_α,disc = Σ_a σ_a;
* the multilevel algebraic flux (DESIGN §6) solves one per vertex patch of every level, and
  σ_alg is again a sum over them (and the coarse solve).

Estimator process p sets up and solves the patches of the vertices it owns (`owned_vertices`:
contiguous blocks of the vertex numbering), and the partial sums are added over the estimator
processes (`Summation`). The results agree with a serial run up to the order of summation of
the patch contributions. The price is memory: each process holds the whole discretisation.

To use it from Python, build the problem on ``MPI.COMM_SELF`` on every process and pass
``comm=MPI.COMM_WORLD`` to `membranes.solve`; the meshes must be the same on every process
(`check_replicated`; gmsh with the same options makes the same mesh).
"""

import contextlib
import functools
import hashlib

import numpy as np


@contextlib.contextmanager
def one_blas_thread():
    """BLAS on one thread inside the block. The patch problems are thousands of small dense
    solves and products (tens of unknowns), where BLAS threads cost more than they save, and
    with several processes on the machine they would oversubscribe its cores (measured on the
    disk, h0 = 0.2, J = 2, 2 cores: multilevel flux set-up 4.4 s with two OpenBLAS threads
    against 1.1 s with one, while other processes ran). Every run is inside one
    (discretisation.as_one_run); MultilevelFlux takes one of its own for direct use."""
    with _blas_controller().limit(limits=1, user_api="blas"):
        yield


@functools.lru_cache(maxsize=None)
def _blas_controller():
    """threadpoolctl's view of the loaded BLAS libraries, found once (finding them scans the
    process's libraries: 3.5 ms, against a few ms for the small blocks it wraps)."""
    from threadpoolctl import ThreadpoolController
    return ThreadpoolController()


def owned_vertices(n, comm):
    """Boolean mask over n vertices: those whose patches this process sets up and solves
    (block `comm.rank` of `comm.size` contiguous blocks of nearly equal size). All vertices
    without a communicator or on one process."""
    mask = np.zeros(n, dtype=bool)
    if comm is None or comm.size == 1:
        mask[:] = True
        return mask
    bounds = np.linspace(0, n, comm.size + 1).round().astype(np.int64)
    mask[bounds[comm.rank]:bounds[comm.rank + 1]] = True
    return mask


def in_two(pool, n, work):
    """work(a, b) over the items [0, n) of a pass whose items are independent (each writes
    its own entries): one call without `pool`; with it (an executor whose thread is spare:
    membranes.pipeline lends process 0's core to the estimator process while process 0 waits),
    two, the first half on the pool's thread and the second on this one. The same numbers
    either way."""
    if pool is None or n < 2:
        work(0, n)
        return
    first = pool.submit(work, 0, n // 2)
    try:
        work(n // 2, n)
    finally:
        first.result()


class PartnerFailed(RuntimeError):
    """A process of the communicator failed (`agree`): its error message."""


def agree(comm, error=None):
    """Collective over comm (None or one process: nothing): PartnerFailed for the first
    process (by rank) that brings an `error` (its message), on every process.

    Processes that share work (P ≥ 3 estimator processes) meet in collectives: `Summation`
    calls it first, and membranes.pipeline at the end of every message. A process that fails
    calls it once with its error, in place of the next collective its partners make, so that
    they learn of the failure there instead of waiting for it for ever."""
    if comm is None or comm.size == 1:
        return
    for e in comm.allgather(error):
        if e is not None:
            raise PartnerFailed(e)


class Summation:
    """Adds partial sums over the processes of `comm` (None: nothing to add).

    The sum is formed on process 0 and broadcast, so every process gets the same bits: the
    processes take identical decisions from it (Newton and GMRES stopping tests), which an
    Allreduce whose reduction order differs between processes would not guarantee."""

    def __init__(self, comm):
        self.comm = comm if comm is not None and comm.size > 1 else None

    def __call__(self, parts):
        """The sums of the arrays `parts` (e.g. the pair (σ_1, σ_2)) over the processes, in one
        reduction."""
        if self.comm is None:
            return parts
        from mpi4py import MPI
        agree(self.comm)            # a partner that failed comes here instead (`agree`)
        partial = np.concatenate([np.asarray(a, dtype=np.float64) for a in parts])
        total = np.empty_like(partial)
        self.comm.Reduce(partial, total, op=MPI.SUM, root=0)
        self.comm.Bcast(total, root=0)
        return np.split(total, np.cumsum([len(a) for a in parts])[:-1])


def _mesh_digest(mesh):
    """A digest of the mesh's vertex coordinates and cells, in their local numbering."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.geometry.x).tobytes())
    h.update(np.ascontiguousarray(mesh.geometry.dofmap.array).tobytes())
    return h.hexdigest()


def check_replicated(mesh, comm):
    """ValueError unless `mesh` is a serial mesh (MPI.COMM_SELF) that is the same, bit for bit,
    on every process of `comm`."""
    if mesh.comm.size > 1:
        raise ValueError(f"the mesh is distributed over {mesh.comm.size} processes; membranes "
                         f"replicates it: build the problem with comm=MPI.COMM_SELF on every "
                         f"process and pass comm=MPI.COMM_WORLD to solve")
    if comm is None or comm.size == 1:
        return
    digests = comm.allgather(_mesh_digest(mesh))
    if len(set(digests)) > 1:
        raise ValueError(f"the mesh differs between the {comm.size} processes; every process "
                         f"must build the same mesh")
