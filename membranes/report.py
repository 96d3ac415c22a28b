"""The report: `membranes report --scene disk --out DIR` (DESIGN §7, §8, §10).

One process, one mesh, all methods measured in the same run:

* exact, inexact and adaptive inexact semismooth Newton (`membranes.solve`, estimators on);
* the PETSc SNES `vinewtonrsls` peer on the decoupled problem (DESIGN §10, CG + BoomerAMG
  inner solves), whose energy error is measured once, at its end (it has no iterate history
  of ours).

Written into DIR (via a temporary folder, so nothing half-written is left on failure):

* `error_vs_time.png` + `error_vs_time.csv`: energy error and η against wall-clock time, one
  curve per method (the peer: one point);
* `estimators_<method>.png` + `estimators_<method>.csv`: η, η_disc, η_lin, η_alg against the
  cumulative GMRES iterations, Newton steps marked (the seed's figures);
* `table.csv`: Newton iterations, GMRES iterations, wall time, final energy error, η per method;
* `error_distribution.png`: the actual per-cell error |||u - u_h|||_K and the estimated η_K of
  the adaptive run, side by side with one colour scale (pyvista, off-screen);
* `contact.png`: u1 - u2 and λ of the adaptive run (pyvista, off-screen);
* `report.md` showing all of them. Every number comes from the run.

matplotlib and pyvista are imported here only, when a report is asked for.
"""

import csv
import os
import shutil
import sys
import tempfile
import time

import numpy as np

METHODS = ("exact", "inexact", "adaptive")
CURVE_COLUMNS = ("newton_it", "kind", "cumulative_linear_its", "wall_time_s", "residual",
                 "energy_error", "eta", "eta_disc", "eta_lin", "eta_alg")
MAX_NEWTON = {"exact": 100, "inexact": 400, "adaptive": 100}


def _write_csv(path, columns, rows):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for r in rows:
            w.writerow(["" if r.get(c) is None else r[c] for c in columns])


def run_methods(problem, say):
    """The three Newton variants and the SNES VI peer on `problem`; returns (runs, peer)."""
    from .decoupled import AMG, solve_decoupled
    from .discretisation import EnergyError
    from .driver import solve
    runs = {}
    for method in METHODS:
        t = time.perf_counter()
        runs[method] = solve(problem, newton=method, max_newton=MAX_NEWTON[method])
        sol = runs[method]
        say(f"report: {method}: {sol.newton_iterations} Newton steps, "
            f"{sol.linear_iterations} GMRES steps, converged = {sol.converged} "
            f"({time.perf_counter() - t:.1f} s)")
    disc = runs["exact"].disc
    peer = solve_decoupled(disc, AMG)
    X = np.concatenate([peer.u1, peer.u2, peer.lam])
    peer_error = EnergyError(disc)(X) if problem.exact is not None else None
    say(f"report: SNES vinewtonrsls: {peer.newton_iterations} iterations, "
        f"{peer.linear_iterations} CG steps, {peer.wall_time_s:.2f} s")
    return runs, (peer, peer_error)


