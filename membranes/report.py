"""The report: `membranes report --scene disk --out DIR` (DESIGN §7, §8, §10).

One process, one mesh, all methods measured in the same run:

* exact, inexact and adaptive inexact semismooth Newton (`membranes.solve`, estimators on);
* the PETSc SNES `vinewtonrsls` peer on the decoupled problem (DESIGN §10, CG + BoomerAMG
  inner solves), followed iterate by iterate through `solve_decoupled(monitor=...)`: the
  energy error of every SNES iterate. Its clock starts as `solve`'s does: it discretises the
  problem itself, and that is timed.

Written into DIR (via a temporary folder, so nothing half-written is left on failure):

* `error_vs_time.png` + `error_vs_time.csv`: energy error and η against wall-clock time at the
  Newton (SNES) iterates, one curve per method;
* `estimators_<method>.png` + `estimators_<method>.csv`: η, η_disc, η_lin, η_alg against the
  cumulative GMRES iterations, Newton steps marked (the seed's figures);
* `table.csv`: Newton iterations, GMRES iterations, wall time, final energy error, η per method;
* `error_distribution.png` + `.csv`: the actual per-cell error |||u - u_h|||_K and the
  estimated η_K of the adaptive run, side by side with one logarithmic colour scale (pyvista,
  off-screen, in `render.py`);
* `contact.png` + `.csv`: u1 - u2 and λ of the adaptive run, with the scene's interface (for
  disk and square the exact free boundary) drawn in red;
* `report.md` showing all of them. Every number comes from the run.

Wall times are the history's: the method's own work from the start, discretisation included,
diagnostics (estimators where the method does not use them, energy errors) excluded (README).
matplotlib and pyvista are imported here only, when a report is asked for.
"""

import json
import os
import sys
import time

import numpy as np

from .discretisation import as_one_run
from .outputs import staged_folder, write_history

METHODS = ("exact", "inexact", "adaptive")
PEER = "snes_vi"
MAX_NEWTON = {"exact": 100, "inexact": 400, "adaptive": 100}
CURVE_COLUMNS = ("newton_it", "kind", "cumulative_linear_its", "wall_time_s", "residual",
                 "energy_error", "eta", "eta_disc", "eta_lin", "eta_alg")
TABLE_COLUMNS = ("method", "converged", "newton_iterations", "linear_iterations",
                 "wall_time_s", "energy_error", "eta", "effectivity")
TABLE_HEADINGS = ("method", "converged", "Newton (SNES) iterations", "linear iterations",
                  "wall time [s]", "energy error", "η", "η / error")


# ## The runs
#
# One after another in this process, on the problem's computational mesh. The peer's monitor
# sees every SNES iterate; its energy error is a diagnostic, outside the peer's clock.

def run_methods(problem, say):
    """Exact, inexact and adaptive Newton on `problem`: {method: Solution}."""
    from .driver import solve
    runs = {}
    for method in METHODS:
        t = time.perf_counter()
        sol = runs[method] = solve(problem, newton=method, max_newton=MAX_NEWTON[method])
        say(f"report: {method}: {sol.newton_iterations} Newton steps, "
            f"{sol.linear_iterations} GMRES steps, converged = {sol.converged} "
            f"({time.perf_counter() - t:.1f} s)")
    return runs


@as_one_run
def run_peer(problem, say):
    """SNES vinewtonrsls (CG + BoomerAMG) on the decoupled problem: (result, records), one
    record per SNES iterate (its 0: the initial guess) with its wall time, discretisation
    included as in `solve`, and its energy error."""
    from .decoupled import AMG, solve_decoupled
    from .discretisation import EnergyError, discretise
    t0 = time.perf_counter()
    disc = discretise(problem)
    setup = time.perf_counter() - t0
    error = EnergyError(disc)
    records = []

    def monitor(its, seconds, u1, u2, lam):
        records.append({"method": PEER, "kind": "initial" if its == 0 else "snes",
                        "newton_it": its, "wall_time_s": setup + seconds,
                        "energy_error": error(np.concatenate([u1, u2, lam]))})

    peer = solve_decoupled(disc, AMG, monitor=monitor)
    peer.wall_time_s += setup
    say(f"report: SNES vinewtonrsls: {peer.newton_iterations} iterations, "
        f"{peer.linear_iterations} CG steps, converged = {peer.converged}, "
        f"{peer.wall_time_s:.2f} s")
    return peer, records


