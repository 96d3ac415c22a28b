"""GMRES inside semismooth Newton (membranes.krylov, DESIGN §3, §4, §8): exact and inexact
variants against MUMPS, the recorded Krylov iterates and their residuals, PETSc options,
non-convergence, and the CLI's new options.

"Same discrete solution" is measured as ‖X - X_ref‖/‖X_ref‖ over all 3N unknowns and as the
relative energy norm of the membrane difference. λ is the most sensitive field (a residual R
in the linear rows moves λ_l by about R_l / D_l, D_l ~ h²): its max-norm difference is up to
ten times the global one (2.4e-8 for inexact fb on the disk, h = 0.05).
"""

import csv
import json

import numpy as np
import pytest
import scipy.sparse as sp
from petsc4py import PETSc

from membranes import solve
from membranes import krylov as krylov_module
from membranes import newton_system as ns
from membranes.cli import main
from membranes.krylov import DEFAULT_OPTIONS, Krylov, parse_petsc_options, with_diagonal
from membranes.linear_solve import petsc_matrix, written_csr
from membranes.newton import EXACT_LINEAR_TOL, linear_step, semismooth_newton

from .conftest import cli_bad_input, scene, solved_with

H = 0.05
CASES = [("min", "full"), ("min", "eliminated"), ("fb", "full"), ("fb", "eliminated")]


def _differences(run, ref):
    """Relative 2-norm difference of X and relative energy-norm difference of (u1, u2)."""
    n, S = ref.disc.n, ref.disc.S1
    du = [a - b for a, b in zip(ns.split(run.X, n)[:2], ns.split(ref.X, n)[:2])]
    u = ns.split(ref.X, n)[:2]
    energy = np.sqrt(sum(d @ (S @ d) for d in du) / sum(v @ (S @ v) for v in u))
    return np.linalg.norm(run.X - ref.X) / np.linalg.norm(ref.X), energy


@pytest.mark.parametrize("cfun,system", CASES)
def test_exact_gmres_matches_mumps(cfun, system):
    ref = solved_with("disk", H, cfun=cfun, system=system, linear_solver="direct")
    run = solved_with("disk", H, cfun=cfun, system=system)
    assert run.converged and ref.converged, run.reason
    assert run.newton_iterations == ref.newton_iterations
    assert max(_differences(run, ref)) <= 1e-9
    newton = [rec for rec in run.history if rec["kind"] == "newton"]
    # a step the Fischer–Burmeister line search damped (step_length < 1) stops short of the
    # linear solution on purpose; every full step is an exact solve
    assert all(rec["alg_residual"] <= EXACT_LINEAR_TOL for rec in newton
               if rec["step_length"] in (None, 1.0))
    assert run.linear_iterations == sum(rec["linear_it"] for rec in newton)
    assert run.linear_iterations > 10 * run.newton_iterations      # Krylov work is counted


@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_inexact_reaches_the_discrete_solution(cfun):
    ref = solved_with("disk", H, cfun=cfun, linear_solver="direct")
    run = solved_with("disk", H, cfun=cfun, newton="inexact")
    assert run.converged, run.reason
    assert run.final_record["residual"] <= 1e-10
    assert max(_differences(run, ref)) <= 1e-8
    iterates = [rec for rec in run.history if rec["kind"] != "krylov"]
    for before, after in zip(iterates, iterates[1:]):
        # the stopping test of the inexact variant, made every ν = 10 Krylov steps
        assert after["alg_residual"] <= before["residual"]
        assert after["linear_it"] % 10 == 0


def _recorded(cfun, system, nu, variant="exact"):
    """Run semismooth Newton on disk h = 0.1, keeping X and R of every recorded iterate."""
    rows = ns.linear_rows(solved_with("disk", 0.1, linear_solver="direct").disc)
    seen = []
    result = semismooth_newton(rows, 0.05, cfun=cfun, system=system, variant=variant,
                               krylov=Krylov(nu=nu),
                               monitor=lambda rec, X, R: seen.append((rec, X.copy(),
                                                                      None if R is None
                                                                      else R.copy())))
    assert result.converged, result.reason
    return rows, result, seen


