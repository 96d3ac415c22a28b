"""The report: `membranes report --scene disk --h H --levels J --out DIR` (§7, §8, §10).

One process group, one problem, every method measured in the same run, one after another:

* exact, inexact and adaptive inexact Newton with the default fast solver (`solver='amg'`:
  FGMRES + the mean/gap BoomerAMG preconditioner on the eliminated system, nested iteration
  over T_0, …, T_J);
* the same three with the paper's configuration (`solver='paper'`: GMRES + ILU(0) on the full
  3N system, on T_J alone from X⁰ = (g, 0, 0)), whose Newton and GMRES counts are those of the
  paper's table (§8, reproduced beside ours in report.md);
* the peers of §10 (`membranes.app.peer`): the nested SNES VI peer; the certified nested peer,
  the same run followed by our estimator set-up and one evaluation at its final iterate (with
  that iterate's residual of the linear rows, §4, so that η is a guaranteed bound); and the
  plain peer (SNES VI on T_J alone, from zero).

Every run records the energy error at each recorded iterate (`errors='iterates'`, off the
clock); the peers' SNES monitor does the same for each SNES iterate, outside their clock.

Written into DIR (staged in it, moved in at the end: `outputs.staged_folder`):

* `table.csv`: per method converged, Newton (SNES) steps, Krylov (CG) steps, wall time, final
  energy error, η, effectivity;
* `error_vs_time.png` + `.csv`: energy error (and η where the run computed it) against wall
  time at the Newton / SNES iterates, the fast solvers with the peers on the left, the paper's
  configuration with the peers on the right;
* `estimators_<method>.png` + `.csv`: η, η_disc, η_lin, η_alg against cumulative Krylov steps.
  Adaptive runs estimate every ν-th Krylov iterate themselves; exact and inexact runs estimate
  only their final iterate, so for this figure they are replayed off the clock with the
  estimators attached at X⁰ and every Newton iterate (the same iterates: report.md says
  whether the replay's counts equal the run's);
* `error_distribution.png` + `.csv`: |||u - u_h|||_K against η_K at the final iterate of the
  adaptive fast run, one logarithmic colour scale (pyvista, off-screen: render.py);
* `contact.png` + `.csv`: u1 - u2 and λ of that iterate, with the scene's interface in red;
* `report.md` showing all of them. Every number comes from the run.

Wall times: `solve`'s clock (discretisation, Newton, Krylov and every estimate the method uses
or certifies with); the peers' solver time plus their discretisation (the same scope). Under
`mpirun` every process computes and process 0 writes; the mesh is gathered onto process 0 for
the two pictures only. matplotlib and pyvista are imported only when a report is asked for:
without matplotlib the report is refused before any run (`check_matplotlib`), without a
pyvista that draws it goes without those two pictures.
"""

import json
import os
import sys
import time

import numpy as np
from mpi4py import MPI

from .versions import one_line

# (label, Newton variant, Krylov preset, nested)
METHODS = (("exact/amg", "exact", "amg", None), ("inexact/amg", "inexact", "amg", None),
           ("adaptive/amg", "adaptive", "amg", None),
           ("exact/paper", "exact", "paper", False), ("inexact/paper", "inexact", "paper", False),
           ("adaptive/paper", "adaptive", "paper", False))
METHOD_NAMES = tuple(m[0] for m in METHODS)
PEERS = ("nested peer", "certified nested peer", "plain peer")
PYVISTA_PICTURES = ("error_distribution.png", "contact.png")
MAX_NEWTON = {"exact": 100, "inexact": 400, "adaptive": 100}
CURVE_COLUMNS = ("method", "level", "newton_it", "kind", "cumulative_linear_its",
                 "wall_time_s", "residual", "energy_error", "eta", "eta_disc", "eta_lin",
                 "eta_alg")
TABLE_COLUMNS = ("method", "converged", "newton_iterations", "newton_per_level",
                 "linear_iterations", "wall_time_s", "energy_error", "eta", "effectivity",
                 "bound_guaranteed", "n_cells")
TABLE_HEADINGS = ("method", "converged", "Newton (SNES) steps", "per level",
                  "Krylov (CG) steps", "wall time [s]", "energy error", "η", "η / error",
                  "guaranteed", "cells")
