"""Linear solves of the Newton systems through petsc4py: the PETSc matrix, the direct solver.

The direct solver is LU factorisation with MUMPS (DESIGN §8, "exact" Newton solved exactly).
A solve returns the solution and the number of linear iterations it counts as (1 for a direct
solve, so that cumulative counts stay meaningful as "solver applications"). The Krylov solver
is in `krylov`.
"""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc


def petsc_matrix(A, copy=True):
    """A scipy sparse matrix as a serial PETSc AIJ matrix, built on copies of its CSR arrays
    (MatCreateSeqAIJWithArrays: no insertion of values one row at a time, which took 4 times
    as long at 1.6e6 entries; PETSc's AIJ wants the column indices of each row sorted).
    copy=False: on A's own arrays where their types allow (the caller keeps A unchanged while
    the matrix lives; its indices may get sorted in place); saves a copy of the system."""
    A = sp.csr_matrix(A, dtype=PETSc.ScalarType, copy=copy)
    A.sort_indices()
    csr = (A.indptr.astype(PETSc.IntType, copy=False), A.indices.astype(PETSc.IntType, copy=False),
           A.data)
    M = PETSc.Mat().createAIJWithArrays(A.shape, csr, comm=PETSc.COMM_SELF)
    M.assemble()
    return M


def row_buffers(bound):
    """Column indices (int32) and values for at most `bound` entries of a CSR matrix that a
    compiled pass writes row after row, its row pointers with them (one pass, where counting
    the entries first took a second one; `written_csr` then shrinks them to the written
    entries: the pages of the tail are never touched, and so never allocated)."""
    return np.empty(bound, dtype=np.int32), np.empty(bound)


def written_csr(indptr, indices, data, shape):
    """The CSR matrix of rows a compiled pass wrote one after the other into the buffers
    `indices` and `data` (arrays of their own, longer than needed: `indptr[-1]` entries
    written; no other array may view them), its columns sorted. The buffers are shrunk in
    place to the written entries (`ndarray.resize`: a realloc, which gives a large block's
    tail back without moving its head): the matrix holds them, not views of a prefix, which
    scipy copies wherever it makes a matrix of them (its `prune`, when the prefix is shorter
    than half the buffer: at 9.3e5 vertices 0.2 s a step for the eliminated Newton matrix,
    the first touch of the new memory included)."""
    nnz = int(indptr[-1])
    indices.resize(nnz, refcheck=False)
    data.resize(nnz, refcheck=False)
    A = sp.csr_matrix((data, indices, indptr), shape=shape)
    A.has_sorted_indices = True
    return A


def scaled_rows(M, s):
    """diag(s) M for a CSR matrix M, by scaling a copy of its stored entries (no sparse
    product: the same numbers, a fraction of the time)."""
    M = sp.csr_matrix(M, copy=True)
    M.data *= np.repeat(s, np.diff(M.indptr))
    return M


class LinearSolveError(RuntimeError):
    """A linear solve that failed; `its` counts the iterations it performed all the same."""

    def __init__(self, message, its=0):
        super().__init__(message)
        self.its = its


def _mumps_solve(M, rhs, workspace_percent):
    ksp = PETSc.KSP().create(PETSc.COMM_SELF)
    try:
        ksp.setOperators(M)
        ksp.setType("preonly")
        pc = ksp.getPC()
        pc.setType("lu")
        pc.setFactorSolverType("mumps")
        pc.setFactorSetUpSolverType()
        # ICNTL(14): extra workspace in percent. The default (20 %) is too small for the full
        # Newton system, whose zero λ-diagonal forces off-diagonal pivots, and MUMPS then
        # returns a failed factorisation (seen on the disk scene).
        pc.getFactorMatrix().setMumpsIcntl(14, workspace_percent)
        x = rhs.duplicate()
        try:
            ksp.solve(rhs, x)
        except PETSc.Error:
            return None
        if ksp.getConvergedReason() < 0 or not np.all(np.isfinite(x.array)):
            return None
        return x.array.copy()
    finally:
        ksp.destroy()


def solve_direct(A, b):
    """Solve A x = b with MUMPS LU; returns (x, 1). Retries once with more MUMPS workspace."""
    M = petsc_matrix(A)
    rhs = PETSc.Vec().createWithArray(np.ascontiguousarray(b, dtype=float), comm=PETSc.COMM_SELF)
    try:
        for workspace in (100, 400):
            x = _mumps_solve(M, rhs, workspace)
            if x is not None:
                return x, 1
        raise LinearSolveError("MUMPS LU factorisation failed (singular matrix or workspace)")
    finally:
        rhs.destroy()
        M.destroy()
