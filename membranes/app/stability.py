"""The stability matrix of §11: `membranes stability --out DIR`.

Every case below is solved by every method: both C-functions (min, Fischer–Burmeister) with
exact Newton and MUMPS (`solver='direct'`), and exact, inexact and adaptive inexact Newton
with the paper's solver (`'paper'`: GMRES + ILU(0) on the full system) and with the fast one
(`'amg'`: FGMRES + mean/gap BoomerAMG on the eliminated system), at most MAX_LINEAR_ITS
Krylov steps per Newton step. A method is named C-function/variant/solver. Every case but
the nested ones is a single mesh (no hierarchy), so its runs are not nested.

What is measured, one row per run (``stability.csv``, ``stability.md``): whether it converged
(the driver's verdict, and no NaN or infinity in the iterate or the history), Newton and
Krylov steps, the final relative residual ‖W R_lin‖/‖W F‖ (rows weighted by 1/μ_α), the
complementarity violation relative to the data's sizes
(`Solution.complementarity_violation`), the scale defect where the case is a scaled copy of
another, the energy error, η and the effectivity η/|||u - u_h||| where the scene knows its
exact solution (measured on the computational polygon: `energy_error_kind`), whether η is a
guaranteed bound, and the wall time of `solve`. An exception inside a run is a failed run
with the exception as its reason. The adaptive variant stops at the discretisation error, so
its residual and complementarity violation are not at round-off, by design.

The cases (`CASES`; h is the gmsh size of the disk meshes, DEFAULT_H by default):

* stiffness — μ1/μ2 ∈ {1e-6, 1e-3, 1, 1e3, 1e6} (μ2 = 1): the radial scene with contact disk
  r ≤ 1/2 (`scenes.radial`, exact solution);
* gap — g ∈ {1e-12, 1e-6, 1e3} under the fixed load f1 = -1, f2 = 0 on the unit disk (user
  data: from contact almost everywhere to no contact at all; no exact solution);
* scaling — the μ1/μ2 = 1 case with f1, f2, g multiplied by 1e-8 and 1e8 (the radial loads
  are proportional to g): u1, u2, λ scale by the same factor s; the defect is the largest over
  u1, u2, λ of ‖X_s/s - X‖∞/‖X‖∞ against the same method on the unscaled case, and the counts
  are compared;
* contact — no contact, grazing contact (w and λ vanish together at the origin:
  Fischer–Burmeister's kink) and near-total contact (r ≤ 0.95), radial scenes;
* mesh — the square scene (exact solution) on an anisotropic mesh (4 × 400 rectangles, cell
  aspect ratio 100), a graded one ((x, y) ↦ (x³, y³) on 16 × 16) and one of 18 cells (3 × 3),
  from `membranes.fem.meshes.structured_square`;
* initial guess — the μ1/μ2 = 1 case from X⁰ = 0 and from a far-off X⁰ violating every
  constraint: u1 = -1e3 u_data, u2 = 1e3 u_data, λ = -1e3 max(λ_data, 1)
  (`Discretisation.data_scales`);
* nested — the cases of `NESTED_CASES` on a hierarchy T_0 … T_2 with T_0 at size 2h (T_2
  twice as fine as their single meshes), run as the product runs by default: nested
  iteration, the coarse levels by inexact Newton at a forcing term (membranes.app.driver),
  the initial guess (if any) on T_0. T_0 at 2h rather than 4h: the coarser T_0 hid the
  drift the forcing safeguard of membranes.nonlinear.newton guards against (BENCHMARKS.md,
  "Tried and dropped").

Exit code 0 when every run converged, EXIT_NOT_CONVERGED otherwise (the files are written in
any case, with the reasons); bad input (h, also one at which a case's mesh would not fit in
memory, `check_sizes`; --out, unknown case names) raises ValueError before any run.
"""

import csv
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from mpi4py import MPI

from . import interrupts
from .report import PARALLEL_COUNTS
from .versions import one_line, software

METHODS = tuple((cfun, newton, solver) for cfun in ("min", "fb")
                for newton, solver in (("exact", "direct"), ("exact", "paper"),
                                       ("inexact", "paper"), ("adaptive", "paper"),
                                       ("exact", "amg"), ("inexact", "amg"),
                                       ("adaptive", "amg")))