# What several processes change besides block-Jacobi ILU(0) (report.md, stability.md)
PARALLEL_COUNTS = (" On several processes the Krylov counts of the amg runs and of the peers "
                   "may differ from a serial run's too (BoomerAMG's coarsening and smoothing "
                   "depend on the partition), and with them the iterate where an adaptive run "
                   "stops; exact and inexact Newton reach the same discrete solution, to "
                   "their tolerance, whatever the number of processes.")
# The paper's table (§8): elements, then Newton and GMRES steps of exact, inexact, adaptive
PAPER = {"elements": (2048, 4064, 7840, 16832, 20928, 27328, 34592),
         "exact": ((8, 12, 15, 19, 22, 25, 28), (330, 585, 930, 1485, 1920, 2460, 2985)),
         "inexact": ((16, 27, 46, 76, 86, 174, 166), (160, 270, 460, 760, 860, 1740, 1660)),
         "adaptive": ((7, 11, 14, 18, 21, 23, 27), (80, 120, 180, 340, 410, 490, 670))}


def _slug(method):
    return method.replace("/", "_").replace(" ", "_")


# ## The runs

def run_methods(problem, say):
    """The six Newton runs: {label: Solution}."""
    from .driver import solve
    runs = {}
    for label, newton, solver, nested in METHODS:
        sol = runs[label] = solve(problem, newton=newton, solver=solver, nested=nested,
                                  errors="iterates", max_newton=MAX_NEWTON[newton])
        say(f"report: {label}: {sol.newton_iterations} Newton steps, "
            f"{sol.linear_iterations} Krylov steps, {sol.wall_time_s:.2f} s, converged = "
            f"{sol.converged}")
    return runs


def replay(problem, sol):
    """The estimators at X⁰ and every Newton iterate of an exact or inexact run (which
    estimates its final iterate only), by running its Newton iteration again off the clock
    with the estimators attached (Newton's `estimate` callback): a list of history-like
    records (level, newton_it, kind, cumulative_linear_its and the estimators)."""
    from ..fem.discretisation import discretise
    from ..linalg.krylov import Krylov
    from ..nonlinear.newton import newton
    from ..nonlinear.system import final_residual
    from .driver import prolong
    from .schedule import LevelEstimates
    from .solution import ESTIMATOR_COLUMNS
    o = sol.options
    krylov = Krylov(o["solver"], o["petsc_options"] or None,
                    **({} if o["nu"] is None else {"nu": o["nu"], "max_it": o["max_linear_its"]}))
    J = problem.levels
    records, prev, offset = [], None, 0
    for j in (range(J + 1) if o["nested"] else [J]):
        pj = problem.on_level(j)
        disc = discretise(pj)
        X0 = None if prev is None else \
            prolong(problem.hierarchy.prolongation(j), disc, prev[0], prev[1])
        certificate = LevelEstimates(disc, "nu", gate=None)     # every iterate in full

        def estimate(X, R, kind, disc=disc, certificate=certificate):
            # Newton hands X⁰ without a residual; X⁰ need not satisfy the linear rows (§4)
            return certificate(X, final_residual(disc, X, o["cfun"]) if R is None else R,
                               kind)

        result = newton(disc, X0, cfun=o["cfun"], variant=o["newton"], system=o["system"],
                        krylov=krylov, estimate=estimate, tol=o["tol"],
                        max_newton=MAX_NEWTON[o["newton"]])
        for rec in result.history:
            est = rec.get("estimates") or {}
            records.append({"level": j, "newton_it": rec["k"], "kind": rec["kind"],
                            "cumulative_linear_its": rec["krylov_total"] + offset,
                            **{k: est.get(k) for k in ESTIMATOR_COLUMNS}})
        offset += result.krylov_steps
        if not result.converged:
            break
        prev = (result.X, disc.n)
    return records


def estimator_rows(problem, sol):
    """The rows of a method's estimator figure and whether they are the run's own: the
    history of an adaptive run; for exact and inexact the run's Newton records with the
    replay's estimators (matched record by record when the counts agree). Collective."""
    from .garbage import release_garbage
    if sol.options["newton"] == "adaptive":
        return [dict(r) for r in sol.history], "run"
    replayed = replay(problem, sol)
    # the replay's PETSc objects (and the peers' before it) stayed parked until the end of
    # the process: a replay is no `solve`, which frees its own (membranes.app.garbage)
    release_garbage(problem)
    own = sol.history
    same = len(replayed) == len(own) and all(
        (a["level"], a["newton_it"], a["cumulative_linear_its"]) ==
        (b["level"], b["newton_it"], b["cumulative_linear_its"]) for a, b in zip(replayed, own))
    if not same:
        return replayed, "replay (counts differ from the run's)"
    return [dict(b, **{k: v for k, v in a.items() if k.startswith("eta")})
            for a, b in zip(replayed, own)], "replay (same counts as the run)"


