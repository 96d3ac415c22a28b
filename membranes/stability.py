"""The stability matrix of DESIGN §11: `membranes stability --out DIR`.

Every case class of DESIGN §11 is run with both C-functions and the three Newton variants:
exact Newton with MUMPS on the full system; exact, inexact and adaptive inexact Newton with
GMRES + ILU(0) on the full system (the paper's solver) and with GMRES + vertex_amg on the
eliminated system (membranes.preconditioner), at most MAX_LINEAR_ITS = 2000 GMRES iterations
per Newton step. Method names read C-function/variant/solver (mumps, ilu, amg). One row per
run goes to ``stability.csv`` and ``stability.md``: converged, Newton
and linear iterations, the final relative residual (newton_system: in units of the data),
the complementarity violation relative to the data (Solution.complementarity_violation), the
scale-invariance defect where the case is a scaled copy of another, the effectivity index
where the exact solution is known, and the wall time.

The cases (``CASES``; h is the gmsh size of the disk meshes, 0.1 by default):

* stiffness — μ1/μ2 ∈ {1e-6, 1e-3, 1, 1e3, 1e6} (μ2 = 1): the radial scene with contact disk
  r ≤ 1/2 (scenes.radial, exact solution);
* gap — g ∈ {1e-12, 1e-6, 1e3} under the fixed load f1 = -1, f2 = 0 on the unit disk (user
  data; from contact almost everywhere to no contact at all, no exact solution);
* scaling — the μ1/μ2 = 1 case with f1, f2, g multiplied by 1e-8 and 1e8 (the radial loads
  are proportional to g): u1, u2, λ must scale by s and the iteration counts stay the same;
  the defect is max over u1, u2, λ of ‖X_s/s - X‖∞/‖X‖∞ against the same method on the
  unscaled case;
* contact — no contact, grazing contact (w and λ vanish together at the origin:
  Fischer–Burmeister's kink) and near-total contact (r ≤ 0.95), radial scenes;
* mesh — the square scene (exact solution) on an anisotropic mesh (4 × 400 rectangles, cell
  aspect ratio 100), a graded one ((x, y) -> (x³, y³) on 16 × 16, cell sizes from 2e-4 to
  0.18) and one of 18 cells (3 × 3);
* initial guess — the μ1/μ2 = 1 radial case from X^0 = 0 and from a far-off X^0 that violates
  every constraint: u1 = -1e3 u_data, u2 = 1e3 u_data, λ = -1e3 λ_data
  (Discretisation.data_scales).

Measured (h = 0.1, 2026-11-21): 248 of 252 runs converge; the 4 failures are GMRES +
ILU(0) on the full system on the anisotropic mesh (exact: GMRES stagnates, 2000 iterations;
inexact: 10 ILU-GMRES steps per Newton step are no Newton direction there), which vertex_amg
on the eliminated system solves. η ≥ error in all 203 runs with both; the effectivity is
1.00–1.9 except for a soft membrane 1: 24.7 at μ1/μ2 = 1e-3 and 815 at 1e-6. There η_F and
η_osc of membrane 1 (weighted by μ1^(-1/2)) carry the jump of f1 = -μ1 Δu1 - λ across the
free boundary, which only the discrete λ_h balances; they decrease like h^1.5 while the error
decreases like h (815 at h = 0.1, 572 at h = 0.05): the bound of DESIGN §7 stays guaranteed
but is not robust in μ1/μ2.

Exit code 0 when every run converged, 3 otherwise (the files are written in any case, with
the reasons); bad input (h, --out, unknown case names) exits 2 before any run.
"""

import csv
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .outputs import staged_folder

# linear solvers: MUMPS on the full system (exact Newton only), GMRES + ILU(0) on the full
# system (the paper's), GMRES + vertex_amg on the eliminated system (membranes.preconditioner)
SOLVERS = {"mumps": {"linear_solver": "direct", "system": "full"},
           "ilu": {"linear_solver": "gmres", "system": "full"},
           "amg": {"linear_solver": "gmres", "system": "eliminated",
                   "petsc_options": {"pc_type": "vertex_amg"}}}
METHODS = tuple((cfun, newton, solver) for cfun in ("min", "fb")
                for newton, solver in (("exact", "mumps"), ("exact", "ilu"), ("inexact", "ilu"),
                                       ("adaptive", "ilu"), ("exact", "amg"),
                                       ("inexact", "amg"), ("adaptive", "amg")))
MAX_LINEAR_ITS = 2000     # per Newton step: bounds the time a stagnating GMRES may take
COLUMNS = ("case", "class", "method", "converged", "newton_iterations", "linear_iterations",
           "final_residual", "complementarity_violation", "scale_defect", "same_counts",
           "effectivity", "energy_error", "eta", "wall_time_s", "description", "reason")
DEFAULT_H = 0.1