# ## Curves (matplotlib)
#
# Each picture is drawn from the rows of its CSV. Missing values (η where no bound is
# available) and zeros (η_lin vanishes where an iterate meets the constraints) are left out of
# the logarithmic curves.

def _figure():
    from matplotlib.figure import Figure
    fig = Figure(figsize=(7.5, 4.8), layout="constrained")
    return fig, fig.add_subplot()


def _points(rows, x, y):
    """(x, y) of the rows where y is present and positive."""
    pts = [(r[x], r[y]) for r in rows if r.get(y) is not None and r[y] > 0]
    return tuple(zip(*pts)) if pts else ((), ())


def plot_error_vs_time(rows, path):
    """Energy error (solid) and η (dashed) against wall-clock time, one colour per method."""
    fig, ax = _figure()
    for i, method in enumerate(dict.fromkeys(r["method"] for r in rows)):
        mine = [r for r in rows if r["method"] == method]
        name = "SNES VI (decoupled)" if method == PEER else method
        ax.plot(*_points(mine, "wall_time_s", "energy_error"), "-o", ms=3, color=f"C{i}",
                label=f"{name}: energy error")
        t, eta = _points(mine, "wall_time_s", "eta")
        if eta:
            ax.plot(t, eta, "--", color=f"C{i}", label=f"{name}: η")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall-clock time [s] (from the start of the method, discretisation included)")
    ax.set_ylabel("energy error |||u - u_h|||, estimate η")
    ax.set_title("Error and estimate against time (Newton / SNES iterates)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=110)


def plot_estimators(method, history, path):
    """η, η_disc, η_lin, η_alg against cumulative GMRES iterations, Newton steps marked."""
    fig, ax = _figure()
    for key, colour in (("eta", "k"), ("eta_disc", "C0"), ("eta_lin", "C1"), ("eta_alg", "C2")):
        its, values = _points(history, "cumulative_linear_its", key)
        if values:
            ax.plot(its, values, "-", color=colour, marker=".", ms=3,
                    label=key.replace("eta", "η"))
    for r in history:
        if r["kind"] == "newton":
            ax.axvline(r["cumulative_linear_its"], color="0.8", lw=0.8, zorder=0)
    ax.set_yscale("log")
    ax.set_xlabel("cumulative GMRES iterations (grey lines: Newton steps)")
    ax.set_ylabel("estimators")
    ax.set_title(f"{method} Newton: estimators against GMRES iterations")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.savefig(path, dpi=110)


# ## Snapshots (pyvista, off-screen, in a separate process: see render.py)

def snapshot(mesh, panels, path, log=False, contour=None, cmap="viridis"):
    """Render side-by-side panels [(name, "cell"/"point", values, title)] of `mesh` to `path`:
    one colour scale for all panels if `log` (logarithmic), else one per panel; `contour`:
    point values whose zero line is drawn in red on every panel."""
    import subprocess
    from dolfinx import plot
    cells, types, x = plot.create_vtk_mesh(mesh)
    data = {"cells": cells, "types": types, "points": x,
            "names": np.array([p[0] for p in panels]), "kinds": np.array([p[1] for p in panels]),
            "titles": np.array([p[3] for p in panels]), "cmap": np.array(cmap),
            "log": np.array(log)}
    for i, p in enumerate(panels):
        data[f"field_{i}"] = np.asarray(p[2], dtype=float)
    if contour is not None:
        data["contour"] = np.asarray(contour, dtype=float)
    npz = path + ".npz"
    np.savez(npz, **data)
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "render.py")
    try:
        proc = subprocess.run([sys.executable, script, npz, path], capture_output=True,
                              text=True)
    finally:
        os.remove(npz)
    if proc.returncode != 0 or not os.path.exists(path):
        raise RuntimeError(f"rendering {os.path.basename(path)} failed: "
                           f"{proc.stderr.strip().splitlines()[-1:] or proc.returncode}")


def write_columns(path, columns):
    """A CSV of equally long named columns ({name: values})."""
    write_history(path, [dict(zip(columns, values)) for values in zip(*columns.values())],
                  tuple(columns))


