"""A posteriori estimators and the guaranteed bound on the distributed mesh (§6, §7).

For an iterate X = (u1h, u2h, λh) with algebraic residual R (§4), per cell K and membrane α:

    η_F,K,α   = ‖μ_α^{1/2} ∇u_αh + μ_α^{-1/2} σ_α‖_K,   σ_α = σ_α,disc + σ_α,alg
    η_osc,K,α = (h_K/π) μ_α^{-1/2} ‖f_α - Π_P1 f_α‖_K
    η_C,K     = 2 (u1h - u2h, λ^pos)_K
    η_lin1,K  = |||s_h - u_h|||_K
    η_lin2,K  = 2 C_PF h_Ω (1/μ1 + 1/μ2)^{1/2} ‖λ^pos‖_Ω |||s_h - u_h|||_K
    η_lin3,K  = C_PF h_Ω (1/μ1 + 1/μ2)^{1/2} ‖λ^neg‖_K
    η_alg,K,α = ‖μ_α^{-1/2} σ_α,alg‖_K

with s_h the nodal projection onto the constraint (s_h = u_h where u1h ≥ u2h, else both
components (u1h + u2h)/2) and λ^pos, λ^neg the nodal positive and negative parts of λh.

**How the numbers are computed.** Every per-cell integral is a UFL form of
`forms/estimators.py` tested with a piecewise constant: the quantities of one evaluation are
the components of one vector-DG0 test function, so one dolfinx assembly over the owned cells
gives them all on every cell (exact quadrature for the polynomial integrands; the data
measures for f). The forms are compiled once per mesh with dolfinx Functions as coefficients;
an evaluation writes the iterate's values into those Functions (nodal values on the owned
dofs, then `scatter_forward` for the ghosts) and assembles. The nodal fields (u1h, u2h,
λ^pos, λ^neg, s_h - u_h, δλ) are the components of one vector-P1 Function: dolfinx packs the
coefficients cell by cell before every assembly, and one gather per vertex for all of them
costs a fraction of one per field. `evaluate`'s default remainder (below) is integrated in the
same assembly as the estimators. Global values are sums over the owned cells reduced over the
communicator: every process returns the same numbers.

**The remainder η_rem** (§6). The flux σ_α = σ_α,disc + σ_α,alg satisfies
∇·σ_α = Π_P1 f_α ± λh - ρ_α on every cell, with ρ_α the part of the residual it leaves out of
balance: ρ_α = r_αh without algebraic flux, r_αh - ∇·σ_α,alg for the multilevel flux (zero in
exact arithmetic; its measured round-off defect, `remainder_of`), r'_αh ∓ (λ'_h - λh) for the
ν flux (`nu_flux`). In the residual of the energy argument behind the bound, ρ enters as
Σ_α (ρ_α, v_α), and Poincaré–Friedrichs
(‖v_α‖ ≤ C_PF h_Ω ‖∇v_α‖, v_α ∈ H¹_0) gives

    |Σ_α (ρ_α, v_α)| ≤ C_PF h_Ω (Σ_α μ_α^{-1} ‖ρ_α‖²)^{1/2} |||v||| = η_rem |||v|||,

a term of the same kind as the flux term ≤ η_1 |||v|||. σ_α,disc's own divergence is exact only
to round-off too: its measured defect d_α = ∇·σ_α,disc - (Π_P1 f_α ± λh - r_αh) (DG1, its norm
from the moments the divergence check assembles, `FluxEquilibration.defect_sq`) joins ρ_α, and
by the triangle inequality η_rem is the sum of the remainder above and C_PF h_Ω (Σ_α μ_α^{-1}
‖d_α‖²)^{1/2} (for the ν flux, whose σ_disc + σ_alg is σ_disc of the later iterate, that
iterate's defect, and the one at X too: a bound larger by round-off). It is 8e-12 of η on the
disk and up to 1.2e-5 of η on `structured_square(16, 16, 5)` (cells of aspect ratio 2.9e5).
So η_rem adds to η_1 in the bound, and, being algebraic in origin, to η_alg in the stopping
criteria (as in Ern & Vohralík, SISC 2013):

    η     = {(η_1 + η_rem + η_lin1 + η_lin3)² + η_lin2 + max(0, Σ_C)}^{1/2}
    η_alg = (Σ_K Σ_α η_alg,K,α²)^{1/2} + η_rem,

which keeps η ≤ η_disc + η_lin + η_alg. With η_rem = 0 this is §7's formula as written.
"""