def method_name(cfun, newton, solver):
    return f"{cfun}/{newton}/{solver}"


def far_off_guess(disc):
    """X^0 violating every constraint, three orders of magnitude off the data's sizes."""
    u_data, lam_data = disc.data_scales()
    n = disc.n
    return np.concatenate([np.full(n, -1e3 * u_data), np.full(n, 1e3 * u_data),
                           np.full(n, -1e3 * max(lam_data, 1.0))])


@dataclass
class Case:
    name: str
    klass: str
    description: str
    build: Callable            # h -> Problem
    initial_guess: object = None
    scaled_from: str = None    # name of the case this one is a scaled copy of ...
    factor: float = None       # ... with f1, f2, g multiplied by `factor`


def _radial(**kwargs):
    def build(h):
        from . import scenes
        return scenes.radial(h=h, **kwargs)
    return build


def _user(**kwargs):
    def build(h):
        from . import scenes
        return scenes.user(h=h, **kwargs)
    return build


def _square(nx, ny, grading=1.0):
    def build(h):
        from . import meshes, scenes
        return scenes.square(mesh=meshes.structured_square(nx, ny, grading))
    return build


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
    return out


CASES = _cases()
CASE_NAMES = tuple(c.name for c in CASES)


def select(names=None):
    """The cases called `names` (all by default), with the cases they are scaled copies of;
    ValueError for an unknown name."""
    if names is None:
        return list(CASES)
    unknown = [n for n in names if n not in CASE_NAMES]
    if unknown:
        raise ValueError(f"unknown stability case {unknown[0]!r} (choose from: "
                         f"{', '.join(CASE_NAMES)})")
    wanted = set(names) | {c.scaled_from for c in CASES if c.name in names and c.scaled_from}
    return [c for c in CASES if c.name in wanted]


def _finite(sol):
    """No NaN or infinity in the solution nor in any recorded number."""
    if not np.all(np.isfinite(sol.X)):
        return False
    return all(not (isinstance(v, float) and not math.isfinite(v))
               for rec in sol.history for v in rec.values())


def run_case(case, h=DEFAULT_H, methods=METHODS, say=lambda line: None):
    """Solve `case` with every method; returns {method name: (Solution, seconds)}."""
    from .driver import solve
    problem = case.build(h)
    out = {}
    for cfun, newton, solver in methods:
        t = time.perf_counter()
        options = dict(SOLVERS[solver])
        if options["linear_solver"] == "gmres":
            options["max_linear_its"] = MAX_LINEAR_ITS
        sol = solve(problem, newton=newton, cfun=cfun, initial_guess=case.initial_guess,
                    **options)
        seconds = time.perf_counter() - t
        out[method_name(cfun, newton, solver)] = (sol, seconds)
        say(f"stability: {case.name:14s} {method_name(cfun, newton, solver):22s} "
            f"{'converged' if sol.converged else 'NOT CONVERGED'}  newton "
            f"{sol.newton_iterations:3d}  linear {sol.linear_iterations:5d}  {seconds:6.2f} s")
    return out


def scale_defect(sol, ref, factor):
    """max over u1, u2, λ of ‖X_s/s - X‖∞ / ‖X‖∞ (a component identically 0 in both: 0)."""
    n = ref.disc.n
    worst = 0.0
    for k in range(3):
        a, b = sol.X[k * n:(k + 1) * n] / factor, ref.X[k * n:(k + 1) * n]
        size = np.abs(b).max()
        worst = max(worst, np.abs(a - b).max() / size if size > 0 else np.abs(a).max())
    return float(worst)


def table(cases, runs):
    """One row (COLUMNS) per case and method; `runs` = {case name: run_case(...)}."""
    rows = []
    for case in cases:
        for method, (sol, seconds) in runs[case.name].items():
            s = sol.summary()
            row = {"case": case.name, "class": case.klass, "method": method,
                   "converged": bool(sol.converged and _finite(sol)),
                   "newton_iterations": s["newton_iterations"],
                   "linear_iterations": s["linear_iterations"],
                   "final_residual": s["final_residual"],
                   "complementarity_violation": s["complementarity_violation"],
                   "scale_defect": None, "same_counts": None,
                   "effectivity": s["effectivity"], "energy_error": s["energy_error"],
                   "eta": s["eta"], "wall_time_s": seconds,
                   "description": case.description,
                   "reason": sol.reason if _finite(sol) else "non-finite value in the output"}
            if case.scaled_from is not None:
                ref = runs[case.scaled_from][method][0]
                row["scale_defect"] = scale_defect(sol, ref, case.factor)
                row["same_counts"] = (sol.newton_iterations == ref.newton_iterations and
                                      sol.linear_iterations == ref.linear_iterations)
            rows.append(row)
    return rows