def _plot_error_vs_time(runs, peer, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, (method, sol) in enumerate(runs.items()):
        rows = [r for r in sol.history if r["kind"] != "krylov"]
        t = [r["wall_time_s"] for r in rows]
        c = f"C{i}"
        if rows[0].get("energy_error") is not None:
            ax.semilogy(t, [r["energy_error"] for r in rows], "-o", ms=3, color=c,
                        label=f"{method}: energy error")
        eta = [(r["wall_time_s"], r["eta"]) for r in rows if r.get("eta") is not None]
        if eta:
            ax.semilogy(*zip(*eta), "--", color=c, label=f"{method}: η")
    p, err = peer
    if err is not None:
        ax.semilogy([p.wall_time_s], [err], "k*", ms=12, label="SNES vinewtonrsls (end)")
    ax.set_xlabel("wall-clock time [s]")
    ax.set_ylabel("energy error, estimate η")
    ax.set_title("Error and estimate against run time (Newton iterates)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_estimators(method, sol, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4.5))
    its = [r["cumulative_linear_its"] for r in sol.history]
    for key, style in (("eta", "k-"), ("eta_disc", "C0-"), ("eta_lin", "C1-"),
                       ("eta_alg", "C2-")):
        pts = [(i, r[key]) for i, r in zip(its, sol.history) if r.get(key)]
        if pts:
            ax.semilogy(*zip(*pts), style, marker=".", ms=3, label=key.replace("eta", "η"))
    for r in sol.history:
        if r["kind"] == "newton":
            ax.axvline(r["cumulative_linear_its"], color="0.8", lw=0.8, zorder=0)
    ax.set_xlabel("cumulative GMRES iterations (grey lines: Newton steps)")
    ax.set_ylabel("estimators")
    ax.set_title(f"{method} Newton: estimators against GMRES iterations")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _snapshot(mesh, panels, path, clim=None, cmap="viridis"):
    """Render side-by-side panels [(name, "cell"/"point", values, title)] of `mesh` to `path`
    in a separate process (render.py: VTK cannot share a process with dolfinx here)."""
    import subprocess
    from dolfinx import plot
    cells, types, x = plot.create_vtk_mesh(mesh)
    data = {"cells": cells, "types": types, "points": x,
            "names": np.array([p[0] for p in panels]), "kinds": np.array([p[1] for p in panels]),
            "titles": np.array([p[3] for p in panels]), "cmap": np.array(cmap)}
    for i, p in enumerate(panels):
        data[f"field_{i}"] = np.asarray(p[2], dtype=float)
    if clim is not None:
        data["clim"] = np.asarray(clim, dtype=float)
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


def _snapshot_errors(sol, actual, path):
    top = float(max(actual.max(), sol.eta_K.max()))
    _snapshot(sol.problem.mesh, [("actual error", "cell", actual, "actual error |||u - u_h|||_K"),
                                 ("estimated eta_K", "cell", sol.eta_K, "estimated eta_K")],
              path, clim=[0.0, top])


def _snapshot_contact(sol, path):
    n = sol.disc.n
    u1, u2, lam = (sol.X[k * n:(k + 1) * n] for k in range(3))
    _snapshot(sol.problem.mesh, [("u1 - u2", "point", u1 - u2, "gap u1 - u2"),
                                 ("lambda", "point", lam, "contact pressure lambda")],
              path, cmap="plasma")


def table_rows(runs, peer):
    rows = []
    for method, sol in runs.items():
        s = sol.summary()
        rows.append({"method": method, "converged": s["converged"],
                     "newton_iterations": s["newton_iterations"],
                     "linear_iterations": s["linear_iterations"],
                     "wall_time_s": s["wall_time_s"], "energy_error": s["energy_error"],
                     "eta": s["eta"], "effectivity": s["effectivity"]})
    p, err = peer
    rows.append({"method": "SNES vinewtonrsls (decoupled, CG + BoomerAMG)",
                 "converged": p.converged, "newton_iterations": p.newton_iterations,
                 "linear_iterations": p.linear_iterations, "wall_time_s": p.wall_time_s,
                 "energy_error": err, "eta": None, "effectivity": None})
    return rows


TABLE_COLUMNS = ("method", "converged", "newton_iterations", "linear_iterations",
                 "wall_time_s", "energy_error", "eta", "effectivity")


def _fmt(v):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _markdown(problem, runs, rows, files):
    s = runs["exact"].summary()
    lines = [f"# Report: scene `{problem.name}`", "",
             f"{s['n_vertices']} vertices, {s['n_cells']} cells, h = {s['h']:.4g} "
             f"(coarse h = {s['h_coarse']:.4g}, {s['levels']} levels). "
             f"{problem.description}.", "",
             "All methods were run in this process on this mesh; every number below comes "
             "from the run (the CSV files hold the data behind each picture).", "",
             "## Newton, GMRES, time and error per method", "",
             "| " + " | ".join(TABLE_COLUMNS) + " |",
             "|" + "---|" * len(TABLE_COLUMNS)]
    lines += ["| " + " | ".join(_fmt(r[c]) for c in TABLE_COLUMNS) + " |" for r in rows]
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
              "![error vs time](error_vs_time.png) (data: `error_vs_time.csv`)", "",
              "## Estimators against GMRES iterations", ""]
    for method in runs:
        lines += [f"![{method}](estimators_{method}.png) (data: `estimators_{method}.csv`)", ""]
    lines += ["## Error distribution (adaptive run, final iterate)", "",
              "Actual per-cell energy error (left) and estimated η_K (right), one colour "
              "scale.", "", "![error distribution](error_distribution.png)", "",
              "## Contact zone (adaptive run)", "", "![contact](contact.png)", ""]
    return "\n".join(lines)


def write_report(problem, out, say=lambda line: None):
    """Run the comparison on `problem` and write the report into `out`."""
    from .discretisation import EnergyError
    runs, peer = run_methods(problem, say)
    out = os.path.abspath(out)
    parent = os.path.dirname(out)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=".membranes-report-", dir=parent)
    try:
        files = []
        curves = []
        for method, sol in runs.items():
            for r in sol.history:
                if r["kind"] != "krylov":
                    curves.append(dict(r, method=method))
            _write_csv(os.path.join(tmp, f"estimators_{method}.csv"), CURVE_COLUMNS,
                       sol.history)
            _plot_estimators(method, sol, os.path.join(tmp, f"estimators_{method}.png"))
        p, err = peer
        curves.append({"method": "snes_vi", "kind": "final", "wall_time_s": p.wall_time_s,
                       "energy_error": err, "newton_it": p.newton_iterations,
                       "cumulative_linear_its": p.linear_iterations})
        _write_csv(os.path.join(tmp, "error_vs_time.csv"), ("method",) + CURVE_COLUMNS, curves)
        _plot_error_vs_time(runs, peer, os.path.join(tmp, "error_vs_time.png"))
        rows = table_rows(runs, peer)
        _write_csv(os.path.join(tmp, "table.csv"), TABLE_COLUMNS, rows)
        adaptive = runs["adaptive"]
        if problem.exact is not None and adaptive.eta_K is not None:
            actual = EnergyError(adaptive.disc).per_cell(adaptive.X)
            _snapshot_errors(adaptive, actual, os.path.join(tmp, "error_distribution.png"))
        _snapshot_contact(adaptive, os.path.join(tmp, "contact.png"))
        with open(os.path.join(tmp, "report.md"), "w") as f:
            f.write(_markdown(problem, runs, rows, files))
        os.makedirs(out, exist_ok=True)
        for name in os.listdir(tmp):
            os.replace(os.path.join(tmp, name), os.path.join(out, name))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return runs, peer


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
    from . import scenes
    if args.levels < 0:
        raise ValueError(f"--levels must be a non-negative integer, got {args.levels}")
    problem = scenes.make(args.scene, h=args.h, levels=args.levels)
    say = (lambda line: None) if args.quiet else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    t = time.perf_counter()
    write_report(problem, args.out, say)
    say(f"report: written to {args.out} in {time.perf_counter() - t:.1f} s")
    return 0