import numpy as np
import ufl
from mpi4py import MPI

from ..fem.quadrature import over
from ..forms.estimators import (
    FLUX_RULE,
    P1_RULE,
    cell_norm_squared,
    contact_estimator,
    energy_squared,
    flux_squared,
    oscillation_squared,
    recovery_load,
    weighted_norm_squared,
)
from ..model.checks import check_force_scale
from .cell_forms import CellForm, chunks, compiled, global_sums
from .equilibration import nodal_function

# Components of the per-cell vector of one evaluation (the vector-DG0 test function's index)
DISC1, DISC2, CONTACT, LIN1, LAM_POS, LAM_NEG = range(6)      # always
FLUX1, FLUX2, ALG1, ALG2 = range(6, 10)                          # with an algebraic flux
REM1, REM2 = range(6, 8)                      # with the remainder, no algebraic flux (evaluate)
# Components of the one vector-P1 Function that holds the forms' nodal fields
U1, U2, LPOS, LNEG, E1, E2, DLAM = range(7)
# The forms square forces, not displacements: μ_α ∇u_αh + σ_α, σ_α,alg, the lifted residuals,
# λ and f_α, all of size μ_α u for a displacement u on a domain of unit size (μ u / ℓ and
# μ u / ℓ² for its length ℓ; §11: scaling μ1, μ2, f1, f2 by c scales them by c and leaves u
# alone). Sizes below model.checks.UNDERFLOW_SCALE are refused
# (`check_force_scale`), as the data's displacements are by membranes.nonlinear.system: with
# μ1 = μ2 = 1e-40 and u ≈ 1e-130 (forces ≈ 1e-170) η_F squared to 0 and η fell to 0.13 times
# the energy error, with μ = 1e-50 and u ≈ 1e-135 η and the error read 0, and every run said
# converged with a guaranteed bound. The overflow of those squares is `_combine`'s check.


def owned(X):
    """The owned entries of an iterate-layout PETSc Vec (read-only), or the array itself."""
    return X.array_r if hasattr(X, "array_r") else np.asarray(X)


def constraint_parts(u1, u2, lam):
    """Nodal values (on the owned dofs) of λ^pos = max(λ, 0), λ^neg = min(λ, 0) and of
    e = s_h - u_h: 0 where u1h ≥ u2h, else ((u2h - u1h)/2, (u1h - u2h)/2), which moves both
    membranes to their mean (§7)."""
    lam_pos = np.maximum(lam, 0.0)
    lam_neg = np.minimum(lam, 0.0)
    half = np.where(u1 < u2, 0.5 * (u2 - u1), 0.0)
    return lam_pos, lam_neg, half, -half


