"""Krylov solves of the semismooth Newton systems through PETSc KSP (DESIGN §3, §4, §8).

A Newton step solves A X = B, either the full 3N system or the eliminated 2N one
(newton_system). `Krylov.solve` runs GMRES on it from the previous Newton iterate
(X^{k,0} = X^{k-1}, DESIGN §8), and every ν iterations hands the current iterate X^{k,i} and
its algebraic residual R^{k,i} = B - A X^{k,i} to a callback (DESIGN §4: what the estimators
need). The callback may end the solve there by returning True: the adaptive variant's
criterion η_alg ≤ γ_alg max(η_disc, η_lin) decides from the estimators (DESIGN §8), and the
solve then returns that iterate. Iteration counts are PETSc's own: the Krylov steps performed.

**Default set-up** (`DEFAULT_OPTIONS`), each entry overridable through `petsc_options`:
GMRES (PETSc's restart, 30) with ILU(0), as in the paper, preconditioned on the right with the
unpreconditioned norm, so that the residual GMRES minimises and reports is ‖B - A X‖ itself.

**A scalable preconditioner for the eliminated system**: ``pc_type vertex_amg``
(`preconditioner.vertex_amg`: for min the exact split into mean and gap, one BoomerAMG V-cycle
on each, the mean's set up once per mesh and kept in the solver; otherwise 2×2 vertex-block
inverse, contact multipliers as slaves, gap scaling for fb, one BoomerAMG V-cycle; options
``vertex_amg_<option>`` go to the inner PCs).
ILU(0)'s GMRES iterations per Newton step grow like 1/h; vertex_amg's do not (disk, exact
Newton, mean per step, min | fb: 1.5k vertices 51 | 40 → 7.4 | 7.1; 1.1e4: 120 | 102 →
8.1 | 8.3; more in BENCHMARKS.md). ILU(0) stays the default: it also serves the full 3N system,
which vertex_amg cannot precondition (the Newton run reports a linear-solver failure), and below
~1e4 vertices it is as fast in wall time.

With vertex_amg the Krylov method is FGMRES (`VERTEX_AMG_OPTIONS`; ``ksp_type`` in the user's
options wins). For a fixed preconditioner FGMRES is right-preconditioned GMRES — the same
iterates in exact arithmetic, the same iteration counts measured (disk, 1e2 … 4.4e5 vertices) —
but it keeps the preconditioned basis vectors M⁻¹v_i, so that building an iterate (the
stopping test below, every ν-th iterate, the solution) costs no preconditioner application:
GMRES applies M⁻¹ once more each time, two more applications per Newton step of ~8 (a
V-cycle and the vertex-block solve each), ~10 % of a step at 1.1e5 vertices.

**The gap's own solve.** Where the mean is settled (`MeanGapAMG.settle_mean`: every step of
a run with the exact mean, membranes.mean) a correction of the step changes the gap and λ
only, and the split is exact: the correction is δ = S_ff⁻¹ g on the free vertices (g = r2 -
r1 there, r the initial residual), u1 = -θ δ, u2 = (1 - θ) δ, λ at the contact vertices from
δ (`MeanGapAMG.gap_correction`). GMRES then runs on S_ff δ = g itself (N_f ≈ 0.55 N unknowns
instead of 2N, the same Krylov method and options, the gap's V-cycle as its PC, δ from 0),
not on the 2N system with the split as PC: its vectors are a quarter as long and its
products with S_ff a quarter of those with the 2N matrix. The test below is the same, on the
whole system's iterate x0 + the correction and its residual (`_GapTest`); the gap's residual
e gates it through R = (ρ - θ e, ρ + (1 - θ) e), ρ the settled mean part. For θ = 1/2 (μ1 =
μ2) GMRES minimises ‖R‖ either way, and the iteration counts are the same. Measured at 9.3e5
vertices (disk, J = 6, the finest level's three steps solved again from their systems): 0.75-
0.93 s a step against 0.84-1.03 s, the same 7, 5 and 5 iterations.

**The stopping test** is ‖R_alg‖ ≤ tol ‖B‖ on the true residual, B the right-hand side of the
3N system. PETSc's default test compares with rtol ‖b‖ — checked in 3.18: with a nonzero
initial guess it is still ‖b‖, not the initial residual (GMRES stops after 0 iterations when
‖b - A x0‖ ≤ rtol ‖b‖). It is replaced by our own test, for three reasons:

1. the eliminated system's right-hand side F - E t is not B (Fischer–Burmeister, where t ≠ 0):
   the test must measure both systems against the same ‖B‖;
2. GMRES's recursive residual estimate drifts from the true residual near round-off (seen:
   estimate 1.9e-12, true residual 3.4e-12, restart 100, disk h = 0.025). The estimate only
   gates the test: where it says "converged", the iterate is built and B - A X computed, and
   GMRES goes on while the true residual is above the tolerance (with a preconditioned norm,
   set through the options, there is no gate: the true residual is computed at every test);
3. the inexact variant's tolerance ‖R_lin(X^{k-1})‖/‖(F, 0)‖ is met by the initial guess
   itself: B - A X^{k-1} = R_lin(X^{k-1}) (the linear rows are the same; the third block is
   B3 - J_C X^{k-1} = -C(X^{k-1})) and ‖B‖ ≥ ‖(F, 0)‖. Tested after every iteration it would
   stop GMRES after one step (or none). As in the paper, where estimators and stopping
   criteria are evaluated every ν Krylov steps, that test is made at i = ν, 2ν, ...
   (`test_every`), and GMRES, whose residual never grows, meets it at i = ν: the inexact
   variant makes ν Krylov steps per Newton step (the paper's table shows the same, 10 per
   step). The exact variant tests after every iteration.

A zero residual (GMRES's happy breakdown) is always tested. The same callback (the KSP
convergence test, called once per iterate right after GMRES forms it) hands out the ν-th
iterates: a KSP monitor would not do, since GMRES monitors iteration i at the top of
iteration i + 1, or after a restart before the test, and cannot tell the last iterate (which
is the Newton iterate, recorded as such) from the others.

**The zero diagonal of the full system.** The λ-block of the full system is diag(β), and
β_l = 0 at vertices where the row is e1 - e2 (min, contact predicted) or where b = 0 < a (fb).
scipy does not store those zeros, and PETSc 3.18's ILU(0) stops in its symbolic phase
("Matrix is missing diagonal entry"), before any pivot is seen: -pc_factor_shift_type
nonzero cannot help (it shifts numerical pivots), and -pc_factor_nonzeros_along_diagonal
needs the entries as well; where they are stored, its row permutation leaves an ILU(0) that
needs 609 GMRES iterations instead of 50 (disk, h = 0.05, second Newton step). What works is
to store the diagonal, zeros included (`with_diagonal`). Natural-order ILU(0) then meets no
zero pivot: the row α_l (u1 - u2)_l + β_l λ_l comes after the rows of u1_l and u2_l, whose
only λ-entries are ∓D_l in column λ_l, and ILU(0) keeps no other fill in it, so its pivot is
β_l + α_l D_l (1/p1_l + 1/p2_l), with p_α,l the ILU(0) pivots of the stiffness rows (positive:
the P1 stiffness of a Delaunay mesh is an M-matrix). That is D_l (1/p1_l + 1/p2_l) > 0 for
min (α = 1, β = 0) and < 0 for fb (α, β ≤ 0, not both zero). The eliminated system gets the
same treatment (one PETSc matrix builder for both).

**Options.** Each solve applies the options under a private prefix (``membranes_<n>_``) and
removes them from PETSc's database right after `setFromOptions`, so nothing leaks from one
solve to the next nor to other PETSc objects. The tolerances and the iteration limit belong to
the Newton variant and to `max_linear_its`: `ksp_rtol`, `ksp_atol`, `ksp_max_it` are refused.
"""