class PeerCurve:
    """The SNES monitor of a peer run: the energy error of every SNES iterate on its level
    (outside the peer's clock), kept with the level's solver seconds so far."""

    def __init__(self):
        self.points, self._errors = [], {}

    def __call__(self, level, its, seconds, disc, X):
        from ..estimation.energy_error import EnergyError
        if id(disc) not in self._errors:        # (the disc kept with it: its id stays its own)
            self._errors = {id(disc): (disc, EnergyError(disc))}
        self.points.append((level, its, seconds, self._errors[id(disc)][1](X)))

    def records(self, method, result, first_level=0):
        """Curve records: the time of an iterate is the solver and discretisation time of
        the levels before it, its level's discretisation, and its level's solver time.
        `first_level`: the hierarchy level of the run's first level (J for the plain peer)."""
        start, t = [], 0.0
        for rec in result.levels:
            start.append(t + rec.setup_time_s)
            t += rec.setup_time_s + rec.wall_time_s
        return [{"method": method, "level": first_level + lv, "newton_it": its,
                 "kind": "initial" if its == 0 else "snes", "wall_time_s": start[lv] + s,
                 "energy_error": err} for lv, its, s, err in self.points]


def run_peers(problem, say):
    """The nested peer (with its certificate) and the plain peer: (rows, curve records)."""
    from ..estimation.energy_error import EnergyError
    from .peer import certify, nested_peer, plain_peer
    rows, curves = [], []
    for label, run in (("nested peer", nested_peer), ("plain peer", plain_peer)):
        monitor = PeerCurve()
        result = run(problem, monitor=monitor)
        error = EnergyError(result.disc)(result.X)
        wall = result.wall_time_s + result.setup_time_s
        row = {"method": label, "converged": result.converged,
               "newton_iterations": result.snes_iterations,
               "newton_per_level": "+".join(str(r.snes_iterations) for r in result.levels),
               "linear_iterations": result.ksp_iterations, "wall_time_s": wall,
               "energy_error": error, "eta": None, "effectivity": None,
               "bound_guaranteed": None, "n_cells": _cells(result.disc.mesh),
               "reason": result.reason}
        rows.append(row)
        curves += monitor.records(label, result, 0 if run is nested_peer else problem.levels)
        say(f"report: {label}: {result.snes_iterations} SNES steps, {result.ksp_iterations} "
            f"CG steps, {wall:.2f} s, converged = {result.converged}")
        if label == "nested peer":
            est, _, seconds = certify(result)
            rows.append(dict(row, method="certified nested peer", wall_time_s=wall + seconds,
                             eta=est["eta"], effectivity=est["eta"] / error,
                             bound_guaranteed=True, eta_rem=est["eta_rem"],
                             certificate_s=seconds))
            curves.append({"method": "certified nested peer", "level": problem.levels,
                           "newton_it": result.levels[-1].snes_iterations,   # (on T_J)
                           "kind": "certificate",
                           "wall_time_s": wall + seconds, "energy_error": error,
                           "eta": est["eta"], "eta_disc": est["eta_disc"],
                           "eta_lin": est["eta_lin"], "eta_alg": est["eta_alg"]})
            say(f"report: certified nested peer: eta {est['eta']:.4e} (+{seconds:.2f} s)")
    return rows, curves


def _cells(mesh):
    return int(mesh.topology.index_map(2).size_global)


def method_row(label, s):
    """A table row from a run's summary."""
    return {"method": label, **{k: s.get(k) for k in TABLE_COLUMNS[1:]},
            "newton_per_level": "+".join(str(p["newton_iterations"]) for p in s["per_level"]),
            "reason": s["reason"]}


# ## Curves (matplotlib, process 0)

