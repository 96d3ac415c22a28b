"""The mean/gap preconditioner of the eliminated Newton system (§3, §10, §12).

**The system.** After the elimination of one unknown per vertex (membranes.nonlinear.system),
the unknowns are Y = (u1, z) and the rows, weighted by W, are at every interior vertex

    r1 = S u1 - a λ,    r2 = S u2 + b λ,    a = D/μ1,  b = D/μ2,

with, for a correction (the constants of the elimination drop out),

    λ eliminated ("free" vertex):     λ = c (u2 - u1),  c = α/β   (0 for min, ≥ 0 for FB)
    u2 eliminated ("contact" vertex): u2 - u1 = d λ,    d = β/α   (0 for min, ≥ 0 for FB).

At the boundary vertices both rows are identity rows (u1 = g, u2 = 0) and λ is eliminated.
S_D denotes the stiffness matrix with those identity rows: it is the u1 block and the u2 block
of the weighted system alike.

**The split (§10).** With θ = a/(a + b) = μ2/(μ1 + μ2), the mean m = (1 - θ) u1 + θ u2
(∝ z = μ1 u1 + μ2 u2 of §10) and the gap δ = u2 - u1 (= -w), the rows fall apart exactly:

    S_D m = (1 - θ) r1 + θ r2                        (every vertex: λ cancels)
    S_D δ + (a + b) λ = r2 - r1,

and with λ = c δ at free vertices and λ = δ/d at contact vertices with d > 0 the second is
the gap's reaction–diffusion problem (S_D + diag p) δ = r2 - r1 with p = (a + b) c or
(a + b)/d ≥ 0, on the vertices G where δ is unknown; at contact vertices with d = 0 (every
contact vertex of Newton-min) δ = 0 and λ = (r2 - r1 - S_D δ)/(a + b). Then
u1 = m - θ δ, u2 = m + (1 - θ) δ. Both are Laplacians plus a nonnegative reaction: one
BoomerAMG V-cycle on each (hypre through PETSc) is a preconditioner whose quality does not
depend on h, where ILU(0) needs O(1/h) Krylov iterations per Newton step. With exact inner
solves the preconditioner is the exact inverse of the eliminated matrix (one Krylov
iteration); the tests check that. The same split serves Newton-min and Fischer–Burmeister.

The mean's operator S_D does not depend on the iterate: its AMG is set up once per mesh
(`InnerPC`, kept by the Krylov solver); the gap's, (S_D + diag p)[G, G] (`gap_operator`, a
MatCreateSubMatrix of the owned G rows on every process), once per Newton step whose G or p
differ from the last step's (the Krylov solver keeps it: a step solved twice, and the steps
of Newton-min once its contact set has settled, where p = 0 and G repeats, reuse it).
Everything else is vertex-local numpy on the owned entries and one parallel product with S_D
where contact vertices have d = 0.

**Inner options.** Defaults `INNER_DEFAULTS`: BoomerAMG with one forward hybrid Gauss–Seidel
sweep down and one backward sweep up (`SWEEPS`: a symmetric V-cycle at half the cost of
PETSc's default symmetric sweeps both ways). They are set under the solver's prefix + 'mean_'
and + 'gap_': a user's option ``mean_pc_type lu`` or ``gap_pc_hypre_boomeramg_strong_threshold
0.5`` reaches them.
"""

import numpy as np
from petsc4py import PETSc

# BoomerAMG's smoothing: one forward hybrid Gauss–Seidel sweep down, one backward sweep up
SWEEPS = {"pc_hypre_boomeramg_relax_type_down": "SOR/Jacobi",
          "pc_hypre_boomeramg_relax_type_up": "backward-SOR/Jacobi"}
INNER_DEFAULTS = {"pc_type": "hypre", "pc_hypre_type": "boomeramg", **SWEEPS}


def petsc_message(error):
    """The last line of a petsc4py error, without its '[0] ' prefix."""
    return str(error).strip().splitlines()[-1].split("] ", 1)[-1]


def put_options(prefix, options):
    """Set `options` (names without '-'; a value None is a flag) under `prefix` in PETSc's
    database. They stay there while the objects that read them live (a factorisation reads its
    solver's options when it is set up, not when its KSP is configured): `take_options` takes
    them out again, so that nothing reaches other PETSc objects."""
    database = PETSc.Options()
    for name, value in options.items():
        database[prefix + name] = "" if value is None else value


def take_options(prefix, options):
    """Remove what `put_options` set."""
    database = PETSc.Options()
    for name in options:
        database.delValue(prefix + name)


def configure(obj, prefix):
    """Configure `obj` (a KSP or a PC) from the options under `prefix`; ValueError on an
    option PETSc refuses."""
    obj.setOptionsPrefix(prefix)
    try:
        obj.setFromOptions()
        if isinstance(obj, PETSc.KSP):
            obj.getNormType()     # PETSc checks here that the KSP supports its norm and side
    except PETSc.Error as e:
        raise ValueError(f"PETSc options: {petsc_message(e)}") from None