import itertools
import shlex
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from .linear_solve import LinearSolveError, petsc_matrix
from .preconditioner import INNER_PREFIX, vertex_amg

DEFAULT_OPTIONS = {"ksp_type": "gmres", "pc_type": "ilu", "ksp_pc_side": "right",
                   "ksp_norm_type": "unpreconditioned"}
VERTEX_AMG_OPTIONS = {"ksp_type": "fgmres"}
RESERVED_OPTIONS = {"ksp_rtol": "the Newton variant sets the linear tolerance",
                    "ksp_atol": "the Newton variant sets the linear tolerance",
                    "ksp_max_it": "use max_linear_its (--max-linear-its)"}
DEFAULT_NU = 10
DEFAULT_MAX_LINEAR_ITS = 10000

_prefixes = itertools.count()
_REASONS = {v: k for k, v in vars(PETSc.KSP.ConvergedReason).items() if k.isupper()}


def parse_petsc_options(text):
    """"-ksp_type gmres -pc_type ilu -ksp_monitor" -> {"ksp_type": "gmres", "pc_type": "ilu",
    "ksp_monitor": None}: an option is '-' and a letter; a value is any other token (so -1e-3
    is a value)."""
    options, name = {}, None
    try:
        tokens = shlex.split(text)
    except ValueError as e:
        raise ValueError(f"PETSc options {text!r}: {e}") from None
    for token in tokens:
        if token[:1] == "-" and token[1:2].isalpha():
            name = token[1:]
            options[name] = None
        elif name is not None and options[name] is None:
            options[name] = token
        else:
            raise ValueError(f"PETSc options: value {token!r} follows no option")
    return options