def check_matplotlib():
    """ValueError unless matplotlib can be imported: the curves need it, but it is no
    dependency of the package (`solve` does not draw), so a plain `pip install` lacks it. Asked
    before any run (on every process, which share the environment), not after all of them.
    The advice pins numpy: an unpinned matplotlib pulls a numpy that dolfinx cannot load."""
    try:
        import matplotlib.figure  # noqa: F401
    except ImportError as e:
        raise ValueError(f"membranes report draws its curves with matplotlib, which cannot be "
                         f"imported here ({e}): pip install matplotlib "
                         f"numpy=={np.__version__}") from None


def _points(rows, x, y):
    pts = [(r[x], r[y]) for r in rows if r.get(y) is not None and r[y] > 0]
    return tuple(zip(*pts)) if pts else ((), ())


def plot_error_vs_time(curves, path):
    """Energy error (solid) and η (dashed) against wall time; left the fast solvers, right
    the paper's configuration, the peers on both."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(13, 5.2), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    colours = {m: f"C{i}" for i, m in enumerate(METHOD_NAMES[:3] + PEERS)}
    colours.update({m: colours[m.replace("paper", "amg")] for m in METHOD_NAMES[3:]})
    for ax, (suffix, title) in zip(axes, (("/amg", "fast solver (amg, nested) and peers"),
                                          ("/paper", "paper's solver (GMRES + ILU(0), T_J) "
                                                     "and peers"))):
        for method in dict.fromkeys(r["method"] for r in curves):
            if "/" in method and not method.endswith(suffix):
                continue
            mine = [r for r in curves if r["method"] == method and r["kind"] != "krylov"]
            t, err = _points(mine, "wall_time_s", "energy_error")
            if method != "certified nested peer" and err:
                ax.plot(t, err, "-o", ms=3, color=colours[method], label=f"{method}: error")
            t, eta = _points(mine, "wall_time_s", "eta")
            if eta:
                style = "*" if method == "certified nested peer" else "--s"
                ax.plot(t, eta, style, ms=5 if len(eta) > 1 else 10, color=colours[method],
                        label=f"{method}: η")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time [s] (discretisation included)")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    axes[0].set_ylabel("energy error |||u - u_h|||, estimate η")
    fig.savefig(path, dpi=100)


def plot_estimators(method, rows, path):
    """η, η_disc, η_lin, η_alg (and the error) against cumulative Krylov steps; grey lines:
    Newton steps, dashed: a new level."""
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7.5, 4.8), layout="constrained")
    ax = fig.add_subplot()
    for key, colour in (("eta", "k"), ("eta_disc", "C0"), ("eta_lin", "C1"),
                        ("eta_alg", "C2"), ("energy_error", "C3")):
        its, values = _points(rows, "cumulative_linear_its", key)
        if values:
            ax.plot(its, values, "-" if key != "energy_error" else ":", color=colour,
                    marker=".", ms=4, label=key.replace("eta", "η").replace("_", " "))
    for a, b in zip(rows, rows[1:]):
        if b["kind"] == "newton":
            ax.axvline(b["cumulative_linear_its"], color="0.85", lw=0.8, zorder=0)
        if b["level"] != a["level"]:
            ax.axvline(b["cumulative_linear_its"], color="0.4", lw=0.8, ls="--", zorder=0)
    ax.set_yscale("log")
    ax.set_xlabel("cumulative Krylov steps (grey: Newton steps, dashed: next level)")
    ax.set_ylabel("estimators")
    ax.set_title(f"{method}: estimators against Krylov steps")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=100)


# ## Pictures of the final iterate (pyvista via render.py)

def error_distribution(sol, path):
    """|||u - u_h|||_K beside η_K (cells): the CSV (process 0) and the picture's
    (panels, path, options) for `render.snapshots`; returns the gathered (error_K, eta_K) on
    process 0 and the picture."""
    from ..estimation.energy_error import EnergyError
    from .outputs import write_columns
    from .render import gather_cells, gather_points
    V, comm = sol.disc.V, sol.comm
    actual = EnergyError(sol.disc).per_cell(sol.X)
    # a run that ended before its certificate (on a coarse level) has no η_K: empty cells
    eta_K = np.full(len(actual), np.nan) if sol.eta_K is None else sol.eta_K
    _, centres = gather_points(V)
    a, e = gather_cells(comm, actual), gather_cells(comm, eta_K)
    if comm.rank == 0:
        write_columns(path + ".csv", {"cell": np.arange(len(a)), "x": centres[:, 0],
                                      "y": centres[:, 1], "error_K": a, "eta_K": e})
    picture = ([("error_K", "cell", actual, "actual error (energy norm on each cell)"),
                ("eta_K", "cell", eta_K, "estimated error eta_K")], path + ".png", dict(log=True))
    return (a, e), picture


def contact_zone(sol, path):
    """u1 - u2 and λ with the scene's interface: the CSV (process 0); returns the picture's
    (panels, path, options) for `render.snapshots`."""
    from dolfinx import fem

    from .outputs import write_columns
    from .render import _gather
    disc = sol.disc
    V, n = disc.V, disc.n
    u1, u2, lam = disc.split(sol.X)
    gap = fem.Function(V)
    gap.x.array[:] = sol.u1.x.array - sol.u2.x.array
    x = V.tabulate_dof_coordinates()[:n]
    cols = [_gather(sol.comm, c) for c in (x[:, 0], x[:, 1], u1 - u2, lam)]
    if sol.comm.rank == 0:
        write_columns(path + ".csv", {"vertex": np.arange(len(cols[0])), "x": cols[0],
                                      "y": cols[1], "gap": cols[2], "lambda": cols[3]})
    return ([("u1 - u2", "point", gap, "gap u1 - u2"),
             ("lambda", "point", sol.lam, "contact pressure lambda")], path + ".png",
            dict(contour=sol.problem.interface, cmap="plasma"))


# ## report.md

def _fmt(v):
    if v is None:
        return "—"
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "**no**"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def paper_comparison(runs, summaries):
    """Our paper-configuration counts beside the paper's column nearest in elements."""
    cells = summaries["exact/paper"]["n_cells"]
    k = int(np.argmin([abs(e - cells) for e in PAPER["elements"]]))
    lines = ["| variant | Newton (ours) | Newton (paper) | GMRES (ours) | GMRES (paper) |",
             "|---|---|---|---|---|"]
    for v in ("exact", "inexact", "adaptive"):
        s = runs[f"{v}/paper"]
        lines.append(f"| {v} | {s.newton_iterations} | {PAPER[v][0][k]} | "
                     f"{s.linear_iterations} | {PAPER[v][1][k]} |")
    return cells, PAPER["elements"][k], lines


