"""Vertex-block AMG preconditioner for the eliminated 2N Newton system (draft)."""

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from .linear_solve import petsc_matrix


def vertex_blocks(A):
    """The 2×2 blocks [[A[l, l], A[l, n+l]], [A[n+l, l], A[n+l, n+l]]] of the vertices, inverted,
    as a sparse 2N × 2N matrix."""
    n = A.shape[0] // 2
    a, d = A.diagonal()[:n], A.diagonal()[n:]
    b, c = A.diagonal(n), A.diagonal(-n)
    det = a * d - b * c
    return sp.bmat([[sp.diags(d / det), sp.diags(-b / det)],
                    [sp.diags(-c / det), sp.diags(a / det)]], format="csr")


def slave_columns(A):
    """z-unknowns whose column of A has entries only in the rows of their own vertex."""
    n = A.shape[0] // 2
    C = A[:, n:].tocoo()
    own = (C.row == C.col) | (C.row == C.col + n)
    other = np.zeros(n, dtype=bool)
    other[C.col[~own & (C.data != 0)]] = True
    return ~other


def gap_scales(A):
    """d_l with u2_l = u1_l + d_l z_l + const where z_l = λ_l (read off the rows of the second
    block: the u1-column and the z-column of vertex l there are μ2 S e_l and μ2 d_l S e_l);
    1 where u2 does not depend on u1."""
    n = A.shape[0] // 2
    B = A[n:].tocoo()
    off = B.row != (B.col % n)
    u1 = np.bincount(B.col[off & (B.col < n)], B.data[off & (B.col < n)], minlength=n)
    z = np.bincount(B.col[off & (B.col >= n)] - n, B.data[off & (B.col >= n)], minlength=n)
    gap = u1 != 0
    return np.where(gap, z / np.where(gap, u1, 1.0), 1.0)


class VertexAMG:
    """PCShell context: y = M^{-1} x."""

    def __init__(self, A, amg_options=None, drop_slaves=True):
        n2 = A.shape[0]
        n = n2 // 2
        self.Binv = vertex_blocks(A)
        Ah = (self.Binv @ A).tocsr()
        slave = np.zeros(n2, dtype=bool)
        if drop_slaves:
            slave[n:] = slave_columns(A)
        self.keep, self.slave = np.flatnonzero(~slave), np.flatnonzero(slave)
        scale = np.ones(n2)
        if drop_slaves:
            d = gap_scales(A)
            scale[n:] = np.where(slave[n:] | (d == 0), 1.0, d)
        self.scale = scale[self.keep]
        Ds = sp.diags(self.scale)
        K = (Ds @ Ah[self.keep][:, self.keep] @ sp.diags(1 / self.scale)).tocsr()
        self.X = Ah[self.slave][:, self.keep].tocsr()
        self.Kmat = petsc_matrix(K)
        self.pc = PETSc.PC().create(PETSc.COMM_SELF)
        self.pc.setOperators(self.Kmat)
        opts = PETSc.Options()
        prefix = "vamg_"
        for k, v in (amg_options or {"pc_type": "hypre"}).items():
            opts[prefix + k] = v
        self.pc.setOptionsPrefix(prefix)
        self.pc.setFromOptions()
        for k in (amg_options or {"pc_type": "hypre"}):
            opts.delValue(prefix + k)
        self.pc.setUp()
        self.xk = self.Kmat.createVecRight()
        self.yk = self.Kmat.createVecLeft()
        self.n_keep = len(self.keep)

    def apply(self, pc, x, y):
        s = self.Binv @ x.array_r
        self.xk.array[:] = s[self.keep] * self.scale
        self.pc.apply(self.xk, self.yk)
        out = np.empty_like(s)
        yk = self.yk.array_r / self.scale
        out[self.keep] = yk
        out[self.slave] = s[self.slave] - self.X @ yk
        y.array[:] = out

    def destroy(self, pc=None):
        for o in (self.pc, self.Kmat, self.xk, self.yk):
            o.destroy()