def _petsc_message(error):
    """The last line of a petsc4py error, without its '[0] ' prefix."""
    return str(error).strip().splitlines()[-1].split("] ", 1)[-1]


def _checked_options(petsc_options):
    """DEFAULT_OPTIONS (and VERTEX_AMG_OPTIONS with ``pc_type vertex_amg``) updated by the
    user's options, names without their leading '-'."""
    user = {str(name).lstrip("-"): value for name, value in (petsc_options or {}).items()}
    for name, value in user.items():
        if name in RESERVED_OPTIONS:
            raise ValueError(f"PETSc option -{name} is not accepted: {RESERVED_OPTIONS[name]}")
        if not (value is None or isinstance(value, (str, bool, int, float))):
            raise ValueError(f"PETSc option -{name}: value {value!r} is not a string or number")
    options = dict(DEFAULT_OPTIONS)
    if user.get("pc_type") == "vertex_amg":
        options.update(VERTEX_AMG_OPTIONS)
    options.update(user)
    return options


def _configure(ksp, options):
    """Apply `options` to `ksp` under a private prefix, then take them out of PETSc's database."""
    prefix = f"membranes_{next(_prefixes)}_"
    database = PETSc.Options()
    for name, value in options.items():
        database[prefix + name] = value
    ksp.setOptionsPrefix(prefix)
    try:
        ksp.setFromOptions()
    except PETSc.Error as e:
        raise ValueError(f"PETSc options: {_petsc_message(e)}") from None
    finally:
        for name in options:
            database.delValue(prefix + name)


def with_diagonal(A):
    """A (CSR) with every diagonal entry stored, zeros included (see the module notes): a zero
    is appended to each row that stores no diagonal entry (A itself if none is missing)."""
    A = sp.csr_matrix(A)
    n = A.shape[0]
    if np.all(A.diagonal() != 0):      # all stored (the usual case): no pass over the entries
        return A
    rows = np.repeat(np.arange(n), np.diff(A.indptr))
    stored = np.zeros(n, dtype=bool)
    stored[rows[A.indices == rows]] = True
    missing = np.flatnonzero(~stored)
    if missing.size == 0:
        return A
    at = A.indptr[missing + 1]          # the end of each such row
    indptr = A.indptr + np.searchsorted(missing, np.arange(n + 1))
    return sp.csr_matrix((np.insert(A.data, at, 0.0), np.insert(A.indices, at, missing), indptr),
                         shape=A.shape)


def _split_options(options):
    """(options for the KSP, options of the vertex-block AMG or None): `pc_type vertex_amg`
    becomes `pc_type none` for PETSc (the Python PC is installed per solve, `_install`), and
    the `vertex_amg_*` options go to its inner PC without their prefix."""
    inner = {name[len(INNER_PREFIX):]: value for name, value in options.items()
             if name.startswith(INNER_PREFIX)}
    outer = {name: value for name, value in options.items() if not name.startswith(INNER_PREFIX)}
    if outer.get("pc_type") != "vertex_amg":
        if inner:
            raise ValueError(f"PETSc option -{INNER_PREFIX}{next(iter(inner))} needs "
                             "-pc_type vertex_amg")
        return outer, None
    outer["pc_type"] = "none"
    return outer, inner


def _install(ksp, A, inner, cache=None, contact=None):
    """The vertex-block AMG of A (`preconditioner.vertex_amg`, with its `cache` and `contact`)
    as the KSP's (Python) PC; PETSc frees it with the KSP."""
    try:
        context = vertex_amg(A, inner, cache, contact)
    except PETSc.Error as e:
        raise ValueError(f"PETSc options of vertex_amg: {_petsc_message(e)}") from None
    except ValueError as e:        # not the eliminated system: the Newton run reports it
        raise LinearSolveError(str(e)) from None
    pc = ksp.getPC()
    pc.setType(PETSc.PC.Type.PYTHON)
    pc.setPythonContext(context)
    return context


