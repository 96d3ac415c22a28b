"""Off-screen pyvista snapshots, run as a separate script: `python render.py DATA.npz OUT.png`.

VTK's scalar bars crash (std::bad_alloc in libstdc++'s regex) in a process that has loaded
dolfinx's C++ libraries, so the report hands the mesh and the fields to this script, which
imports numpy and pyvista only. DATA.npz holds `points` (n, 3), `cells` (VTK cell array),
`types`, and panels: `names` (k,), `kinds` ("cell"/"point"), `field_<i>` arrays, `titles`,
and optionally `clim` (shared colour range) and `cmap`.
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
    clim = data["clim"].tolist() if "clim" in data else None
    cmap = str(data["cmap"]) if "cmap" in data else "viridis"
    plotter = pv.Plotter(off_screen=True, shape=(1, len(names)),
                         window_size=(700 * len(names), 650))
    for i, name in enumerate(names):
        g = grid.copy()
        target = g.cell_data if str(data["kinds"][i]) == "cell" else g.point_data
        target[name] = data[f"field_{i}"]
        plotter.subplot(0, i)
        plotter.add_text(str(data["titles"][i]), font_size=12)
        plotter.add_mesh(g, scalars=name, clim=clim, cmap=cmap,
                         scalar_bar_args={"title": name, "vertical": False})
        plotter.view_xy()
    plotter.screenshot(png_path)
    plotter.close()


if __name__ == "__main__":
    render(sys.argv[1], sys.argv[2])