MAX_LINEAR_ITS = 2000     # per Newton step: bounds the time a stagnating Krylov solve may take
COLUMNS = ("case", "class", "method", "converged", "newton_iterations", "linear_iterations",
           "final_residual", "complementarity_violation", "scale_defect", "same_counts",
           "effectivity", "energy_error", "eta", "bound_guaranteed", "wall_time_s",
           "description", "reason")
DEFAULT_H = 0.1
NOT_ROBUST = 3.0          # effectivities above this are reported as not robust


def method_name(cfun, newton, solver):
    return f"{cfun}/{newton}/{solver}"


def far_off_guess(disc):
    """X⁰ violating every constraint, three orders of magnitude off the data's sizes."""
    u_data, lam_data = disc.data_scales()
    n = disc.n
    X = disc.vector3()
    X.array[:n] = -1e3 * u_data
    X.array[n:2 * n] = 1e3 * u_data
    X.array[2 * n:] = -1e3 * max(lam_data, 1.0)
    return X


@dataclass
class Case:
    name: str
    klass: str
    description: str
    build: Callable            # (h, levels) -> Problem
    initial_guess: object = None
    scaled_from: str = None    # name of the case this one is a scaled copy of ...
    factor: float = None       # ... with f1, f2, g multiplied by `factor`
    levels: int = 0            # refinements of T_0 (then at size 2h): nested runs


def _radial(**kwargs):
    def build(h, levels=0):
        from ..model import scenes
        return scenes.radial(h=h, levels=levels, **kwargs)
    build.domain = "disk"        # meshed at size h (`check_sizes`)
    return build


def _user(**kwargs):
    def build(h, levels=0):
        from ..model import scenes
        return scenes.user(h=h, levels=levels, **kwargs)
    build.domain = "disk"        # meshed at size h (`check_sizes`)
    return build


def _square(nx, ny, grading=1.0):
    def build(h, levels=0):
        from ..fem.meshes import structured_square
        from ..model import scenes
        return scenes.square(mesh=structured_square(nx, ny, grading), levels=levels)
    return build


NESTED = 2               # refinements of the nested cases' hierarchies
NESTED_CASES = ("mu_ratio_1e-06", "mu_ratio_1e+06", "g_1e-12", "grazing", "near_total",
                "far_guess")


def _cases():
    out = []
    for r in (1e-6, 1e-3, 1.0, 1e3, 1e6):
        out.append(Case(f"mu_ratio_{r:g}", "stiffness", f"radial, contact r <= 0.5, mu1 = {r:g},"
                        f" mu2 = 1", _radial(rho=0.5, mu1=r, mu2=1.0)))
    for g in (1e-12, 1e-6, 1e3):
        out.append(Case(f"g_{g:g}", "gap", f"unit disk, f1 = -1, f2 = 0, g = {g:g}",
                        _user(g=g, f1="-1", f2="0", domain="disk")))
    for s in (1e-8, 1e8):
        out.append(Case(f"scaled_{s:g}", "scaling", f"mu_ratio_1 with f1, f2, g times {s:g}",
                        _radial(rho=0.5, g=0.05 * s), scaled_from="mu_ratio_1", factor=s))
    out += [Case("no_contact", "contact", "radial, no contact", _radial(contact=False)),
            Case("grazing", "contact", "radial, grazing contact at the origin",
                 _radial(rho=0.0)),
            Case("near_total", "contact", "radial, contact r <= 0.95", _radial(rho=0.95)),
            Case("anisotropic", "mesh", "square scene, 4 x 400 rectangles (aspect ratio 100)",
                 _square(4, 400)),
            Case("graded", "mesh", "square scene, 16 x 16 graded by (x, y) -> (x^3, y^3)",
                 _square(16, 16, 3.0)),
            Case("tiny", "mesh", "square scene, 3 x 3 rectangles (18 cells)", _square(3, 3)),
            Case("zero_guess", "initial guess", "mu_ratio_1 from X0 = 0",
                 _radial(rho=0.5), initial_guess="zero"),
            Case("far_guess", "initial guess", "mu_ratio_1 from u1 = -1e3 u_data, u2 = 1e3 "
                 "u_data, lam = -1e3 lam_data", _radial(rho=0.5), initial_guess=far_off_guess)]
    out += [Case(f"nested_{c.name}", "nested", f"{c.description}; nested on T_0 … T_{NESTED}",
                 c.build, c.initial_guess, levels=NESTED)
            for c in out if c.name in NESTED_CASES]
    return out