@pytest.mark.parametrize("cfun,system", CASES)
def test_recorded_residuals_are_the_true_algebraic_residuals(cfun, system):
    """R handed to the monitor is B - A X, recomputed here from the previous Newton iterate."""
    rows, result, seen = _recorded(cfun, system, nu=7)
    previous = None
    for rec, X, R in seen:
        if rec["kind"] == "initial":
            assert R is None and rec["alg_residual"] is None
        else:
            # the system of the step: FB linearised at `previous` or at its projection
            # (newton: active-set steps)
            A, B = ns.full_system(rows, *ns.complementarity_rows(
                rows, cfun, previous, rec["linearised_at"] == "projection"))
            scale = np.linalg.norm(B)
            assert np.linalg.norm(B - A @ X - R) <= 1e-12 * scale
            assert rec["alg_residual"] == pytest.approx(np.linalg.norm(R) / scale, rel=1e-12)
            if system == "eliminated" and rec["step_length"] in (None, 1.0):
                assert np.all(R[2 * rows.n:] == 0)   # damped: (1 - t) R_lin(previous)
        assert rec["residual"] == pytest.approx(
            np.linalg.norm(ns.nonlinear_residual(rows, cfun, X)) / rows.norm_F, rel=1e-12)
        if rec["kind"] != "krylov":
            previous = X
    assert [rec for rec, _, _ in seen] == result.history


@pytest.mark.parametrize("nu", [1, 7])
def test_krylov_rows_every_nu_iterations(nu):
    _, result, _ = _recorded("min", "full", nu=nu)
    history, done = result.history, 0
    steps = [rec for rec in history if rec["kind"] == "newton"]
    for step in steps:
        rows = [rec for rec in history if rec["newton_it"] == step["newton_it"]]
        krylov = [rec for rec in rows if rec["kind"] == "krylov"]
        total = step["linear_it"]
        assert [rec["linear_it"] for rec in krylov] == list(range(nu, total, nu))
        assert all(rec["cumulative_linear_its"] == done + rec["linear_it"] for rec in rows)
        assert rows[-1] is step                 # the Newton iterate closes its step
        done += total
        if nu == 1:
            # each iteration PETSc counts produced its own iterate; GMRES's true residual
            # does not increase
            residuals = [rec["alg_residual"] for rec in krylov + [step]]
            assert all(b <= a + 1e-14 for a, b in zip(residuals, residuals[1:]))
            assert len(set(residuals)) == len(residuals)
    assert result.linear_iterations == done == history[-1]["cumulative_linear_its"]
    times = [rec["wall_time_s"] for rec in history]
    assert times == sorted(times)


@pytest.mark.parametrize("name,cfun", [("disk", "min"), ("disk", "fb"), ("square", "min"),
                                       ("square", "fb")])
def test_eliminated_step_starts_from_the_previous_iterate(name, cfun):
    """The guess keeps X^{k-1}'s λ where λ stays an unknown and its u1, u2 where u2 does; where
    u2 is eliminated it keeps the mean (μ1 u1 + μ2 u2)/(μ1 + μ2) (round-off) and λ, and its u2
    is the one the complementarity row gives (disk: μ1 = μ2; square: μ1 = 1, μ2 = 2)."""
    rows = ns.linear_rows(solved_with(name, 0.1, linear_solver="direct").disc)
    mu1, mu2 = (solved_with(name, 0.1, linear_solver="direct").problem.mu1,
                solved_with(name, 0.1, linear_solver="direct").problem.mu2)
    n = rows.n
    X = np.random.default_rng(1).uniform(-1, 1, 3 * n)
    step = linear_step(rows, cfun, "eliminated", X)
    alpha, beta, B3 = ns.complementarity_rows(rows, cfun, X)
    lam_out = np.abs(beta) >= rows.kappa * np.abs(alpha)
    (u1, u2, lam), (g1, g2, glam) = ns.split(X, n), ns.split(step.expand(step.guess), n)
    assert 0 < lam_out.sum() < n
    assert np.all(g1[lam_out] == u1[lam_out]) and np.all(g2[lam_out] == u2[lam_out])
    out = ~lam_out
    assert np.all(glam[out] == lam[out])
    mean = (mu1 * u1 + mu2 * u2) / (mu1 + mu2)
    assert np.allclose(((mu1 * g1 + mu2 * g2) / (mu1 + mu2))[out], mean[out], rtol=0,
                       atol=1e-15 * np.abs(X).max() * 4)
    assert np.allclose((alpha * (g1 - g2) + beta * glam)[out], B3[out], rtol=0,
                       atol=1e-15 * np.abs(X).max() * 8)