def _image(alt, name, missing):
    """The markdown of picture `name`, or why it is missing (`missing`: {name: reason})."""
    if name in missing:
        return f"*No picture: {missing[name]}.*"
    return f"![{alt}]({name})"


def markdown(problem, runs, summaries, rows, cells, sources, seconds, missing=None):
    """report.md (process 0: `summaries` are the runs' summaries, made collectively);
    `missing`: {picture: why it was not drawn}."""
    missing = missing or {}
    s = summaries["exact/paper"]
    actual, eta_K = cells
    ours, theirs, comparison = paper_comparison(runs, summaries)
    lines = [f"# Report: scene `{problem.name}`", "",
             f"{s['n_vertices']} vertices, {s['n_cells']} cells on T_J, h = {s['h']:.4g} "
             f"(coarse h = {s['h_coarse']:.4g}, J = {s['levels']}); {problem.description}; "
             f"{s['processes']} process(es). All methods ran in this run, one after another "
             f"({seconds:.0f} s in all); every number below comes from it.", "",
             "Methods: `<variant>/amg` — FGMRES + mean/gap BoomerAMG on the eliminated "
             "system, nested over T_0..T_J; `<variant>/paper` — GMRES + ILU(0) on the full "
             "system on T_J from (g, 0, 0), the paper's configuration" +
             (f" (on {s['processes']} processes block-Jacobi ILU(0), so its counts differ "
              "from a serial run's)" if s["processes"] > 1 else "") + ". Peers (§10): PETSc "
             "SNES vinewtonrsls on the decoupled problem, CG + BoomerAMG inside (their steps "
             "are SNES steps, their Krylov steps CG steps); the certified nested peer adds "
             "our estimator set-up and one evaluation at its final iterate. Wall times: from "
             "the start of the method, discretisation included; energy errors off the clock." +
             (PARALLEL_COUNTS if s["processes"] > 1 else ""),
             "", f"Software: {one_line(s['software'])}.",
             "", "## Steps, time, error", "",
             "| " + " | ".join(TABLE_HEADINGS) + " |", "|" + "---|" * len(TABLE_HEADINGS)]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in TABLE_COLUMNS) + " |" for r in rows]
    lines += ["", "Data: `table.csv`. Energy error: "
              f"{runs['exact/paper'].energy_error_kind}."]
    for r in rows:
        if not r["converged"]:
            lines += ["", f"{r['method']}: not converged: {r['reason']}."]
    lines += ["", "## The paper's table (§8)", "",
              f"Our paper configuration on {ours} cells beside the paper's column of {theirs} "
              "elements (" + ("its disk meshes are not ours" if problem.name == "disk" else
                              f"its problem is the disk, not the {problem.name} scene") +
              ": compare orders of magnitude).", ""]
    lines += comparison
    lines += ["", "## Error and estimate against wall time", "",
              "![error vs time](error_vs_time.png)", "",
              "Dots: Newton (SNES) iterates of every level; squares: η where the run "
              "computed it; star: the certified peer's η. Data: `error_vs_time.csv`.", "",
              "## Estimators against Krylov steps", ""]
    for m in METHOD_NAMES:
        lines += [f"![{m}](estimators_{_slug(m)}.png)", "",
                  f"Data: `estimators_{_slug(m)}.csv` (estimators: {sources[m]}).", ""]
    lines += ["## Error distribution (adaptive/amg, final iterate)", "",
              _image("error distribution", "error_distribution.png", missing), "",
              "Actual |||u - u_h|||_K (left) and η_K (right), one logarithmic colour scale. " +
              (f"Largest cell values {actual.max():.3e} (actual), {eta_K.max():.3e} "
               f"(estimated); root sums of squares {np.sqrt((actual ** 2).sum()):.4e} and "
               f"{np.sqrt((eta_K ** 2).sum()):.4e}." if not np.isnan(eta_K).all() else
               f"Largest cell value {actual.max():.3e}, root sum of squares "
               f"{np.sqrt((actual ** 2).sum()):.4e}; no η_K: the run ended before its "
               "certificate.") + " Data: `error_distribution.csv`.", "",
              "## Contact zone (adaptive/amg, final iterate)", "",
              _image("contact", "contact.png", missing),
              "", "The gap u1 - u2 and the contact pressure λ; red: the scene's interface. "
              "Data: `contact.csv`.", ""]
    return "\n".join(lines)