CASES = _cases()
CASE_NAMES = tuple(c.name for c in CASES)


def select(names=None):
    """The cases called `names` (all by default), with the cases they are scaled copies of;
    ValueError for an unknown name or one given twice (as for options given twice)."""
    if names is None:
        return list(CASES)
    unknown = [n for n in names if n not in CASE_NAMES]
    if unknown:
        raise ValueError(f"unknown stability case {unknown[0]!r} (choose from: "
                         f"{', '.join(CASE_NAMES)})")
    twice = [n for i, n in enumerate(names) if n in names[:i]]
    if twice:
        raise ValueError(f"stability case {twice[0]!r} given twice")
    wanted = set(names) | {c.scaled_from for c in CASES if c.name in names and c.scaled_from}
    return [c for c in CASES if c.name in wanted]


def check_sizes(cases, h, comm, methods=METHODS):
    """Refuse, before any run, a case whose disk mesh would not fit in memory for the
    heaviest of `methods` (`report.check_memory`): a late case must not fail after the
    earlier ones have run, and a run refused by its own check is a failed row (`run_case`),
    not a refusal."""
    from .report import check_memory
    for case in cases:
        domain = getattr(case.build, "domain", None)
        if domain is not None:
            check_memory(h * 2 if case.levels else h, case.levels, domain, comm,
                         dict.fromkeys(m[2] for m in methods))


def check_h(h):
    if isinstance(h, bool) or not isinstance(h, (int, float)) or not math.isfinite(h) \
            or h <= 0:
        raise ValueError(f"h must be a positive finite number, got {h}")
    return float(h)


# ## Runs

def finite(sol):
    """No NaN or infinity in the iterate nor in any recorded number (collective)."""
    ok = bool(np.all(np.isfinite(sol.X.array_r))) and all(
        not (isinstance(v, float) and not math.isfinite(v))
        for rec in sol.history for v in rec.values())
    return sol.comm.allreduce(ok, op=MPI.LAND)


def run_case(case, h=DEFAULT_H, methods=METHODS, say=lambda line: None):
    """Solve `case` with every method: {method name: Solution, or the exception raised}."""
    from .driver import solve
    problem = case.build(h * 2 if case.levels else h, case.levels)
    out = {}
    for cfun, newton, solver in methods:
        name = method_name(cfun, newton, solver)
        options = {} if solver == "direct" else {"max_linear_its": MAX_LINEAR_ITS}
        try:
            sol = solve(problem, newton=newton, cfun=cfun, solver=solver,
                        initial_guess=case.initial_guess, **options)
        except Exception as e:      # noqa: BLE001  (a failed run is a row of the matrix)
            interrupts.raise_pending()      # (unless a signal made it: the signal's)
            out[name] = e
            say(f"stability: {case.name:14s} {name:22s} ERROR {type(e).__name__}: {e}")
            continue
        out[name] = sol
        say(f"stability: {case.name:14s} {name:22s} "
            f"{'converged' if sol.converged else 'NOT CONVERGED'}  newton "
            f"{sol.newton_iterations:3d}  linear {sol.linear_iterations:5d}  "
            f"{sol.wall_time_s:6.2f} s")
    return out


def scale_defect(sol, ref, factor):
    """max over u1, u2, λ of ‖X_s/s - X‖∞ / ‖X‖∞ (a component identically 0 in both: 0);
    None where the two runs' meshes do not number their dofs alike."""
    comm = ref.comm
    xa = sol.disc.V.tabulate_dof_coordinates()[:sol.disc.n]
    xb = ref.disc.V.tabulate_dof_coordinates()[:ref.disc.n]
    same = xa.shape == xb.shape and np.array_equal(xa, xb)
    if not comm.allreduce(same, op=MPI.LAND):
        return None
    worst = 0.0
    for a, b in zip(sol.disc.split(sol.X), ref.disc.split(ref.X)):
        diff = comm.allreduce(float(np.max(np.abs(a / factor - b), initial=0.0)), op=MPI.MAX)
        size = comm.allreduce(float(np.max(np.abs(b), initial=0.0)), op=MPI.MAX)
        big = comm.allreduce(float(np.max(np.abs(a / factor), initial=0.0)), op=MPI.MAX)
        worst = max(worst, diff / size if size > 0 else big)
    return float(worst)


