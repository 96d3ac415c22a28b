"""Which iterates the adaptive method estimates, and how (§7, §8): `LevelEstimates`, the
`estimate(X, R, kind)` callback that `membranes.nonlinear.newton` calls on one mesh.

The bound of §7 holds at any iterate; what is scheduled here is only where it is computed. A
full estimate (the flux equilibration of §5 and the algebraic flux of §6) is made where a
stopping test of Algorithm 1 reads it and is likely to hold; elsewhere the cheap
linearisation estimate η_lin, and before the first full estimate on a mesh the gradient
recovery estimate η_rec, decide (docs/choices.md, "Which Newton iterates get the flux
equilibration"). The same signals tell Newton which steps are not expected to be the last, so
that their Krylov solves may stop at a forcing term (docs/choices.md, "Krylov depth of the
Newton steps that will not be the last").
"""

import time

from ..nonlinear.newton import linear_criterion

DEFAULT_GAMMA = 0.3
# the Newton test η_lin ≤ γ_lin η_disc is evaluated in full at X^k only where η_lin(X^k) ≤
# γ_lin GATE η_disc of the last full estimate on the mesh, or η_rec before it
# (`LevelEstimates`); None: always
GATE = 1.0
# before the first full estimate η_rec stands in for η_disc, which may exceed it: an iterate
# with η_lin within REC_MARGIN of the gate is estimated unless the last step's rate takes η_lin
# below the gate at the next step (`LevelEstimates._skip`)
REC_MARGIN = 2.0
# η_rec is made anew at a gate unless η_lin, forecast from the last two Newton iterates and
# then computed alone, lies above STALE · REC_MARGIN · the gate of the last η_rec on the mesh:
# the iterate is then skipped against that η_rec (`LevelEstimates._recovered`); None: η_rec
# at every gate
STALE = 4.0