def output_names():
    """The files `write_report` writes (module notes): `main` checks before any run that no
    folder in DIR has one of these names (the outputs could not move in at the end)."""
    names = ["table.csv", "error_vs_time.csv", "error_vs_time.png", "report.md",
             "error_distribution.csv", "contact.csv", *PYVISTA_PICTURES]
    for m in METHOD_NAMES:
        names += [f"estimators_{_slug(m)}.csv", f"estimators_{_slug(m)}.png"]
    return names


def write_report(problem, out, say=lambda line: None):
    """Run every method and peer on `problem` and write the report into `out` (collective;
    process 0 writes). Returns (runs {label: Solution}, table rows)."""
    from .outputs import staged_folder, write_rows
    from .render import snapshots
    check_matplotlib()
    comm = problem.mesh.comm
    t = time.perf_counter()
    # the pyvista pictures may be missing: then an older report's copy goes too
    with staged_folder(out, comm, replaces=PYVISTA_PICTURES) as tmp:
        runs = run_methods(problem, say)
        peer_rows, peer_curves = run_peers(problem, say)
        summaries = {m: runs[m].summary() for m in METHOD_NAMES}      # collective
        rows = [method_row(m, summaries[m]) for m in METHOD_NAMES] + peer_rows
        figures = {m: estimator_rows(problem, runs[m]) for m in METHOD_NAMES}
        curves = [dict(r, method=m) for m in METHOD_NAMES for r in runs[m].history
                  if r["kind"] != "krylov"] + peer_curves
        final = runs["adaptive/amg"]
        cells, errors = error_distribution(final, os.path.join(tmp, "error_distribution"))
        pictures = [errors, contact_zone(final, os.path.join(tmp, "contact"))]
        # both pyvista pictures in one rendering process; one that pyvista cannot draw (not
        # importable, no OpenGL, ...) is left out, with the reason
        missing = {os.path.basename(path): why for (_, path, _), why in
                   zip(pictures, snapshots(final.disc.V, pictures)) if why}
        for why in missing.values():
            say(f"report: warning: {why}; the report goes without that picture")
        if comm.rank == 0:
            write_rows(os.path.join(tmp, "table.csv"), rows, TABLE_COLUMNS)
            write_rows(os.path.join(tmp, "error_vs_time.csv"), curves, CURVE_COLUMNS)
            plot_error_vs_time(curves, os.path.join(tmp, "error_vs_time.png"))
            for m, (frows, _) in figures.items():
                write_rows(os.path.join(tmp, f"estimators_{_slug(m)}.csv"), frows,
                           CURVE_COLUMNS[1:])
                plot_estimators(m, frows, os.path.join(tmp, f"estimators_{_slug(m)}.png"))
            text = markdown(problem, runs, summaries, rows, cells,
                            {m: f[1] for m, f in figures.items()}, time.perf_counter() - t,
                            missing)
            with open(os.path.join(tmp, "report.md"), "w", encoding="utf-8") as f:
                f.write(text)
    return runs, rows