@dataclass
class Krylov:
    """A PETSc Krylov solver: `options` (the user's `petsc_options` on top of DEFAULT_OPTIONS,
    checked by configuring a KSP), ν (`nu`: iterates handed out every ν steps) and the
    iteration limit of one solve."""
    petsc_options: dict = None
    nu: int = DEFAULT_NU
    max_linear_its: int = DEFAULT_MAX_LINEAR_ITS
    options: dict = field(init=False)
    _petsc: dict = field(init=False, repr=False)
    _vertex_amg: dict = field(init=False, repr=False)
    _cache: dict = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self):
        for name in ("nu", "max_linear_its"):
            value = getattr(self, name)
            if isinstance(value, bool) or not float(value).is_integer() or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value}")
            setattr(self, name, int(value))
        self.options = _checked_options(self.petsc_options)
        self._petsc, self._vertex_amg = _split_options(self.options)
        ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        try:
            _configure(ksp, self._petsc)
            if self._vertex_amg is not None:      # check the inner options on a 2 x 2 system
                _install(ksp, sp.identity(2, format="csr"), self._vertex_amg)
        finally:
            ksp.destroy()

    @property
    def vertex_amg(self):
        """The inner options of ``pc_type vertex_amg`` (a dict), or None for another PC."""
        return self._vertex_amg

    def solve(self, A, b, x0, tol, scale, test_every=1, on_iterate=None, cancel=None,
              mean_theta=None, contact=None):
        """Solve A x = b from x0 until ‖b - A x‖ ≤ tol · scale (tested after iterations
        test_every, 2 test_every, ...) or until on_iterate says stop. Every ν iterations that
        do not meet the test, on_iterate(its, current) is called; current() returns
        (x, b - A x) at that iterate; a true return value stops the solve at that iterate.
        `cancel()`, asked before the preconditioner is set up, before the first iteration and
        after every iteration, stops the solve at once when true (a step computed ahead that
        will be dropped, membranes.newton); its iterate is returned. `mean_theta`: the θ of
        the mean the caller keeps (membranes.mean), for vertex_amg's mean/gap split where the
        system alone does not fix it (no contact vertex). `contact`: where a min step on the
        eliminated system eliminated u2 (newton.LinearStep.contact), for vertex_amg's split.
        Returns (x, b - A x, its); raises LinearSolveError (with `its`) if the KSP stops
        before either happens (e.g. at max_linear_its)."""
        x0 = np.array(x0, dtype=float)
        ksp, work, idle = self._kept_ksp(A.shape[0])
        M = rhs = x = gap = None    # the 2N system's PETSc objects, or the gap's own solve
        failed = True
        try:
            _configure(ksp, self._petsc)
            if cancel is not None and cancel():     # dropped before its preconditioner is set up
                failed = False
                return x0, b - A @ x0, 0
            bound = tol * scale
            if self._vertex_amg is not None:
                context = _install(ksp, A, self._vertex_amg, self._cache, contact)
                if hasattr(context, "settle_mean"):       # the mean/gap split
                    r0 = b - A @ x0
                    context.settle_mean(r0, bound, mean_theta)
                    g = context.gap_rhs(r0) if context.mean_settled and \
                        context.gap is not None and \
                        self._petsc.get("ksp_type") in GAP_KSP_TYPES else None
                    if g is not None and np.any(g):     # (GMRES breaks down on g = 0)
                        gap = _GapSolve(context, r0, g, self._petsc)
            if gap is None:
                M = petsc_matrix(with_diagonal(A), copy=False)   # A is the step's: not changed
                rhs = PETSc.Vec().createWithArray(np.array(b, dtype=float), comm=PETSc.COMM_SELF)
                x = PETSc.Vec().createWithArray(x0.copy(), comm=PETSc.COMM_SELF)
                ksp.setOperators(M)
                solver, rhs_s, x_s = ksp, rhs, x
                test = _StoppingTest(A, b, work, bound, test_every, self.nu, on_iterate, cancel)
            else:
                solver, rhs_s, x_s = gap.ksp, gap.rhs, gap.x
                test = _GapTest(A, b, gap, bound, test_every, self.nu, on_iterate, cancel, x0)
            solver.setTolerances(max_it=self.max_linear_its)
            solver.setInitialGuessNonzero(gap is None)
            solver.setConvergenceTest(test)
            try:
                solver.solve(rhs_s, x_s)
            except PETSc.Error as e:
                raise LinearSolveError(f"PETSc: {_petsc_message(e)}",
                                       its=solver.getIterationNumber()) from None
            its, reason = solver.getIterationNumber(), solver.getConvergedReason()
            failed = False
            tested = test.tested if test.its == its else None
            if tested is not None and np.array_equal(test.built, x_s.array_r):
                xs, r = tested             # the iterate the test built: its residual is known
            else:
                xs = test.solution(x_s.array.copy())
                r = b - A @ xs
            if reason > 0 and (test.stopped or np.linalg.norm(r) <= bound):
                return xs, r, its
            raise LinearSolveError(
                f"{solver.getType()} stopped after {its} iterations "
                f"({_REASONS.get(reason, reason)}) at ||R_alg||/||B|| = "
                f"{np.linalg.norm(r) / scale:.2e} > {tol:.1e}", its=its)
        finally:
            # the step's objects go: its PC (PETSc frees a Python PC's context, and with it the
            # gap's AMG, when the PC type changes), its matrix (the KSP holds `idle`, an empty
            # matrix of the same size, in its place) and the test, which holds A and b
            if gap is not None:
                gap.destroy()
            ksp.getPC().setType(PETSc.PC.Type.NONE)
            ksp.setConvergenceTest(None)
            ksp.setOperators(idle)
            for obj in (x, rhs, M):
                if obj is not None:
                    obj.destroy()
            if failed:                 # a PETSc error: the next solve starts afresh
                self.release()

    def _kept_ksp(self, size):
        """(KSP, work vector, idle matrix) for systems of `size` unknowns: created for the first
        system of that size and kept for the next ones (one KSP per mesh, `release` frees it),
        so that GMRES allocates its Krylov vectors once per mesh, not once per Newton step
        (at 9.3e5 vertices: 1.9e6 unknowns, 15 MB a vector; creating them took ~0.07 s of
        each solve). A KSP gets the same settings every solve (`_configure`), its PC is fresh
        every solve (its type set anew), and GMRES keeps no state from one solve to the next
        but its vectors' memory: the same iterates as with a new KSP."""
        kept = self._cache.get("ksp")
        if kept is not None and kept[0] == size:
            return kept[1:]
        self.release()
        ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        work = PETSc.Vec().createSeq(size, comm=PETSc.COMM_SELF)
        empty = np.zeros(size + 1, dtype=PETSc.IntType)
        idle = PETSc.Mat().createAIJWithArrays(
            (size, size), (empty, np.zeros(0, dtype=PETSc.IntType), np.zeros(0)),
            comm=PETSc.COMM_SELF)
        idle.assemble()
        self._cache["ksp"] = (size, ksp, work, idle)
        return ksp, work, idle

    def release(self):
        """Free the kept KSP (`_kept_ksp`)."""
        kept = self._cache.pop("ksp", None)
        if kept is not None:
            for obj in kept[1:]:
                obj.destroy()