def _fmt(value):
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "**no**"
    if isinstance(value, float):
        return f"{value:.2e}" if value and (abs(value) < 1e-2 or abs(value) >= 1e4) \
            else f"{value:.3g}"
    return str(value)


def markdown(rows, h, seconds):
    ok = sum(r["converged"] for r in rows)
    cases = list(dict.fromkeys(r["case"] for r in rows))
    lines = ["# Stability matrix (DESIGN §11)", "",
             f"{ok} of {len(rows)} runs converged ({len(cases)} cases × "
             f"{len(rows) // max(len(cases), 1)} methods; disk meshes at h = {h}; "
             f"{seconds:.0f} s in all). Method = C-function / Newton variant / linear solver.",
             "Residuals are relative to the data scale (newton_system); the complementarity "
             "violation is relative to the data's displacement and pressure sizes; the "
             "effectivity is η/|||u - u_h||| at the final iterate where the exact solution is "
             "known (— where the final iterate carries no guaranteed bound: the last inexact "
             "iterate with the ν-flux); the adaptive variant stops at the discretisation "
             "error, so its residual and complementarity are not at round-off.", ""]
    failures = [r for r in rows if not r["converged"]]
    lines += ["## Failures", ""]
    lines += [f"* {r['case']} {r['method']}: {r['reason']}" for r in failures] or ["None."]
    bound = [r for r in rows if r["effectivity"] is not None and r["effectivity"] < 1.0]
    lines += ["", "## Bound", "",
              (f"η ≥ |||u - u_h||| in every run where both are known "
               f"({sum(r['effectivity'] is not None for r in rows)} runs)." if not bound else
               "η < error in: " + ", ".join(f"{r['case']} {r['method']} "
                                            f"({r['effectivity']:.3f})" for r in bound))]
    known = {}
    for r in rows:
        if r["effectivity"] is not None:
            known.setdefault(r["case"], []).append(r["effectivity"])
    if known:
        lines += ["", "Effectivity per case (smallest – largest over the methods): " +
                  "; ".join(f"{c} {min(v):.3g} – {max(v):.3g}" for c, v in known.items()) +
                  ". Large values for a soft membrane 1 (μ1/μ2 ≤ 1e-3) come from η_F and "
                  "η_osc of that membrane, weighted by μ1^(-1/2) (DESIGN §7): guaranteed, "
                  "not robust in μ (module notes of membranes.stability)."]
    scaled = [r for r in rows if r["scale_defect"] is not None]
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
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r[k]) for k in head) + " |")
    lines += ["", "## Cases", ""]
    seen = {}
    for r in rows:
        seen.setdefault(r["case"], (r["class"], r["description"]))
    lines += [f"* {name} ({klass}): {text}" for name, (klass, text) in seen.items()]
    return "\n".join(lines) + "\n"


def write_stability(out, h=DEFAULT_H, names=None, say=lambda line: None):
    """Run the selected cases and write stability.csv and stability.md into `out`."""
    if not (isinstance(h, (int, float)) and math.isfinite(h) and h > 0):
        raise ValueError(f"h must be a positive finite number, got {h}")
    cases = select(names)
    out = os.path.abspath(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"--out {out} exists and is not a folder")
    t = time.perf_counter()
    runs = {case.name: run_case(case, h, say=say) for case in cases}
    rows = table(cases, runs)
    seconds = time.perf_counter() - t
    with staged_folder(out) as tmp:
        with open(os.path.join(tmp, "stability.csv"), "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(COLUMNS)
            for r in rows:
                writer.writerow(["" if r[c] is None else r[c] for c in COLUMNS])
        with open(os.path.join(tmp, "stability.md"), "w") as f:
            f.write(markdown(rows, h, seconds))
    return rows


# ## Command line: `membranes stability`

def add_parser(sub):
    p = sub.add_parser("stability", help="run the stiff and extreme cases of DESIGN §11 with "
                       "every method; write stability.md and stability.csv")
    p.add_argument("--out", metavar="DIR", required=True)
    p.add_argument("--h", type=float, default=DEFAULT_H,
                   help=f"gmsh size of the disk meshes (default {DEFAULT_H})")
    p.add_argument("--cases", metavar="NAMES",
                   help="comma-separated subset of: " + ", ".join(CASE_NAMES))
    p.add_argument("--quiet", action="store_true")
    return p


def main(args):
    from .cli import EXIT_NOT_CONVERGED
    names = None if args.cases is None else [n.strip() for n in args.cases.split(",")]
    say = (lambda line: None) if args.quiet else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    rows = write_stability(args.out, args.h, names, say)
    ok = sum(r["converged"] for r in rows)
    print(f"stability: {ok} of {len(rows)} runs converged; "
          f"{os.path.join(os.path.abspath(args.out), 'stability.md')}")
    return 0 if ok == len(rows) else EXIT_NOT_CONVERGED