# ## Command line: `membranes report`

def add_parser(sub):
    r = sub.add_parser("report", help="compare exact, inexact and adaptive Newton (fast and "
                       "paper solvers) with the SNES VI peers on a scene; pictures, CSVs and "
                       "report.md")
    r.add_argument("--scene", choices=("disk", "square"), default="disk",
                   help="a scene with an exact solution (default disk)")
    r.add_argument("--h", type=float, default=0.16,
                   help="gmsh target size of the coarse mesh (default 0.16)")
    r.add_argument("--levels", type=int, default=3,
                   help="uniform refinements; the runs compute on the finest mesh (default 3)")
    r.add_argument("--out", metavar="DIR", required=True, type=os.path.expanduser,
                   help="folder for the outputs (made if missing; nothing is written on bad "
                        "input)")
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    return r


def check_memory(h, levels, domain, comm, solvers=None):
    """Refuse, before meshing, a size at which a run of the Krylov presets `solvers` (default
    the report's) would not fit in memory: `checks.check_request` with the heaviest of them,
    with the ν flux's estimators, each process holding its share (what `solve` checks before
    each run, `driver.MEMORY_METHOD`). The scenes check the leanest method only: a size
    between the two was meshed, then refused by the first run's own check (`stability` too,
    where such a refusal became a failed row for every direct run)."""
    from ..model.checks import check_request, estimate_vertices, heaviest
    from .driver import MEMORY_METHOD
    vertices, _ = estimate_vertices(h, levels, domain)
    solvers = dict.fromkeys(m[2] for m in METHODS) if solvers is None else solvers
    methods = [dict(MEMORY_METHOD[solver], estimators=True, alg_flux="nu")
               for solver in solvers]
    check_request(h, levels, domain, comm=comm, processes=comm.size, replicated=False,
                  limit_option=False, **heaviest(vertices, methods))


def main(args):
    """`membranes report`: 0, or EXIT_NOT_CONVERGED when a method did not converge (the report
    is written all the same); bad input raises ValueError before anything is written."""
    from ..model import scenes
    from ..model.folders import check_output_folder
    from .cli import EXIT_NOT_CONVERGED, emit
    comm = MPI.COMM_WORLD
    check_matplotlib()
    check_output_folder(args.out, comm, names=output_names())
    check_memory(args.h, args.levels, args.scene, comm)
    problem = scenes.make(args.scene, h=args.h, levels=args.levels)
    quiet = args.quiet or comm.rank != 0
    say = (lambda line: None) if quiet else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    t = time.perf_counter()
    _, rows = write_report(problem, args.out, say)
    say(f"report: written to {args.out} in {time.perf_counter() - t:.1f} s")
    if comm.rank == 0:
        from .outputs import json_safe
        table = [{k: r.get(k) for k in TABLE_COLUMNS + ("reason",)} for r in rows]
        emit(json.dumps({"report": os.path.join(os.path.abspath(args.out), "report.md"),
                         "table": json_safe(table)}))
    failed = [r["method"] for r in rows if not r["converged"]]
    if failed:
        if comm.rank == 0:
            print(f"membranes: not converged: {', '.join(failed)}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0