class _StoppingTest:
    """The KSP convergence test of the module notes; it also hands out every ν-th iterate,
    and stops GMRES there (`stopped`) when the callback returns True."""

    def __init__(self, A, b, work, bound, test_every, nu, on_iterate, cancel=None):
        self.A, self.b, self.work, self.bound = A, b, work, bound
        self.test_every, self.nu, self.on_iterate = test_every, nu, on_iterate
        self.cancel = cancel
        self.its, self._current, self.stopped, self.built = 0, None, False, None

    def solution(self, y):
        """The iterate x of A x = b from the KSP's solution y (y itself here; y is not
        changed)."""
        return y

    def gate(self, rnorm):
        """Whether GMRES's residual estimate `rnorm` lets ‖b - A x‖ meet the bound."""
        return rnorm <= self.bound

    def current(self):
        """(x, b - A x) at the iterate under test, built once."""
        if self._current is None:
            self.built = self.ksp.buildSolution(self.work).array.copy()
            x = self.solution(self.built)
            self._current = (x, self.b - self.A @ x)
        return self._current

    @property
    def tested(self):
        """(x, b - A x) at the last iterate the test built (`current`), or None: the KSP's
        solution when it stopped at that iterate (the same vector, `built`: GMRES builds its
        solution as buildSolution does; `Krylov.solve` checks), so that the residual is not
        formed again."""
        return self._current

    def __call__(self, ksp, its, rnorm):
        if its == 0 and self.cancel is not None and self.cancel():
            # cancelled while the preconditioner was set up: no iteration (0.1 s at 9.3e5
            # vertices) before the step ahead is dropped
            self.stopped = True
            return PETSc.KSP.ConvergedReason.CONVERGED_ITS
        if its <= self.its:     # the initial guess, or the same iterate again after a restart
            return PETSc.KSP.ConvergedReason.ITERATING
        self.ksp, self.its, self._current = ksp, its, None
        try:
            return self._verdict(ksp, its, rnorm)
        finally:
            # the KSP handed in holds a PETSc reference, and this test lives in that KSP's
            # context: kept past the call, the pair would never be freed (measured: the ILU
            # factor and GMRES vectors of every solve, ~16 MB a Newton step at 35k cells)
            self.ksp = None

    def _verdict(self, ksp, its, rnorm):
        if self.cancel is not None and self.cancel():
            self.stopped = True
            return PETSc.KSP.ConvergedReason.CONVERGED_ITS
        estimate_is_residual = ksp.getNormType() == PETSc.KSP.NormType.UNPRECONDITIONED
        if (its % self.test_every == 0 or rnorm == 0) and \
                (not estimate_is_residual or self.gate(rnorm)) and \
                np.linalg.norm(self.current()[1]) <= self.bound:
            return PETSc.KSP.ConvergedReason.CONVERGED_ATOL
        if self.on_iterate is not None and its % self.nu == 0 and \
                self.on_iterate(its, self.current):
            self.stopped = True
            return PETSc.KSP.ConvergedReason.CONVERGED_ITS
        return PETSc.KSP.ConvergedReason.ITERATING