class LevelEstimates:
    """The estimators of one mesh (§7) with the run's algebraic flux (§6), set up once: the
    `estimate(X, R, kind)` callback of Newton (membranes.nonlinear.newton). Only a run that
    estimates builds one.

    * 'multilevel': every iterate gets σ_alg with ∇·σ_alg = r_αh exactly (no remainder).
    * 'nu': an iterate is first estimated without algebraic flux, its whole lifted residual
      bounded by Poincaré–Friedrichs (η_rem; enough where the residual is at round-off). If
      that does not meet the linear criterion η_alg ≤ γ_alg max(η_disc, η_lin), the iterate
      handed over before in the same Newton step, X^{k,i-ν} (X^{k,0}, the iterate of the
      solver's initial guess, announced with kind 'step'), is estimated with the ν flux
      σ_disc(X^{k,i}) - σ_disc(X^{k,i-ν}) and its remainder, and returned marked
      `of_previous` (Newton accepts that iterate if the criterion holds on it). σ_disc of
      each iterate is solved once (Estimators keeps the last two).

    **Where the Newton test needs σ_disc.** At the end of a Newton step (kind 'newton') the test
    is η_lin ≤ γ_lin η_disc. η_lin needs no flux (`Estimators.linearisation`, one small
    assembly); η_disc does. Between Newton steps on one mesh η_disc barely moves (the
    discretisation error of iterates near the discrete solution), while η_lin falls
    superlinearly. So once a full estimate on the mesh has given η_disc, an iterate with η_lin >
    γ_lin · GATE · that η_disc (GATE = 1) is returned with η_lin only, marked `partial` and
    without a bound: its Newton test would hold only if η_disc grew in one step, and Newton goes
    on. Before the first full estimate on the mesh, the gradient recovery estimate η_rec
    (`Estimators.recovered`, two small assemblies) stands in for η_disc: both estimate the same
    discretisation error, but η_rec is no bound and η_disc may exceed it (several times on an
    anisotropic mesh: BENCHMARKS.md, "The Newton gates"). So within REC_MARGIN (2) of the gate
    an iterate is estimated in full, unless the rate of the last Newton step takes η_lin below
    the gate at the next step (`_skip`). An iterate clearly above the gate is skipped against
    the last η_rec on the mesh, with η_lin alone (`_recovered`, STALE). This is a schedule of
    the estimates, like ν for Krylov (§8): a wrong guess costs about one more Newton step, never
    the bound; the iterate Newton stops at is always estimated in full and certified. GATE = 1
    because a full estimate whose test fails is wasted, and on T_J it costs more than the Newton
    step that a skipped, passing test costs: estimating an iterate pays only if its test is
    likely to hold (docs/choices.md). `gate=None` estimates every Newton iterate in full, and so
    does kind 'stalled' (an iterate that its Newton step left unchanged: η_lin no longer falls,
    and η_rec may be far below η_disc where the mesh does not resolve the data, so the gate
    would skip it at every repetition).

    Each answer to kind 'newton' whose test fails says whether the next step is expected not
    to be the last either (`more_steps`, `_more_steps`): Newton then stops that step's Krylov
    solve at the forcing term ADAPTIVE_FORCING instead of solving it to the exact floor, and
    hands the iterate over as kind 'forced'. Where the gate skips it, it is answered as a
    'newton' iterate; otherwise its test may hold, and the answer None makes Newton finish
    the solve to the floor first (the iterate is then estimated as 'newton').

    `setups` (a membranes.app.setups.Setups): take the flux equilibration of the mesh from it,
    set up by an earlier solve on the same mesh, instead of setting one up; `setup_time` then
    counts only the estimators' own forms. (The data parts, σ_disc's loads and η_osc, are made
    at the first full evaluation either way: `membranes.estimation.estimators.Estimators`.)
    """

    def __init__(self, disc, alg_flux, hierarchy=None, gamma_alg=DEFAULT_GAMMA,
                 gamma_lin=DEFAULT_GAMMA, gate=GATE, setups=None):
        # (imported here: only a run that estimates builds one)
        from ..estimation.equilibration import FluxEquilibration
        from ..estimation.estimators import Estimators
        t = time.perf_counter()
        equilibration = setups.equilibration(disc) if setups is not None \
            else FluxEquilibration(disc.V, disc.dx_data)
        self.est = Estimators(disc, equilibration)
        self.multilevel = None
        if alg_flux == "multilevel":
            from ..estimation.multilevel import MultilevelFlux  # only a run that uses it
            self.multilevel = MultilevelFlux(disc, hierarchy, self.est.lifting)
        self.gamma_alg, self.gamma_lin, self.gate = gamma_alg, gamma_lin, gate
        self.eta_disc = None           # η_disc of the last full estimate on this mesh
        self.eta_rec = None            # η_rec of the last gate that made one on this mesh
        self.eta_lin = None            # η_lin of the last Newton iterate on this mesh
        self.before = None             # η_lin of the Newton iterate before that one
        self.pending = None            # ('nu') the iterate handed over last: (X, R) copies
        self.setup_time = time.perf_counter() - t
        self.time = 0.0
        self.count = 0

    def _skip(self, eta_lin, target, previous):
        """Whether the Newton test η_lin ≤ target is not worth a full estimate: it fails
        against the last η_disc on the mesh, or, with η_rec standing in (not a bound; η_disc
        may exceed it), η_lin is above REC_MARGIN · target, or it is within that margin but
        the rate of the last Newton step (from `previous`) takes it below target at the next."""
        if eta_lin <= target:
            return False
        if self.eta_disc is not None or eta_lin > REC_MARGIN * target:
            return True
        return self._forecast(eta_lin, previous) <= target    # (rate 1: never, η_lin > target)

    @staticmethod
    def _forecast(eta_lin, previous):
        """η_lin of the next Newton iterate, taken on at the last step's rate η_lin / `previous`
        (rate 1 without a previous η_lin on the mesh)."""
        return eta_lin * (eta_lin / previous) if previous else eta_lin

    def _recovered(self, X):
        """(η_rec, the η_lin parts at X) for a gate before the first full estimate on the mesh.
        η_rec, like η_disc, barely moves between Newton iterates near the discrete solution,
        but it does between those of a far initial guess (docs/choices.md). Where the last two
        η_lin forecast this iterate's above STALE · REC_MARGIN · the gate of the last η_rec,
        η_lin is computed alone (one small assembly instead of two); if it is indeed above, the
        iterate is skipped against that η_rec: only an η_rec STALE times larger would make its
        test worth a full estimate. Else η_rec is made anew with η_lin, as at the first gate
        (and after an η_rec of 0, against which every η_lin would be clearly above)."""
        if STALE is not None and self.eta_rec and self.eta_lin is not None:
            clear = STALE * REC_MARGIN * self.gamma_lin * self.gate * self.eta_rec
            if self._forecast(self.eta_lin, self.before) > clear:
                lin = self.est.linearisation(X)
                if lin["eta_lin"] > clear:
                    return self.eta_rec, lin
        self.eta_rec, lin = self.est.recovered(X, linearisation=True)
        return self.eta_rec, lin

    def _newton_lin(self, eta_lin):
        """Record η_lin of a Newton iterate (the last two forecast the next, `_recovered`)."""
        self.before, self.eta_lin = self.eta_lin, eta_lin

    @classmethod
    def _more_steps(cls, eta_lin, target, previous):
        """Whether the Newton step after an iterate whose test failed is expected not to be
        the last: the `_forecast` of η_lin stays above REC_MARGIN · target. Such a step's
        Krylov solve stops at the forcing term; if the gate then says its test may hold after
        all, the solve goes on to the exact floor (kind 'forced', membranes.nonlinear.newton),
        so a wrong guess costs only the gate."""
        return cls._forecast(eta_lin, previous) > REC_MARGIN * target

    def _keep(self, X, R):
        self._drop()
        self.pending = (X.copy(), R.copy())

    def _drop(self):
        if self.pending is not None:
            for v in self.pending:
                v.destroy()
            self.pending = None

    def _evaluate(self, X, R):
        if R is not None and self.multilevel is not None:
            rh = self.est.lifted(R)
            sigma_alg, defects = [], []
            for r in rh:                 # (each σ_alg's divergence defect, to round-off, §6)
                sigma_alg.append(self.multilevel.sigma(r))
                defects.append(self.multilevel.defect_sq)
            return self.est.evaluate(X, R, sigma_alg=sigma_alg,
                                     eta_rem=self.est.remainder_of(defects))
        return self.est.evaluate(X, R)

    def __call__(self, X, R, kind=None):
        t = time.perf_counter()
        try:
            if kind == "step":                 # X^{k,0} of a new Newton step
                if self.multilevel is None:
                    self._keep(X, R)
                return None
            previous = self.eta_lin
            if kind == "forced" and self.gate is None:
                return None                      # finish the solve: every test in full
            if kind in ("newton", "forced") and self.gate is not None:
                if self.eta_disc is not None:
                    lin, reference = self.est.linearisation(X), self.eta_disc
                else:                            # η_rec stands in (`_recovered`)
                    reference, lin = self._recovered(X)
                target = self.gamma_lin * self.gate * reference
                if self._skip(lin["eta_lin"], target, previous):
                    self._newton_lin(lin["eta_lin"])
                    lin["partial"] = True
                    lin["more_steps"] = self._more_steps(lin["eta_lin"], target, previous)
                    return lin
                if kind == "forced":             # its test may hold: finish the solve
                    return None
            out = self._evaluate(X, R)
            if kind in ("newton", "stalled"):
                self._newton_lin(out["eta_lin"])
                out["more_steps"] = self._more_steps(out["eta_lin"],
                                                     self.gamma_lin * out["eta_disc"], previous)
            if kind == "krylov" and self.multilevel is None:
                if not linear_criterion(out, self.gamma_alg) and self.pending is not None:
                    (Xp, Rp), current = self.pending, (X, R)
                    sigma_alg, eta_rem = self.est.nu_flux(Xp, Rp, X, R)
                    out = self.est.evaluate(Xp, Rp, sigma_alg=sigma_alg, eta_rem=eta_rem)
                    out["of_previous"] = True
                    self._keep(*current)
                else:
                    self._keep(X, R)
            out["bound"] = True
            self.eta_disc = out["eta_disc"]
            self.count += 1
            return out
        finally:
            self.time += time.perf_counter() - t