def error_distribution(sol, path):
    """Actual |||u - u_h|||_K (from the exact solution) beside η_K, and the CSV behind them;
    returns both arrays."""
    from .discretisation import EnergyError
    mesh = sol.problem.mesh
    actual = EnergyError(sol.disc).per_cell(sol.X)
    ncells = mesh.topology.index_map(2).size_local
    centres = mesh.geometry.x[mesh.geometry.dofmap.array.reshape(-1, 3)[:ncells], :2].mean(1)
    write_columns(path + ".csv", {"cell": np.arange(ncells), "x": centres[:, 0],
                                  "y": centres[:, 1], "error_K": actual, "eta_K": sol.eta_K})
    snapshot(mesh, [("error_K", "cell", actual, "actual error (energy norm on each cell)"),
                    ("eta_K", "cell", sol.eta_K, "estimated error eta_K")],
             path + ".png", log=True)
    return actual, sol.eta_K


def contact_zone(sol, path):
    """u1 - u2 and λ with the scene's interface (the exact free boundary for disk and square),
    and the CSV behind them."""
    disc, problem = sol.disc, sol.problem
    n = disc.n
    u1, u2, lam = (sol.X[k * n:(k + 1) * n] for k in range(3))
    x = disc.V.tabulate_dof_coordinates()
    write_columns(path + ".csv", {"vertex": np.arange(n), "x": x[:, 0], "y": x[:, 1],
                                  "gap": u1 - u2, "lambda": lam})
    contour = None if problem.interface is None else problem.interface(x[:, :2].T)
    snapshot(problem.mesh, [("u1 - u2", "point", u1 - u2, "gap u1 - u2"),
                            ("lambda", "point", lam, "contact pressure lambda")],
             path + ".png", contour=contour, cmap="plasma")


# ## Table and report.md

def table_rows(runs, peer, peer_records):
    """One row per method (values of its summary), then the peer's."""
    rows = []
    for method, sol in runs.items():
        s = sol.summary()
        rows.append({"method": method, **{k: s[k] for k in TABLE_COLUMNS[1:]}})
    rows.append({"method": PEER, "converged": peer.converged,
                 "newton_iterations": peer.newton_iterations,
                 "linear_iterations": peer.linear_iterations, "wall_time_s": peer.wall_time_s,
                 "energy_error": peer_records[-1]["energy_error"], "eta": None,
                 "effectivity": None})
    return rows


def _fmt(v):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def markdown(problem, runs, rows, cells):
    """report.md: the table, the pictures and the numbers of this run."""
    s = runs["exact"].summary()
    actual, eta_K = cells
    lines = [f"# Report: scene `{problem.name}`", "",
             f"{s['n_vertices']} vertices, {s['n_cells']} cells, h = {s['h']:.4g} "
             f"(coarse h = {s['h_coarse']:.4g}, {s['levels']} levels). "
             f"{problem.description}.", "",
             "All methods ran in this process on this mesh, one after another; every number "
             "below comes from the run (the CSV files hold the data behind each picture). "
             "Newton: GMRES + ILU(0), estimators every ν = 10 GMRES steps. The peer "
             f"(`{PEER}`): PETSc SNES vinewtonrsls on the decoupled problem (DESIGN §10), CG + "
             "BoomerAMG inside; its iterations are SNES steps, its linear iterations CG steps. "
             "Wall times: the method's own work from its start, discretisation included; "
             "estimators count only for adaptive Newton, which uses them.", "",
             "## Newton, GMRES, time and error per method", "",
             "| " + " | ".join(TABLE_HEADINGS) + " |",
             "|" + "---|" * len(TABLE_HEADINGS)]
    lines += ["| " + " | ".join(_fmt(r[c]) for c in TABLE_COLUMNS) + " |" for r in rows]
    lines += ["", "Data: `table.csv`."]
    for method, sol in runs.items():
        if not sol.converged:
            lines += ["", f"{method}: not converged: {sol.reason}."]
    if problem.name == "disk" and problem.levels > 0:
        lines += ["", "Note: with levels ≥ 1 the computational domain is the polygon of the "
                  "coarse mesh (DESIGN §9); the energy error is measured against the disk's "
                  "exact solution, whose trace differs from g on that polygon by O(h_0²). The "
                  "estimator bounds the error of the polygon problem, not that mismatch, so η "
                  "can fall below this measured error."]
    lines += ["", "## Error and estimate against wall-clock time", "",
              "![error vs time](error_vs_time.png)", "",
              "Dots: Newton (SNES) iterates. Data: `error_vs_time.csv`.", "",
              "## Estimators against GMRES iterations", ""]
    for method in runs:
        lines += [f"![{method}](estimators_{method}.png)", "",
                  f"Data: `estimators_{method}.csv` (every recorded iterate).", ""]
    lines += ["## Error distribution (adaptive run, final iterate)", "",
              "![error distribution](error_distribution.png)", "",
              "Actual per-cell energy error |||u - u_h|||_K (left) and estimated η_K (right), "
              f"one logarithmic colour scale. Largest cell values {actual.max():.3e} (actual) "
              f"and {eta_K.max():.3e} (estimated); root sums of squares "
              f"{np.sqrt((actual ** 2).sum()):.4e} and {np.sqrt((eta_K ** 2).sum()):.4e}. "
              "Data: `error_distribution.csv`.", "",
              "## Contact zone (adaptive run, final iterate)", "",
              "![contact](contact.png)", "",
              "The gap u1 - u2 and the contact pressure λ; red: the scene's interface, the "
              "exact free boundary. Data: `contact.csv`.", ""]
    return "\n".join(lines)