def test_petsc_options_override_and_do_not_leak():
    ilu = solved_with("disk", 0.1)
    jacobi = solve(scene("disk", 0.1), petsc_options={"pc_type": "jacobi"})
    assert jacobi.converged and jacobi.newton_iterations == ilu.newton_iterations
    assert jacobi.linear_iterations > 2 * ilu.linear_iterations
    assert jacobi.summary()["petsc_options"] == {**DEFAULT_OPTIONS, "pc_type": "jacobi"}
    assert not [k for k in PETSc.Options().getAll() if k.startswith("membranes_")]
    again = solve(scene("disk", 0.1))
    assert again.linear_iterations == ilu.linear_iterations


@pytest.mark.parametrize("options", [{"ksp_type": "bogus"}, {"pc_type": "nonsense"},
                                     {"ksp_rtol": 1e-3}, {"-ksp_max_it": 5},
                                     {"ksp_gmres_restart": [30]}])
def test_bad_petsc_options(options):
    with pytest.raises(ValueError):
        solve(scene("disk", 0.3), petsc_options=options)


@pytest.mark.parametrize("kwargs", [{"nu": 0}, {"nu": 2.5}, {"max_linear_its": 0},
                                    {"newton": "inexact", "linear_solver": "direct"},
                                    {"linear_solver": "direct", "nu": 5},
                                    {"linear_solver": "direct", "petsc_options": {}}])
def test_bad_krylov_arguments(kwargs):
    with pytest.raises(ValueError):
        solve(scene("disk", 0.3), **kwargs)


def test_linear_solver_failure_is_reported():
    run = solve(scene("disk", 0.1), max_linear_its=5)
    assert not run.converged
    assert "Newton step 1" in run.reason and "DIVERGED_MAX_IT" in run.reason
    assert run.newton_iterations == 0 and run.linear_iterations == 5
    assert run.X is not None and run.final_record["kind"] == "initial"


def test_matrix_builders():
    """with_diagonal stores every diagonal entry (a zero where A has none) and changes no value;
    petsc_matrix gives PETSc the same matrix, with each row's column indices sorted (as AIJ
    wants), whatever their order in A."""
    rng = np.random.default_rng(1)
    A = sp.random(40, 40, density=0.15, format="csr", random_state=2)
    diagonal = np.where(rng.random(40) < 0.5, 1.0 + rng.random(40), 0.0)   # half of it missing
    A = sp.csr_matrix(A - sp.diags(A.diagonal()) + sp.diags(diagonal))
    A.eliminate_zeros()
    assert 0 < (A.diagonal() == 0).sum() < 40
    D = with_diagonal(A)
    C = D.tocoo()
    assert np.array_equal(np.sort(C.row[C.row == C.col]), np.arange(40))
    assert np.array_equal(D.toarray(), A.toarray())
    unsorted = A.copy()
    for i in range(40):                     # reverse each row's entries
        a, b = unsorted.indptr[i], unsorted.indptr[i + 1]
        unsorted.indices[a:b] = unsorted.indices[a:b][::-1].copy()
        unsorted.data[a:b] = unsorted.data[a:b][::-1].copy()
    assert np.array_equal(unsorted.toarray(), A.toarray())
    M = petsc_matrix(unsorted)
    indptr, indices, data = M.getValuesCSR()
    assert all(np.all(np.diff(indices[indptr[i]:indptr[i + 1]]) > 0) for i in range(40))
    assert np.array_equal(sp.csr_matrix((data, indices, indptr), shape=A.shape).toarray(),
                          A.toarray())
    M.destroy()


def test_written_csr_holds_its_buffers():
    """written_csr: the matrix of the rows written into longer buffers, on the buffers
    themselves (shrunk to the entries written, no copy), and so are the matrices scipy makes
    of it (a view of a prefix shorter than half its buffer would be copied by each)."""
    A = sp.random(50, 60, density=0.1, format="csr", random_state=3)
    A.sort_indices()
    bound = 4 * A.nnz                               # the written entries: a quarter
    indices, data = np.empty(bound, dtype=np.int32), np.empty(bound)
    indices[:A.nnz], data[:A.nnz] = A.indices, A.data
    address = data.ctypes.data
    W = written_csr(A.indptr.astype(np.int64), indices, data, A.shape)
    assert np.array_equal(W.toarray(), A.toarray())
    assert data.size == indices.size == A.nnz
    for M in (W, sp.csr_matrix(W)):
        assert np.shares_memory(M.data, data) and np.shares_memory(M.indices, indices)
        assert M.data.ctypes.data == address