GAP_KSP_TYPES = ("fgmres", "gmres")    # the Krylov methods the gap's own solve is taken with


class _GapSolve:
    """The gap's own system S_ff δ = g (module notes: a settled mean), its KSP (the step's
    options) with the gap's inner PC (`preconditioner.MeanGapAMG`), and its vectors: the
    right side g = (r2 - r1) on the free vertices of the step's initial residual r0
    (`MeanGapAMG.gap_rhs`), the solution δ from 0."""

    def __init__(self, context, r0, g, options):
        self.context, self.r0 = context, r0
        self.rhs = PETSc.Vec().createWithArray(g, comm=PETSc.COMM_SELF)
        self.x = PETSc.Vec().createWithArray(np.zeros(context.free.size), comm=PETSc.COMM_SELF)
        self.work = PETSc.Vec().createSeq(context.free.size, comm=PETSc.COMM_SELF)
        self.ksp = PETSc.KSP().create(PETSc.COMM_SELF)
        self.ksp.setOperators(context.gap.mat)
        _configure(self.ksp, options)
        self.ksp.setPC(context.gap.pc)

    def destroy(self):
        for obj in (self.ksp, self.rhs, self.x, self.work):
            obj.destroy()


class _GapTest(_StoppingTest):
    """The stopping test of the gap's own solve (module notes): the iterate it hands out and
    tests is x0 + the correction of the gap's iterate δ (`MeanGapAMG.gap_correction`), its
    residual that of A x = b. The gap's residual estimate e gates the test through the
    residual of the whole system, R = (ρ - θ e, ρ + (1 - θ) e) (ρ the settled mean part
    of r0, e zero at the contact vertices): ‖R‖² ≥ 2‖ρ‖² - 2 |1 - 2θ| ‖ρ_f‖ ‖e‖ +
    (θ² + (1 - θ)²) ‖e‖², equal for θ = 1/2 (μ1 = μ2)."""

    def __init__(self, A, b, gap, bound, test_every, nu, on_iterate, cancel, x0):
        super().__init__(A, b, gap.work, bound, test_every, nu, on_iterate, cancel)
        self.gap, self.x0 = gap, x0
        context = gap.context
        theta, rho = context.theta, context.rho        # ρ as settle_mean measured it
        self.rho2 = 2.0 * float(rho @ rho)
        self.cross = 2.0 * abs(1.0 - 2.0 * theta) * float(np.linalg.norm(rho[context.free]))
        self.e2 = theta * theta + (1.0 - theta) * (1.0 - theta)

    def solution(self, y):
        return self.x0 + self.gap.context.gap_correction(self.gap.r0, y)

    def gate(self, rnorm):
        low = self.rho2 - self.cross * rnorm + self.e2 * rnorm * rnorm
        return low <= self.bound * self.bound