def table(cases, runs):
    """One row (COLUMNS) per case and method; `runs` = {case name: run_case(...)}
    (collective: the summaries reduce over the communicator)."""
    rows = []
    for case in cases:
        for method, sol in runs[case.name].items():
            row = dict.fromkeys(COLUMNS)
            mine = {"case": case.name, "class": case.klass, "method": method,
                    "description": case.description}
            row.update(mine)
            if isinstance(sol, Exception):
                rows.append(dict(row, converged=False,
                                 reason=f"{type(sol).__name__}: {sol}"))
                continue
            s = sol.summary()
            ok = finite(sol)
            row.update({k: s[k] for k in COLUMNS if k in s and k not in mine})
            row.update(converged=bool(sol.converged and ok), wall_time_s=s["wall_time_s"],
                       reason=sol.reason if ok else "non-finite value in the output")
            ref = runs.get(case.scaled_from, {}).get(method) if case.scaled_from else None
            if ref is not None and not isinstance(ref, Exception):
                row["scale_defect"] = scale_defect(sol, ref, case.factor)
                row["same_counts"] = (sol.newton_iterations == ref.newton_iterations and
                                      sol.linear_iterations == ref.linear_iterations)
            rows.append(row)
    return rows


# ## stability.md

def _fmt(value):
    if value is None:
        return "—"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "**no**"
    if isinstance(value, float):
        if value == 0.0:
            return "0"
        return f"{value:.2e}" if value and (abs(value) < 1e-2 or abs(value) >= 1e4) \
            else f"{value:.3g}"
    return str(value)


def findings(rows):
    """The counts and lists stability.md opens with (also `main`'s one-line verdict)."""
    known = [r for r in rows if r.get("effectivity") is not None]
    eff = [r for r in known if r["converged"]]
    return {"runs": len(rows), "converged": sum(bool(r["converged"]) for r in rows),
            "failures": [r for r in rows if not r["converged"]],
            "with_effectivity": len(known),
            "below_one": [r for r in known if r["effectivity"] < 1.0],   # any iterate (§7)
            "not_robust": [r for r in eff if r["effectivity"] > NOT_ROBUST]}


def markdown(rows, h, seconds, processes):
    f = findings(rows)
    cases = list(dict.fromkeys(r["case"] for r in rows))
    lines = ["# Stability matrix (§11)", "",
             f"{f['converged']} of {f['runs']} runs converged ({len(cases)} cases; disk "
             f"meshes at h = {h}; {processes} process(es); {seconds:.0f} s in all). Method = "
             "C-function / Newton variant / solver (direct: MUMPS; paper: GMRES + " +
             ("ILU(0)" if processes == 1 else "block-Jacobi ILU(0)") + ", full system; amg: "
             "FGMRES + mean/gap BoomerAMG, eliminated system).",
             "Residuals are ‖W R_lin‖/‖W F‖ (rows weighted by 1/μ_α); the complementarity "
             "violation is relative to the data's displacement and pressure sizes; the "
             "effectivity is η/|||u - u_h||| at the final iterate where the exact solution "
             "is known; the adaptive variant stops at the discretisation error, so its "
             "residual and complementarity are not at round-off." +
             (PARALLEL_COUNTS if processes > 1 else ""), "",
             f"Software: {one_line(software())}.", "", "## Failures", ""]
    lines += [f"* {r['case']} {r['method']}: {r['reason']}" for r in f["failures"]] or ["None."]
    lines += ["", "## Bound", ""]
    if f["below_one"]:
        lines.append("η < error in: " + ", ".join(
            f"{r['case']} {r['method']} ({r['effectivity']:.3f})" for r in f["below_one"]))
    else:
        lines.append(f"η ≥ |||u - u_h||| in all {f['with_effectivity']} runs where both are "
                     "known, failed runs included (the bound holds at any iterate, §7).")
    known = {}
    for r in rows:
        if r.get("effectivity") is not None and r["converged"]:
            known.setdefault(r["case"], []).append(r["effectivity"])
    if known:
        lines += ["", "Effectivity per case (smallest – largest over the converged runs): " +
                  "; ".join(f"{c} {min(v):.4g} – {max(v):.4g}" for c, v in known.items()) +
                  "."]
    if f["not_robust"]:
        lines += ["", f"Not robust (effectivity above {NOT_ROBUST:g}): " + ", ".join(
            sorted({r["case"] for r in f["not_robust"]})) + "."]
    scaled = [r for r in rows if r.get("scale_defect") is not None]
    if scaled:
        lines += ["", "## Scale invariance", "",
                  f"Largest defect {max(r['scale_defect'] for r in scaled):.1e}; iteration "
                  f"counts equal in {sum(bool(r['same_counts']) for r in scaled)} of "
                  f"{len(scaled)} scaled runs."]
    head = ("case", "method", "converged", "newton_iterations", "linear_iterations",
            "final_residual", "complementarity_violation", "scale_defect", "same_counts",
            "effectivity", "wall_time_s")
    titles = ("case", "method", "conv.", "Newton", "linear", "residual", "compl. viol.",
              "scale defect", "same counts", "effectivity", "time s")
    lines += ["", "## All runs", "", "| " + " | ".join(titles) + " |",
              "|" + "---|" * len(titles)]
    lines += ["| " + " | ".join(_fmt(r.get(k)) for k in head) + " |" for r in rows]
    lines += ["", "## Cases", ""]
    seen = {}
    for r in rows:
        seen.setdefault(r["case"], (r["class"], r["description"]))
    lines += [f"* {name} ({klass}): {text}" for name, (klass, text) in seen.items()]
    return "\n".join(lines) + "\n"