def test_parse_petsc_options():
    assert parse_petsc_options("-ksp_type gmres -ksp_monitor -pc_factor_shift_amount -1e-3 "
                               "-pc_type ilu") == \
        {"ksp_type": "gmres", "ksp_monitor": None, "pc_factor_shift_amount": "-1e-3",
         "pc_type": "ilu"}
    assert parse_petsc_options("") == {}
    for bad in ("gmres", "-ksp_type gmres ilu", '-pc_type "ilu'):
        with pytest.raises(ValueError):
            parse_petsc_options(bad)


def test_cli_writes_krylov_rows_and_summary(tmp_path):
    out = tmp_path / "out"
    assert main(["solve", "--h", "0.1", "--nu", "5", "--system", "eliminated",
                 "--petsc-options", "-ksp_gmres_restart 50", "--quiet", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["linear_solver"] == "gmres" and summary["nu"] == 5
    assert summary["petsc_options"]["ksp_gmres_restart"] == "50"
    with open(out / "history.csv") as f:
        rows = list(csv.DictReader(f))
    assert {r["kind"] for r in rows} == {"initial", "krylov", "newton"}
    assert rows[0]["alg_residual"] == ""
    assert all(int(r["linear_it"]) % 5 == 0 for r in rows if r["kind"] == "krylov")
    assert int(rows[-1]["cumulative_linear_its"]) == summary["linear_iterations"]


CLI_CASES = {
    "nu zero": ["--nu", "0"],
    "nu not an integer": ["--nu", "1.5"],
    "max linear its negative": ["--max-linear-its", "-3"],
    "unknown newton": ["--newton", "sloppy"],
    "unknown linear solver": ["--linear-solver", "magic"],
    "inexact with direct": ["--newton", "inexact", "--linear-solver", "direct"],
    "nu with direct": ["--linear-solver", "direct", "--nu", "5"],
    "petsc options with direct": ["--linear-solver", "direct", "--petsc-options", "-pc_type lu"],
    "bogus ksp type": ["--petsc-options", "-ksp_type bogus"],
    "reserved option": ["--petsc-options", "-ksp_rtol 1e-3"],
    "value without option": ["--petsc-options", "gmres"],
    "unbalanced quote": ["--petsc-options", "-pc_type 'ilu"],
}


@pytest.mark.parametrize("case", sorted(CLI_CASES))
def test_cli_bad_krylov_options(case, tmp_path, capsys):
    cli_bad_input(CLI_CASES[case], tmp_path / "out", capsys)


@pytest.mark.parametrize("cancel_at,its", [(1, 0), (2, 0), (3, 1), (5, 3)])
def test_cancel_stops_the_solve_at_once(cancel_at, its, monkeypatch):
    """`cancel` (a step computed ahead, dropped: membranes.newton) is asked before the
    preconditioner is set up (call 1), before the first iteration (call 2) and after every
    iteration (call 2 + i after iteration i): the solve stops at the first true answer with
    that many iterations, and returns its iterate with the true residual b - A x (round-off);
    call 1 returns the guess without a preconditioner."""
    rows = ns.linear_rows(solved_with("disk", 0.1, linear_solver="direct").disc)
    step = linear_step(rows, "min", "eliminated", ns.initial_guess(rows, 0.1))
    calls, installed = [], []

    def cancel():
        calls.append(len(calls) + 1)
        return len(calls) >= cancel_at
    install = krylov_module._install

    def spy(*args):
        installed.append(True)
        return install(*args)
    krylov = Krylov({"pc_type": "vertex_amg"})     # (checks its options with a 2 x 2 install)
    monkeypatch.setattr(krylov_module, "_install", spy)
    x, r, done = krylov.solve(step.A, step.b, step.guess, 1e-14, step.norm_B, cancel=cancel)
    assert done == its and calls[-1] == cancel_at
    assert np.linalg.norm(r - (step.b - step.A @ x)) <= 1e-12 * step.norm_B
    if its == 0:
        assert np.array_equal(x, step.guess)
    assert installed == ([] if cancel_at == 1 else [True])
