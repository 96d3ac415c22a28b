"""Off-screen pyvista pictures of fields on the mesh, for the report.

VTK's scalar bars crash (std::bad_alloc in libstdc++'s regex) in a process that has loaded
dolfinx's C++ libraries, so the pictures are drawn by this file run as a separate script,
`python render.py DATA.npz OUT.png [DATA2.npz OUT2.png ...]`, which imports numpy and pyvista
only (once for all the pictures it is given: the import is most of a small picture's time).
`snapshots` (the dolfinx side) gathers the cells of the distributed mesh and the fields onto
process 0 — for pictures only, which a report can afford — writes one DATA.npz per picture
and runs the script once; `snapshot` draws one picture.

DATA.npz holds `points` (n, 3), `cells` (VTK cell array), `types`, and panels: `names` (k,),
`kinds` ("cell"/"point"), `field_<i>` arrays, `titles`, `cmap`, `log` (True: one logarithmic
colour scale shared by all panels, from the smallest to the largest positive value, NaN values
drawn in the NaN colour; False: one linear scale per panel) and optionally `contour` (point
values whose zero line is drawn in red on every panel).

**Gathered mesh.** Every owned cell of every process goes to process 0 as a triangle with three
points of its own (3 points per cell, in cell order of process 0, 1, …): no global vertex
numbering is needed, and a P1 field sampled at these points draws exactly as on the shared
vertices.
"""

import os
import re
import sys

import numpy as np

VTK_TRIANGLE = 5
RENDER_SECONDS = 300        # a picture of a report's mesh takes seconds; a hung GL driver not
ANSI = re.compile(r"\x1b\[[0-9;]*m")     # VTK colours its log lines
FAILED = "render: failed: "                 # how the script names a picture it could not draw


# ## The script side (numpy and pyvista only)

def render(data_path, png_path):
    if not os.environ.get("DISPLAY"):
        # without an X display VTK's default window aborts; its EGL window renders headless
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv
    pv.OFF_SCREEN = True
    data = np.load(data_path, allow_pickle=False)
    grid = pv.UnstructuredGrid(data["cells"], data["types"], data["points"])
    names = [str(n) for n in data["names"]]
    fields = [data[f"field_{i}"] for i in range(len(names))]
    log = bool(data["log"])
    clim = None
    if log:
        values = np.concatenate(fields)
        # (NaN, a panel without values such as a run's missing η_K, is left out: a colour
        # range ending at NaN drew every panel in one colour)
        positive = values[values > 0]
        clim = [positive.min(), positive.max()] if positive.size else [1e-300, 1.0]
    line = None
    if "contour" in data:
        grid.point_data["contour"] = data["contour"]
        line = grid.contour([0.0], scalars="contour")
    plotter = pv.Plotter(off_screen=True, shape=(1, len(names)),
                         window_size=(700 * len(names), 650))
    for i, name in enumerate(names):
        g = grid.copy()
        target = g.cell_data if str(data["kinds"][i]) == "cell" else g.point_data
        target[name] = np.maximum(fields[i], clim[0]) if log else fields[i]
        plotter.subplot(0, i)
        plotter.add_text(str(data["titles"][i]), font_size=12)
        plotter.add_mesh(g, scalars=name, clim=clim, log_scale=log, cmap=str(data["cmap"]),
                         scalar_bar_args={"title": name, "vertical": False, "fmt": "%.2e",
                                          "position_x": 0.12, "width": 0.72})
        if line is not None and line.n_points:
            plotter.add_mesh(line, color="red", line_width=3)
        plotter.view_xy()
    plotter.screenshot(png_path)
    plotter.close()


# ## The dolfinx side: gather onto process 0 (collective on the mesh's communicator)

def _gather(comm, local):
    """The arrays of all processes concatenated on process 0 (None elsewhere)."""
    parts = comm.gather(np.asarray(local), root=0)
    return np.concatenate(parts) if comm.rank == 0 else None


def cell_points(V):
    """Coordinates (owned cells, 3, 3) of the P1 dofs of every owned cell of V's mesh."""
    mesh = V.mesh
    nc = mesh.topology.index_map(2).size_local
    dofs = V.dofmap.list.array.reshape(-1, 3)[:nc]
    return V.tabulate_dof_coordinates()[dofs]


def at_cell_vertices(V, f):
    """A P1 Function's values at the three dofs of every owned cell, (owned cells, 3)."""
    nc = V.mesh.topology.index_map(2).size_local
    return f.x.array[V.dofmap.list.array.reshape(-1, 3)[:nc]]


def gather_points(V):
    """(points (3 c, 3), cell centres (c, 2)) of all owned cells on process 0."""
    p = cell_points(V)
    return _gather(V.mesh.comm, p.reshape(-1, 3)), _gather(V.mesh.comm, p.mean(axis=1)[:, :2])