def inner_defaults(options, name):
    """The options of the inner PC `name` ('mean', 'gap') to put under the solver's prefix:
    `INNER_DEFAULTS` (unless the user chose another PC type) below the user's."""
    head = name + "_"
    user = {k[len(head):]: v for k, v in options.items() if k.startswith(head)}
    merged = dict(INNER_DEFAULTS) if user.get("pc_type", "hypre") == "hypre" else {}
    merged.update(user)
    return {head + k: v for k, v in merged.items()}


class InnerPC:
    """A PC on the matrix M configured from the options under `prefix` (`inner_defaults`:
    BoomerAMG by default); `apply()`: one application to the Vec `b`, into `x`."""

    def __init__(self, M, prefix):
        self.M = M
        self.pc = PETSc.PC().create(M.getComm())
        self.pc.setOperators(M)
        configure(self.pc, prefix)
        self.pc.setUp()
        self.x, self.b = M.createVecs()

    def apply(self):
        self.pc.apply(self.b, self.x)
        return self.x

    def destroy(self):
        for obj in (self.pc, self.b, self.x):
            obj.destroy()


def gap_operator(S_D, G, p):
    """K = (S_D + diag p)[G, G], the gap's operator of the module notes: a MatCreateSubMatrix
    of the owned rows G (local indices) on every process, with the reaction p (on G) added to
    its diagonal where any process has a nonzero one."""
    comm = S_D.getComm()
    r0 = S_D.getOwnershipRange()[0]
    iset = PETSc.IS().createGeneral(np.asarray(r0 + G, dtype=PETSc.IntType), comm=comm)
    K = S_D.createSubMatrix(iset, iset)
    iset.destroy()
    from mpi4py import MPI
    if comm.tompi4py().allreduce(bool(np.any(p != 0.0)), op=MPI.LOR):
        reaction = K.createVecLeft()
        reaction.array[:] = p
        K.setDiagonal(reaction, addv=PETSc.InsertMode.ADD_VALUES)
        reaction.destroy()
    return K


class MeanGapPC:
    """The preconditioner of the module notes as a petsc4py Python PC context.

    S_D: the stiffness matrix with identity boundary rows (PETSc Mat, n × n per process);
    ab = a + b = D (1/μ1 + 1/μ2) (owned, 0 at the boundary); theta = μ2/(μ1 + μ2);
    lam_out, c, d: the step's elimination (membranes.nonlinear.system.EliminatedStep);
    mean: the mesh's InnerPC on S_D; gap: a callable (G, p) → the InnerPC on the gap's
    operator (S_D + diag p)[G, G] (`gap_operator`), whose owner frees it (the Krylov solver,
    which keeps it for a later step with the same G and p: membranes.linalg.krylov)."""

    def __init__(self, S_D, ab, theta, lam_out, c, d, mean, gap):
        self.S, self.theta, self.mean = S_D, float(theta), mean
        n = len(lam_out)
        self.n = n
        self.free = lam_out
        self.soft = ~lam_out & (d != 0.0)         # contact vertices with d > 0 (FB)
        self.hard = ~lam_out & (d == 0.0)         # contact vertices with d = 0 (min)
        self.ab = ab
        self.d = np.where(self.soft, d, 1.0)
        comm = S_D.getComm().tompi4py()
        from mpi4py import MPI
        self.any_hard = comm.allreduce(bool(self.hard.any()), op=MPI.LOR)
        self.G = np.flatnonzero(self.free | self.soft)       # G: where δ is unknown
        self.gap = gap(self.G, np.where(self.free, ab * c, ab / self.d)[self.G])
        self.delta, self.S_delta = S_D.createVecs()

    def apply(self, pc, x, y):
        """y = M⁻¹ x (module notes)."""
        n, th = self.n, self.theta
        r = x.array_r
        r1, r2 = r[:n], r[n:]
        diff = r2 - r1
        self.mean.b.array[:] = (1.0 - th) * r1 + th * r2
        m = self.mean.apply().array_r
        self.gap.b.array[:] = diff[self.G]
        delta = self.delta.array
        delta[:] = 0.0
        delta[self.G] = self.gap.apply().array_r
        out = y.array
        out[:n] = m - th * delta
        out[n:] = np.where(self.free, m + (1.0 - th) * delta, delta / self.d)
        if self.any_hard:
            self.S.mult(self.delta, self.S_delta)
            h = self.hard
            out[n:][h] = (diff[h] - self.S_delta.array_r[h]) / self.ab[h]

    def destroy(self, pc=None):
        for obj in (self.delta, self.S_delta):
            obj.destroy()
