"""Off-screen pyvista snapshots, run as a separate script: `python render.py DATA.npz OUT.png`.

VTK's scalar bars crash (std::bad_alloc in libstdc++'s regex) in a process that has loaded
dolfinx's C++ libraries, so the report hands the mesh and the fields to this script, which
imports numpy and pyvista only. DATA.npz holds `points` (n, 3), `cells` (VTK cell array),
`types`, and panels: `names` (k,), `kinds` ("cell"/"point"), `field_<i>` arrays, `titles`,
`cmap`, `log` (True: one logarithmic colour scale shared by all panels, from the smallest
positive to the largest value; False: one linear scale per panel) and optionally `contour`
(point values whose zero line is drawn in red on every panel).
"""

import os
import sys

import numpy as np


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
        clim = [values[values > 0].min(), values.max()]
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


if __name__ == "__main__":
    render(sys.argv[1], sys.argv[2])
