"""What `solve` returns: the iterate, its history, its certified bound and the figures of a run.

Every process holds its own part of the iterate (the owned dofs of the distributed mesh) and
the same history, counts and estimates (MPI reductions), so every process returns an equal
`Solution`; `summary()` is the content of summary.json (docs/outputs.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
from dolfinx.fem import Function
from mpi4py import MPI
from petsc4py import PETSc

from ..fem.discretisation import Discretisation
from ..fem.meshes import mesh_size
from ..model.problem import Problem
from .versions import software

# the estimators of an iterate as they go into records and summary.json (§7)
ESTIMATOR_COLUMNS = ("eta", "eta_disc", "eta_lin", "eta_alg", "eta_F", "eta_osc", "eta_C",
                     "eta_lin1", "eta_lin2", "eta_lin3", "eta_rem")


def record_of_X(history):
    """The record of the returned iterate X: the last that is not a Krylov iterate (a solve
    that failed leaves the Krylov records of the step it did not finish after it)."""
    return next(rec for rec in reversed(history) if rec["kind"] != "krylov")


@dataclass
class Solution:
    problem: Problem
    # the discretisation of the computational mesh T_J (repr: not it nor the history, whose
    # arrays and records made a Solution in a notebook print some 1e5 characters)
    disc: Discretisation = field(repr=False)
    X: PETSc.Vec                  # iterate layout [u1 | u2 | λ] (owned dofs)
    converged: bool
    reason: str
    newton_iterations: int
    linear_iterations: int
    wall_time_s: float
    history: list[dict[str, Any]] = field(repr=False)
    options: dict[str, Any]
    energy_error: Optional[float] = None
    energy_error_kind: Optional[str] = None  # which error energy_error is (see `summary`)
    functions: list[Function] = field(default_factory=list)
    eta_K: Optional[np.ndarray] = None      # local distribution η_K over the owned cells (§7)
    estimates: Optional[dict[str, Any]] = None        # the estimators at X, where estimated
    estimator_times: tuple[Optional[float], Optional[float]] = (None, None)  # set-up, evals [s]
    per_level: list[dict[str, Any]] = field(default_factory=list)

    @property
    def comm(self) -> MPI.Comm:
        return self.disc.comm

    @property
    def u1(self) -> Function:
        return self.functions[0]

    @property
    def u2(self) -> Function:
        return self.functions[1]

    @property
    def lam(self) -> Function:
        return self.functions[2]

    @property
    def final_record(self) -> dict[str, Any]:
        """The history record of X (`record_of_X`)."""
        return record_of_X(self.history)

    def complementarity_violation(self) -> float:
        """Largest violation of w = u1 - u2 ≥ 0, λ ≥ 0, λ w = 0 at interior vertices, relative
        to the data scale (§11): w against u_scale = max(u_data, |u|∞), λ against
        max(λ_data, |λ|∞, λ_u), λ_u = u_scale / ((1/μ1 + 1/μ2) (C_PF h_Ω)²) the pressure
        that moves the gap by u_scale (u_data's relation to the loads, read backwards). Without
        λ_u, zero loads (λ_data = 0, solution (g, 0, 0)) measured λ's round-off against itself:
        a violation of 1 where Newton from a zero guess left λ at ±1e-18. Collective."""
        d = self.disc
        u1, u2, lam = d.split(self.X)
        inner = d.interior
        w, lam = (u1 - u2)[inner], lam[inner]
        u_data, lam_data = d.data_scales()
        comm = d.comm

        def gmax(a):
            return comm.allreduce(float(np.max(a, initial=0.0)), op=MPI.MAX)

        u_scale = max(u_data, gmax(np.abs(u1)), gmax(np.abs(u2)))
        lam_u = u_scale / ((1.0 / d.mu1 + 1.0 / d.mu2) * d.poincare ** 2)
        lam_scale = max(lam_data, gmax(np.abs(lam)), lam_u, np.finfo(float).tiny)
        # (+ 0.0: a max over -w = -0.0 printed "-0.0" in summary.json)
        return float(max(gmax(-w) / u_scale, gmax(-lam) / lam_scale,
                         gmax(np.abs(w * lam)) / (u_scale * lam_scale))) + 0.0

    def summary(self) -> dict[str, Any]:
        """The keys of summary.json (docs/outputs.md). Collective, as
        `complementarity_violation` is: call it on every process (called on process 0 alone,
        under `if rank == 0`, it waits for the others for ever), then print on one."""
        p = self.problem
        mesh = p.mesh
        est = self.estimates or {}
        eta, err = est.get("eta"), self.energy_error
        out = {
            "scene": p.name,
            "description": p.description,
            "n_vertices": int(mesh.topology.index_map(0).size_global),
            "n_cells": int(mesh.topology.index_map(2).size_global),
            "h": mesh_size(mesh),
            "h_coarse": mesh_size(p.hierarchy.meshes[0]),
            "levels": p.levels,
            "mu1": p.mu1, "mu2": p.mu2, "g": p.g,
            "processes": self.comm.size,
            **self.options,
            "per_level": self.per_level,
            "converged": self.converged,
            "reason": self.reason,
            "newton_iterations": self.newton_iterations,
            "linear_iterations": self.linear_iterations,
            "wall_time_s": self.wall_time_s,
            "final_residual": self.final_record["residual"],
            "complementarity_violation": self.complementarity_violation(),
            "energy_error": err,
            "energy_error_kind": self.energy_error_kind,
        }
        out.update({k: est.get(k) for k in ESTIMATOR_COLUMNS})
        out["bound_guaranteed"] = est.get("bound")
        out["effectivity"] = eta / err if eta is not None and err else None
        out["estimator_setup_s"], out["estimator_time_s"] = self.estimator_times
        out["software"] = software()
        return out