OUTPUT_NAMES = ("stability.csv", "stability.md")      # what `write_stability` writes


def write_stability(out, h=DEFAULT_H, names=None, methods=METHODS, say=lambda line: None,
                    comm=MPI.COMM_WORLD):
    """Run the selected cases and write stability.csv and stability.md into `out`
    (collective; process 0 writes). Returns the rows."""
    from .outputs import json_safe, staged_folder
    h = check_h(h)
    cases = select(names)
    check_sizes(cases, h, comm, methods)
    t = time.perf_counter()
    with staged_folder(out, comm) as tmp:
        runs = {case.name: run_case(case, h, methods, say) for case in cases}
        rows = table(cases, runs)
        seconds = time.perf_counter() - t
        if comm.rank == 0:
            with open(os.path.join(tmp, OUTPUT_NAMES[0]), "w", newline="",
                      encoding="utf-8") as f:
                writer = csv.writer(f)
                writer.writerow(COLUMNS)
                for r in rows:
                    writer.writerow(["" if json_safe(r.get(c)) is None else json_safe(r[c])
                                     for c in COLUMNS])
            with open(os.path.join(tmp, OUTPUT_NAMES[1]), "w", encoding="utf-8") as f:
                f.write(markdown(rows, h, seconds, comm.size))
    return rows


# ## Command line: `membranes stability`

def add_parser(sub):
    p = sub.add_parser("stability", help="run the stiff and extreme cases of §11 with every "
                       "method; write stability.md and stability.csv")
    p.add_argument("--out", metavar="DIR", required=True, type=os.path.expanduser,
                   help="folder for the outputs (made if missing; nothing is written on bad "
                        "input)")
    p.add_argument("--h", type=float, default=DEFAULT_H,
                   help=f"gmsh size of the disk meshes (default {DEFAULT_H})")
    p.add_argument("--cases", metavar="NAMES",
                   help="comma-separated subset of: " + ", ".join(CASE_NAMES))
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    return p


def main(args):
    from ..model.folders import check_output_folder
    from .cli import EXIT_NOT_CONVERGED, emit
    comm = MPI.COMM_WORLD
    names = None if args.cases is None else [n.strip() for n in args.cases.split(",")]
    check_h(args.h)
    select(names)                                  # unknown names: before any run
    # (no folder named as an output: they could not move in after the runs)
    check_output_folder(args.out, comm, names=OUTPUT_NAMES)
    quiet = args.quiet or comm.rank != 0
    say = (lambda line: None) if quiet else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    rows = write_stability(args.out, args.h, names, say=say, comm=comm)
    f = findings(rows)
    if comm.rank == 0:
        emit(f"stability: {f['converged']} of {f['runs']} runs converged; "
             f"{os.path.join(os.path.abspath(args.out), 'stability.md')}")
    return 0 if f["converged"] == f["runs"] else EXIT_NOT_CONVERGED