def gather_cells(comm, values):
    """Values on the owned cells (in mesh order), gathered on process 0."""
    return _gather(comm, values)


def gather_vertices(V, f):
    """A P1 Function at the gathered points (3 per cell) on process 0."""
    return _gather(V.mesh.comm, at_cell_vertices(V, f).reshape(-1))


def snapshot(V, panels, path, log=False, contour=None, cmap="viridis"):
    """Render side-by-side panels [(name, "cell"/"point", values, title)] to `path` (PNG):
    one colour scale for all panels if `log` (logarithmic), else one per panel; `contour`: a
    function of the points (2, n) whose zero line is drawn in red. Values: "cell" panels the
    owned cells' values (mesh order), "point" panels P1 Functions on V. Collective; process 0
    renders, and every process raises RuntimeError if the rendering failed (its data file
    not written included)."""
    error, = snapshots(V, [(panels, path, dict(log=log, contour=contour, cmap=cmap))])
    if error is not None:
        raise RuntimeError(error)


def snapshots(V, pictures):
    """`snapshot` of several pictures [(panels, path, options)] on V's mesh in one rendering
    process (module notes). Returns, on every process, per picture None (drawn) or why it
    is missing (one line); a missing picture leaves no file. Collective."""
    import subprocess
    comm = V.mesh.comm
    points, _ = gather_points(V)
    gathered = [[gather_cells(comm, values) if kind == "cell" else gather_vertices(V, values)
                 for _, kind, values, _ in panels] for panels, _, _ in pictures]
    errors = [None] * len(pictures)
    if comm.rank == 0:
        c = len(points) // 3
        cells = np.column_stack([np.full(c, 3), np.arange(3 * c).reshape(c, 3)]).ravel()
        paths = [path for _, path, _ in pictures]
        names = [os.path.basename(path) for path in paths]
        written = []
        try:
            for (panels, path, options), fields in zip(pictures, gathered):
                written.append(path + ".npz")
                np.savez(written[-1], **_data(cells, points, panels, fields, **options))
            proc = subprocess.run([sys.executable, os.path.abspath(__file__),
                                   *[a for pair in zip(written, paths) for a in pair]],
                                  capture_output=True, text=True, timeout=RENDER_SECONDS)
            lines = [line.strip() for line in ANSI.sub("", proc.stderr).splitlines()
                     if line.strip()]
            # what spoilt a picture that names no failure of its own: the process's last
            # line that is not another picture's failure, or its exit code
            own = [line for line in lines if not line.startswith(FAILED)]
            crash = own[-1] if own else f"exit code {proc.returncode}"
            for i, path in enumerate(paths):
                named = [line[len(FAILED + path) + 2:] for line in lines
                         if line.startswith(f"{FAILED}{path}: ")]
                if named:
                    errors[i] = f"rendering {names[i]} failed: {named[-1]}"
                elif proc.returncode != 0 or not os.path.exists(path):
                    errors[i] = f"rendering {names[i]} failed: {crash}"
        except subprocess.TimeoutExpired:
            errors = [f"rendering {name} failed: no picture in {RENDER_SECONDS} s"
                      for name in names]
        except OSError as e:    # a data file not written (raised, it left the others waiting)
            errors = [f"rendering {name} failed: {type(e).__name__}: {e}" for name in names]
        finally:
            for npz in written:
                if os.path.exists(npz):
                    os.remove(npz)
        for path, error in zip(paths, errors):
            if error is not None and os.path.exists(path):      # no half-drawn picture
                os.remove(path)
    return comm.bcast(errors, root=0)


def _data(cells, points, panels, fields, log=False, contour=None, cmap="viridis"):
    """The contents of one picture's DATA.npz (module notes)."""
    c = len(cells) // 4
    data = {"cells": cells, "types": np.full(c, VTK_TRIANGLE, dtype=np.uint8),
            "points": points, "names": np.array([p[0] for p in panels]),
            "kinds": np.array([p[1] for p in panels]),
            "titles": np.array([p[3] for p in panels]), "cmap": np.array(cmap),
            "log": np.array(log)}
    for i, values in enumerate(fields):
        data[f"field_{i}"] = np.asarray(values, dtype=float)
    if contour is not None:
        data["contour"] = np.asarray(contour(points[:, :2].T), dtype=float)
    return data


def render_all(pairs):
    """Render every (DATA.npz, OUT.png) pair; a picture that raises is named on stderr in one
    line (FAILED, its path, the error) and the others are still drawn. Exit code 0: any
    other code is a crash (a GL driver's at exit, say), which spoils every picture."""
    for data_path, png_path in pairs:
        try:
            render(data_path, png_path)
        except Exception as e:
            print(f"{FAILED}{png_path}: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(render_all(zip(sys.argv[1::2], sys.argv[2::2])))