def write_report(problem, out, say=lambda line: None):
    """Run the comparison on `problem` and write the report into `out`; returns the runs
    ({method: Solution}) and the table rows."""
    out = os.path.abspath(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise ValueError(f"--out {out} exists and is not a folder")
    runs = run_methods(problem, say)
    peer, peer_records = run_peer(problem, say)
    with staged_folder(out) as tmp:
        curves = [dict(r, method=method) for method, sol in runs.items() for r in sol.history
                  if r["kind"] != "krylov"] + peer_records
        write_history(os.path.join(tmp, "error_vs_time.csv"), curves,
                      ("method",) + CURVE_COLUMNS)
        plot_error_vs_time(curves, os.path.join(tmp, "error_vs_time.png"))
        for method, sol in runs.items():
            write_history(os.path.join(tmp, f"estimators_{method}.csv"), sol.history,
                          CURVE_COLUMNS)
            plot_estimators(method, sol.history, os.path.join(tmp, f"estimators_{method}.png"))
        rows = table_rows(runs, peer, peer_records)
        write_history(os.path.join(tmp, "table.csv"), rows, TABLE_COLUMNS)
        cells = error_distribution(runs["adaptive"], os.path.join(tmp, "error_distribution"))
        contact_zone(runs["adaptive"], os.path.join(tmp, "contact"))
        with open(os.path.join(tmp, "report.md"), "w") as f:
            f.write(markdown(problem, runs, rows, cells))
    return runs, rows


# ## Command line: `membranes report`

def add_parser(sub):
    r = sub.add_parser("report", help="compare exact, inexact, adaptive Newton and the PETSc "
                       "SNES VI peer on a scene; pictures, CSVs and report.md")
    r.add_argument("--scene", choices=("disk", "square"), default="disk")
    r.add_argument("--h", type=float, default=0.16,
                   help="gmsh target size of the coarse mesh (default 0.16)")
    r.add_argument("--levels", type=int, default=3,
                   help="uniform refinements; the finest mesh is computed on (default 3)")
    r.add_argument("--out", metavar="DIR", required=True)
    r.add_argument("--quiet", action="store_true")
    return r


def main(args):
    """`membranes report`: exit code 0, or 3 when a method did not converge (the report is
    written all the same); bad input raises ValueError before anything is written."""
    from . import scenes
    from .cli import EXIT_NOT_CONVERGED
    problem = scenes.make(args.scene, h=args.h, levels=args.levels)
    say = (lambda line: None) if args.quiet else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    t = time.perf_counter()
    _, rows = write_report(problem, args.out, say)
    say(f"report: written to {args.out} in {time.perf_counter() - t:.1f} s")
    print(json.dumps({"report": os.path.join(os.path.abspath(args.out), "report.md"),
                      "table": rows}))
    failed = [r["method"] for r in rows if not r["converged"]]
    if failed:
        print(f"membranes: not converged: {', '.join(failed)}", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    return 0