class Estimators:
    """The estimators of §7 on one mesh: set up once (spaces, Functions, compiled forms, the
    residual lifting), evaluated at any iterate by `evaluate(X, R)`.

    `equilibration`: the σ_α,disc of §5, a `membranes.estimation.equilibration.
    FluxEquilibration` (`sigma(alpha, u, lam, r, f, mu, out)`, its RT_1 space `rt_space`);
    it is asked only by `sigma_disc` (and so by `evaluate` and `nu_flux`). Without it,
    `assemble` takes σ_disc from the caller. `eager_data`: make the data parts (`_data_parts`)
    in the set-up, for a caller that evaluates at once (the certificate of a given iterate)."""

    def __init__(self, disc, equilibration=None, eager_data=False):
        from dolfinx import fem
        from petsc4py import PETSc

        from .lifting import Lifting
        mesh = disc.mesh
        self.disc, self.equilibration, self.comm = disc, equilibration, disc.comm
        self.n = disc.n
        self.mu = (float(disc.mu1), float(disc.mu2))
        check_force_scale(disc)
        self.cpf = float(disc.poincare)
        self.c_lambda = self.cpf * np.sqrt(1.0 / self.mu[0] + 1.0 / self.mu[1])   # C_λ, §7
        mu = [fem.Constant(mesh, PETSc.ScalarType(m)) for m in self.mu]
        self._mu = mu
        V = disc.V
        self.lifting = Lifting(V, None if equilibration is None           # R_α ↦ r_αh (§4)
                               else equilibration.r.function_space)     # (its DG1 space)
        self.DG1 = self.lifting.Q
        if equilibration is not None and equilibration.area is None:
            equilibration.area = self.lifting.area      # (its defect norm's cells: the same)
        self.RT = (equilibration.rt_space if equilibration is not None
                   else fem.FunctionSpace(mesh, ("RT", 2)))
        # σ_disc's loads and η_osc, made at the first full evaluation (`_data_parts`)
        self._loads = self._osc_t = self._osc_sum = None
        # coefficients the evaluations write into. The nodal fields u1h, u2h, λ^pos, λ^neg,
        # s_h - u_h and δλ = λ'_h - λh (ν flux) are the components of ONE vector-P1 Function:
        # dolfinx packs a form's coefficients cell by cell, and the values of a vertex then lie
        # side by side (one gather instead of one per field)
        self.nodal = nodal_function(V, DLAM + 1)
        self._nodal = self.nodal.x.array.reshape(-1, DLAM + 1)         # (vertices, fields)
        # the forms' coefficients σ_α,disc, σ_α,alg and r_αh (lifted R_α), made at first use
        self._sigma = self._sigma_alg = self._rho = None
        self._build_forms()
        if eager_data:
            self._data_parts()
        self._recent = []                                               # σ_disc's last two
        self._defect_rem = {}           # σ_disc's measured defect as a remainder, by its σ_1
        self._u_sigma = [fem.Function(V) for _ in range(3)]             # σ_disc's iterate
        self._layouts = {}                                              # `_alike`'s verdicts
        self._recovery = None                                           # `recovered`'s forms

    # ## Set-up

    def _build_forms(self):
        mesh = self.disc.mesh
        u1, u2, lam_pos, lam_neg, e1, e2, dlam = (self.nodal[i] for i in range(DLAM + 1))
        mu1, mu2 = self._mu
        dp = ufl.dx(domain=mesh, metadata=P1_RULE)
        df = ufl.dx(domain=mesh, metadata=FLUX_RULE)
        linearisation = self._linearisation_form

        # (the builders run when their form is first used: the coefficients are made then)
        def base(w):
            s1, s2 = self.sigma
            return (flux_squared(mu1, u1, s1, w[DISC1], df)
                    + flux_squared(mu2, u2, s2, w[DISC2], df)
                    + contact_estimator(u1, u2, lam_pos, w[CONTACT], dp)
                    + linearisation(w, LIN1, LAM_POS, LAM_NEG))

        def with_alg(w):
            (s1, s2), (a1, a2) = self.sigma, self.sigma_alg
            return (base(w)
                    + flux_squared(mu1, u1, s1 + a1, w[FLUX1], df)
                    + flux_squared(mu2, u2, s2 + a2, w[FLUX2], df)
                    + weighted_norm_squared(mu1, a1, w[ALG1], df)
                    + weighted_norm_squared(mu2, a2, w[ALG2], df))

        # ρ_1 = r_1h - δλ, ρ_2 = r_2h + δλ (δλ = λ'_h - λh, zero outside the ν flux; §6)
        def remainder(w, i=0, j=1):
            r1, r2 = self.rho
            return (weighted_norm_squared(mu1, r1 - dlam, w[i], dp)
                    + weighted_norm_squared(mu2, r2 + dlam, w[j], dp))

        # compiled at first use (a run may never need some of them)
        self._cell_forms = {
            "disc": (6, base), "alg": (10, with_alg), "rem": (2, remainder),
            "lin": (3, linearisation),
            # `evaluate`'s default remainder in the same assembly as the estimators
            "disc_rem": (8, lambda w: base(w) + remainder(w, REM1, REM2))}

    def _linearisation_form(self, w, i=0, j=1, k=2):
        """The integrals of η_lin1,K², ‖λ^pos‖_K², ‖λ^neg‖_K² tested with w[i], w[j], w[k]."""
        mesh = self.disc.mesh
        _, _, lam_pos, lam_neg, e1, e2, _ = (self.nodal[m] for m in range(DLAM + 1))
        mu1, mu2 = self._mu
        dp = ufl.dx(domain=mesh, metadata=P1_RULE)
        return (energy_squared(mu1, mu2, e1, e2, w[i], dp)
                + cell_norm_squared(lam_pos, w[j], dp)
                + cell_norm_squared(lam_neg, w[k], dp))

    @property
    def sigma(self):
        """[σ_1,disc, σ_2,disc], the RT_1 Functions of the forms' σ_disc, made at the first
        use; the first σ_disc computed on the mesh is solved into them (`sigma_disc`)."""
        if self._sigma is None:
            from dolfinx import fem
            self._sigma = [fem.Function(self.RT) for _ in range(2)]
        return self._sigma

    @property
    def rho(self):
        """[ρ_1, ρ_2], the DG1 Functions of the remainder's r_αh, made at the first use."""
        if self._rho is None:
            from dolfinx import fem
            self._rho = [fem.Function(self.DG1) for _ in range(2)]
        return self._rho

    @property
    def sigma_alg(self):
        """(σ_1,alg, σ_2,alg), the RT_1 Functions an algebraic flux is written into; made at
        the first use (a run whose Krylov solves meet their test before ν needs none)."""
        if self._sigma_alg is None:
            from dolfinx import fem
            self._sigma_alg = [fem.Function(self.RT) for _ in range(2)]
        return self._sigma_alg

    def _cell_form(self, name):
        entry = self._cell_forms[name]
        if not isinstance(entry, CellForm):
            entry = self._cell_forms[name] = CellForm(self.disc.mesh, *entry)
        return entry

    cells_disc = property(lambda self: self._cell_form("disc"),
                          doc="CellForm of the estimators without algebraic flux")
    cells_alg = property(lambda self: self._cell_form("alg"),
                         doc="CellForm of the estimators with an algebraic flux")
    cells_rem = property(lambda self: self._cell_form("rem"), doc="CellForm of η_rem's terms")
    cells_disc_rem = property(lambda self: self._cell_form("disc_rem"),
                              doc="`cells_disc` and η_rem's terms in one CellForm")

    def _data_parts(self):
        """Make, at its first call, what only a full evaluation reads of the data: σ_disc's
        loads -(ψ_a f_α, q) (§5, `FluxEquilibration.loads`) and η_osc,K,α (§7), whose DG1
        projections take the same assembly's moments where the measures agree. Once per mesh,
        but not in the set-up: the Krylov solves before the first full evaluation (the gates
        read neither) then do not carry them (docs/performance.md). Collective."""
        if self._osc_t is not None:
            return
        disc, eq, moments = self.disc, self.equilibration, None
        if eq is not None:
            self._loads, moments = eq.loads((disc.f1, disc.f2), moments=True)
            moments = moments if eq.measures is disc.dx_data else None  # (other integrals)
        from .lifting import dg1_projections
        pf = dg1_projections(disc, (disc.f1, disc.f2), self.lifting, moments)   # (not kept)
        del moments
        mu1, mu2 = self._mu
        osc = CellForm(disc.mesh, 2, lambda w: over(disc.dx_data, lambda dx: (
            oscillation_squared(mu1, disc.f1, pf[0], w[0], dx)
            + oscillation_squared(mu2, disc.f2, pf[1], w[1], dx))))
        self._osc_t = np.sqrt(np.maximum(np.ascontiguousarray(osc.cells().T), 0.0))  # (2, K)
        self._osc_sum = (self._osc_t ** 2).sum()                        # η_osc², local

    @property
    def loads(self):
        """[Load of f_1, Load of f_2] (`_data_parts`; collective at the first use)."""
        self._data_parts()
        return self._loads

    @property
    def osc(self):
        """η_osc,K,α for every owned cell, (cells, 2) (a view; collective at the first use)."""
        self._data_parts()
        return self._osc_t.T

    # ## Iterate data

    def _write(self, X):
        """u1h, u2h and the nodal λ^pos, λ^neg, s_h - u_h of X into `nodal`."""
        n = self.n
        a = owned(X)
        u1, u2, lam = a[:n], a[n:2 * n], a[2 * n:3 * n]
        values = self._nodal
        values[:n, U1], values[:n, U2] = u1, u2
        for i, v in zip((LPOS, LNEG, E1, E2), constraint_parts(u1, u2, lam)):
            values[:n, i] = v
        self.nodal.x.scatter_forward()

    def linearisation(self, X):
        """η_lin = η_lin1 + η_lin3 + η_lin2^{1/2} and its parts at X (§7), without σ_disc: the
        same integrals as `evaluate`'s, one small assembly. It lets a caller skip the flux
        equilibration where η_lin alone shows that a stopping test fails (`app.schedule`)."""
        self._write(X)
        q = self._cell_form("lin").cells()
        return self._linearisation_parts(*self._linearisation_sums(q))

    def _linearisation_sums(self, q):
        """The global sums of η_lin1,K², η_lin3,K² and ‖λ^pos‖_K² from the columns of q
        (cells, 3) of `_linearisation_form`."""
        lin1, lam_pos, lam_neg = self.comm.allreduce(
            np.maximum(q, [0.0, -np.inf, 0.0]).sum(axis=0), op=MPI.SUM)
        return lin1, self.c_lambda ** 2 * lam_neg, lam_pos

    def recovered(self, X, linearisation=False):
        """η_rec = (Σ_α ‖μ_α^{1/2} ∇u_αh - μ_α^{-1/2} G_α‖²)^{1/2} at X, G_α ∈ P1² the vertex
        average of μ_α ∇u_αh (`forms.estimators.recovery_load`, lumped mass): the gradient
        recovery estimate of the discretisation error (Zienkiewicz–Zhu), the expression of η_F
        (§7) with -G_α in place of the equilibrated σ_α,disc. Not a bound, since G_α is not
        equilibrated: it stands in for η_disc only where none has been computed on the mesh,
        to decide whether the flux equilibration is worth computing (membranes.app.schedule).
        Two small assemblies, no patch problem; the second also integrates η_lin's terms, so
        `linearisation=True` returns (η_rec, `linearisation(X)`) at no extra assembly."""
        from dolfinx import fem, la
        if self._recovery is None:
            self._recovery = self._recovery_forms()
        load, G, cells = self._recovery
        self._write(X)
        G.x.array[:] = 0.0
        for part in load:                                    # `chunks`
            fem.assemble_vector(G.x.array, part)
        G.x.scatter_reverse(la.ScatterMode.add)
        # the owned vertices' averages (the ghosts' follow): the lumped mass (1, ψ_a) is the
        # discretisation's contact weight D
        n = self.n
        G.x.array.reshape(-1, 4)[:n] /= self.disc.D.array_r[:, None]
        G.x.scatter_forward()
        q = cells.cells()                              # (cells, 2 + 3): η_rec's, η_lin's
        eta_rec = float(np.sqrt(max(global_sums(self.comm, q[:, :2]).sum(), 0.0)))
        if not linearisation:
            return eta_rec
        return eta_rec, self._linearisation_parts(*self._linearisation_sums(q[:, 2:]))

    def _recovery_forms(self):
        """`recovered`'s forms, compiled at its first use: the loads (μ_α ∇u_αh, ψ_a) of both
        membranes into one P1⁴ Function G = (G_1, G_2), and the per-cell norms (η_rec's two,
        then η_lin's three)."""
        mesh = self.disc.mesh
        G = nodal_function(self.disc.V, 4)
        dp = ufl.dx(domain=mesh, metadata=P1_RULE)      # exact: G_α ∈ P1², ∇u_αh constant
        v = ufl.TestFunction(G.function_space)
        u1, u2 = self.nodal[U1], self.nodal[U2]
        mu1, mu2 = self._mu
        load = compiled(chunks(recovery_load(mu1, u1, ufl.as_vector([v[0], v[1]]), dp)
                               + recovery_load(mu2, u2, ufl.as_vector([v[2], v[3]]), dp),
                               mesh), mesh)
        G1, G2 = ufl.as_vector([G[0], G[1]]), ufl.as_vector([G[2], G[3]])
        cells = CellForm(mesh, 5, lambda w: flux_squared(mu1, u1, -G1, w[0], dp)
                         + flux_squared(mu2, u2, -G2, w[1], dp)
                         + self._linearisation_form(w, 2, 3, 4))
        return load, G, cells

    def _linearisation_parts(self, lin1_sq, lin3_sq, lam_pos_sq):
        """η_lin1, η_lin2, η_lin3 and η_lin (§7) from the global sums of η_lin1,K², η_lin3,K²
        and ‖λ^pos‖_K²."""
        eta_lin1, eta_lin3 = np.sqrt(max(lin1_sq, 0.0)), np.sqrt(max(lin3_sq, 0.0))
        # η_lin2 = (Σ_K η_lin2,K²)^{1/2} = 2 C_λ ‖λ^pos‖ η_lin1: a product of two
        # energy-norm quantities, which enters η² as it is (§7)
        eta_lin2 = 2.0 * self.c_lambda * np.sqrt(max(lam_pos_sq, 0.0)) * eta_lin1
        return {"eta_lin": float(eta_lin1 + eta_lin3 + np.sqrt(eta_lin2)),
                "eta_lin1": float(eta_lin1), "eta_lin2": float(eta_lin2),
                "eta_lin3": float(eta_lin3)}

    def lifted(self, R, out=None):
        """(r_1h, r_2h): the liftings of R_1, R_2 (§4) as DG1 Functions (zero for R None),
        written into `out` (two DG1 Functions) if given."""
        from dolfinx import fem
        out = out if out is not None else [fem.Function(self.DG1) for _ in range(2)]
        if R is None:
            for r in out:
                r.x.array[:] = 0.0
            return out
        n = self.n
        a = owned(R)
        return [self.lifting(a[k * n:(k + 1) * n], r) for k, r in enumerate(out)]

    def _same(self, a, b):
        """Whether the iterate-sized arrays a, b are equal on every process (collective)."""
        local = (a is None and b is None) or (a is not None and b is not None
                                              and np.array_equal(a, b))
        return self.comm.allreduce(bool(local), op=MPI.LAND)

    def sigma_disc(self, X, R=None):
        """((σ_1,disc, σ_2,disc), (r_1h, r_2h)) at X with algebraic residual R (§4, §5).

        The last two are kept (the ν flux asks for σ_disc at X and at the later iterate, and
        the later one is the next ν flux's X; `evaluate` at X asks again): an iterate seen
        before is found by comparing X and R on every process (collectively, so that all
        processes compute or none), and a new one is written into the Functions of the
        older kept one: the Functions returned stay valid until σ_disc is asked for two
        other iterates. Where no kept one has them, σ_disc is solved into the forms' own σ
        Functions (`sigma`; no second copy under the evaluation), and that kept one is dropped
        when another σ_disc is copied over them (`_set_flux`)."""
        from dolfinx import fem
        x = np.array(owned(X))
        r = None if R is None else np.array(owned(R))
        for i, (key, value) in enumerate(self._recent):
            if self._same(key[0], x) and self._same(key[1], r):
                self._recent.insert(0, self._recent.pop(i))
                return value
        eq = self.equilibration
        if eq is None:
            raise ValueError("σ_disc needs an equilibration (Estimators(disc, equilibration))")
        if len(self._recent) == 2:
            sigma, rh = self._recent.pop()[1]
        else:
            sigma = (tuple(self.sigma) if not any(value[0][0] is self.sigma[0]
                                                  for _, value in self._recent)
                     else tuple(fem.Function(self.RT) for _ in range(2)))
            rh = tuple(fem.Function(self.DG1) for _ in range(2))
        u = self.disc.functions(x, out=self._u_sigma)
        self.lifted(r, rh)
        defects = []
        for alpha in (1, 2):
            eq.sigma(alpha, u[alpha - 1], u[2], rh[alpha - 1], self.loads[alpha - 1],
                     self.mu[alpha - 1], out=sigma[alpha - 1])
            defects.append(eq.defect_sq)
        self._defect_rem[id(sigma[0])] = self.remainder_of(defects)     # (module notes)
        eq.release()                    # its work vectors: not alive under the cell integrals
        self._recent.insert(0, ((x, r), (sigma, rh)))
        return sigma, rh

    # ## The remainder and the ν flux (§6)

    def remainder(self, r, dlam=None):
        """η_rem = C_PF h_Ω (Σ_α μ_α^{-1} ‖ρ_α‖²)^{1/2} with ρ_1 = r_1 - δλ, ρ_2 = r_2 + δλ
        (r_α DG1 Functions, δλ = λ'_h - λh given by its owned nodal values, or 0)."""
        self._set_rho(r, dlam)
        total = global_sums(self.comm, self.cells_rem.cells()).sum()
        return float(self.cpf * np.sqrt(max(total, 0.0)))

    def defect_remainder(self, sigma):
        """C_PF h_Ω (Σ_α μ_α^{-1} ‖d_α‖²)^{1/2} for σ = (σ_1,disc, σ_2,disc) as `sigma_disc`
        returned them, d_α their measured divergence defects (module notes)."""
        return self._defect_rem[id(sigma[0])]

    def remainder_of(self, squares):
        """η_rem = C_PF h_Ω (Σ_α μ_α^{-1} ‖ρ_α‖²)^{1/2} from the global ‖ρ_1‖², ‖ρ_2‖² (the
        multilevel flux's measured divergence defects, `multilevel.MultilevelFlux.defect_sq`)."""
        total = sum(max(float(q), 0.0) / m for q, m in zip(squares, self.mu))
        return float(self.cpf * np.sqrt(total))

    def _set_rho(self, r, dlam=None):
        """r_α and δλ into the remainder's coefficients (`remainder`)."""
        n = self.n
        for target, source in zip(self.rho, r):
            if not self._alike(source.function_space, target.function_space):
                raise ValueError("r_αh must be a DG1 Function (the lifting's space)")
            target.x.array[:] = source.x.array
        self._nodal[:n, DLAM] = 0.0 if dlam is None else dlam
        self.nodal.x.scatter_forward()

    def nu_flux(self, X, R, X_later, R_later):
        """The algebraic flux of ν extra iterations (§6) at X (residual R) from the later
        iterate X_later (residual R_later) of the same linear solve:

            σ_α,alg = σ_α,disc(X_later, R_later) - σ_α,disc(X, R),

        so that σ_α,disc + σ_α,alg = σ_α,disc(X_later), whose divergence is
        Π_P1 f_α ± λ'_h - r'_αh = Π_P1 f_α ± λh - ρ_α with ρ_α = r'_αh ∓ (λ'_h - λh)
        (- for α = 1); hence ∇·σ_α,alg = r_αh - r'_αh ± (λ'_h - λh) and the remainder
        η_rem = C_PF h_Ω (Σ_α μ_α^{-1} ‖ρ_α‖²)^{1/2}. Returns ((σ_1,alg, σ_2,alg), η_rem)."""
        from dolfinx import fem
        (now, _), (later, r_later) = self.sigma_disc(X, R), self.sigma_disc(X_later, R_later)
        alg = []
        for s_now, s_later in zip(now, later):
            a = fem.Function(s_now.function_space)
            a.x.array[:] = s_later.x.array - s_now.x.array
            alg.append(a)
        n = self.n
        lam, lam_later = (owned(Y)[2 * n:3 * n] for Y in (X, X_later))
        return tuple(alg), (self.remainder(r_later, lam_later - lam)
                            + self.defect_remainder(later))

    # ## Evaluation (§7)

    def _set_flux(self, targets, sources):
        """Copy the RT_1 Functions `sources` into the forms' coefficients `targets`: the dof
        arrays where the two spaces number the dofs alike (checked once per space: the same
        element and cell dofs), else by interpolation (exact between two RT_1 spaces)."""
        if targets is self._sigma and sources[0] is not targets[0]:   # drop what they held
            self._recent = [kept for kept in self._recent if kept[1][0][0] is not targets[0]]
        for target, source in zip(targets, sources):
            if target is source:
                continue
            if self._alike(source.function_space, target.function_space):
                target.x.array[:] = source.x.array
            else:
                target.interpolate(source)

    def _alike(self, V, W):
        key = (id(V), id(W))
        if key not in self._layouts:
            same = (V is W) or (
                V.ufl_element() == W.ufl_element()
                and V.dofmap.index_map.size_local == W.dofmap.index_map.size_local
                and V.dofmap.index_map.num_ghosts == W.dofmap.index_map.num_ghosts
                and np.array_equal(V.dofmap.list.array, W.dofmap.list.array))
            self._layouts[key] = (self.comm.allreduce(bool(same), op=MPI.LAND), V, W)
        return self._layouts[key][0]

    def evaluate(self, X, R=None, sigma_alg=None, eta_rem=None):
        """Every estimator at X (§7). R: the algebraic residual in the iterate layout (None:
        zero); sigma_alg: (σ_1,alg, σ_2,alg) RT_1 Functions, or None; eta_rem: the remainder
        the flux leaves (§6; module notes). Default: without σ_alg, the Poincaré–Friedrichs
        bound of the whole lifted residual, C_PF h_Ω (Σ_α μ_α^{-1} ‖r_αh‖²)^{1/2} (0 where
        R = 0), so that η is a guaranteed bound at every iterate; with σ_alg, 0 (the
        multilevel flux, whose divergence is r_αh exactly); `nu_flux` returns the ν flux's.
        σ_disc's measured divergence defect (`defect_remainder`) is added to either.

        Returns a dict: the global eta, eta_disc, eta_lin, eta_alg, eta_F, eta_osc, eta_C
        (Σ_C), eta_lin1, eta_lin2, eta_lin3, eta_rem, eta_1, and eta_K, the local
        distribution of §7 on the owned cells (in the mesh's cell order)."""
        sigma, r = self.sigma_disc(X, R)
        defect = self.defect_remainder(sigma)
        if eta_rem is None and sigma_alg is None and R is not None:
            # `remainder(r)`, integrated with the estimators (one assembly)
            self._set_rho(r)
            self._write(X)
            self._set_flux(self.sigma, sigma)
            q = self.cells_disc_rem.cells()
            return self._combine(q, (DISC1, DISC2), False, defect, rem=True)
        return self.assemble(X, sigma, sigma_alg, defect + (eta_rem or 0.0))

    def assemble(self, X, sigma, sigma_alg=None, eta_rem=0.0):
        """The estimators at X for the given σ_disc (and σ_alg): `evaluate` without the flux
        equilibration (module notes for eta_rem)."""
        self._write(X)
        self._set_flux(self.sigma, sigma)
        if sigma_alg is None:
            q = self.cells_disc.cells()
            flux = (DISC1, DISC2)
        else:
            self._set_flux(self.sigma_alg, sigma_alg)
            q = self.cells_alg.cells()
            flux = (FLUX1, FLUX2)
        return self._combine(q, flux, sigma_alg is not None, float(eta_rem))

    def _combine(self, q, flux, with_alg, eta_rem, rem=False):
        """The global values and η_K from the per-cell integrals q (§7): `flux` the columns of
        η_F,K,α²; with `rem`, η_rem from q's columns REM1, REM2 (as `remainder`) added to
        `eta_rem`. Column by
        column (views of q: no copy of it at the peak of an evaluation); the global sums in
        one reduction."""
        qt = q.T                                                        # (k, cells)
        o1, o2 = self.osc.T
        disc_K = [np.sqrt(np.maximum(qt[i], 0.0)) for i in (DISC1, DISC2)]   # η_disc,K,α
        flux_K = (disc_K if list(flux) == [DISC1, DISC2]
                  else [np.sqrt(np.maximum(qt[i], 0.0)) for i in flux])      # η_F,K,α
        eta_1_sq = (flux_K[0] + o1) ** 2 + (flux_K[1] + o2) ** 2        # η_1,K²
        sums = [eta_1_sq.sum(),
                ((disc_K[0] + o1) ** 2 + (disc_K[1] + o2) ** 2).sum(),  # η_disc's flux part²
                (flux_K[0] ** 2 + flux_K[1] ** 2).sum(),                # η_F²
                self._osc_sum]                                          # η_osc²
        del disc_K, flux_K                      # (one column at a time from here on)
        eta_C_K = qt[CONTACT]
        lin1_sq = np.maximum(qt[LIN1], 0.0)                             # η_lin1,K²
        lin3_sq = self.c_lambda ** 2 * np.maximum(qt[LAM_NEG], 0.0)     # η_lin3,K²
        sums += [c.sum() for c in (eta_C_K, lin1_sq, lin3_sq, qt[LAM_POS])]
        eta_1_sq += lin1_sq
        eta_1_sq += lin3_sq
        del lin1_sq, lin3_sq
        eta_1_sq += np.abs(eta_C_K)
        eta_K = np.sqrt(eta_1_sq, out=eta_1_sq)
        if with_alg:
            sums.append(np.maximum(qt[ALG1], 0.0).sum() + np.maximum(qt[ALG2], 0.0).sum())
        if rem:
            sums += [qt[REM1].sum(), qt[REM2].sum()]
        s = self.comm.allreduce(np.array(sums), op=MPI.SUM)
        if not np.all(np.isfinite(s)):      # the same on every process
            raise ValueError(f"the estimators overflow double precision (mu1 = {self.mu[0]:g}, "
                             f"mu2 = {self.mu[1]:g}): rescale the data; the solution scales "
                             f"with f / mu and g (theory §11)")
        if rem:
            eta_rem += float(self.cpf * np.sqrt(max(s[-2:].sum(), 0.0)))
        eta_1, disc_part, eta_F, eta_osc = np.sqrt(np.maximum(s[[0, 1, 2, 3]], 0.0))
        sum_C = float(s[4])
        lin = self._linearisation_parts(s[5], s[6], s[7])
        eta_lin1, eta_lin2, eta_lin3 = lin["eta_lin1"], lin["eta_lin2"], lin["eta_lin3"]
        alg_flux = np.sqrt(max(s[8], 0.0)) if with_alg else 0.0
        eta = np.sqrt((eta_1 + eta_rem + eta_lin1 + eta_lin3) ** 2 + eta_lin2 + max(0.0, sum_C))
        return {
            "eta": float(eta),
            "eta_disc": float(disc_part + np.sqrt(abs(sum_C))),
            "eta_alg": float(alg_flux + eta_rem),
            "eta_F": float(eta_F), "eta_osc": float(eta_osc), "eta_C": sum_C,
            "eta_rem": float(eta_rem), "eta_1": float(eta_1), "eta_K": eta_K, **lin,
        }
