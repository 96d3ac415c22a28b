"""Shared fixtures: solves are cached per session so several tests can check one run."""

import functools
import os
import shutil
import subprocess
import sys

from membranes import scenes, solve
from membranes.app.logs import quiet_jit_logging

quiet_jit_logging()


@functools.lru_cache(maxsize=None)
def scene(name, h, **kwargs):
    return scenes.make(name, h=h, **kwargs)


@functools.lru_cache(maxsize=None)
def solved(name, h, cfun="min", system=None):
    """A cached exact solve without estimators (the tests of the discrete solution)."""
    return solve(scene(name, h), newton="exact", cfun=cfun, system=system, estimators=False)


@functools.lru_cache(maxsize=None)
def solved_with(name, h, **options):
    """A cached solve with any options of `membranes.solve` (e.g. solver="direct")."""
    return solve(scene(name, h), **options)


def write_msh(path, kind):
    """Write a small gmsh file: 'triangles', 'quads' (recombined), 'box' (3D), 'p2' or 'one'
    (a single triangle)."""
    import gmsh
    gmsh.initialize([])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(kind)
        if kind == "one":
            points = [gmsh.model.geo.addPoint(x, y, 0, 10.0) for x, y in ((0, 0), (1, 0), (0, 1))]
            lines = [gmsh.model.geo.addLine(points[i], points[(i + 1) % 3]) for i in range(3)]
            gmsh.model.geo.addPlaneSurface([gmsh.model.geo.addCurveLoop(lines)])
            gmsh.model.geo.synchronize()
            gmsh.model.mesh.generate(2)
        elif kind == "box":
            gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(3, [1], 1)
            gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.5)
            gmsh.model.mesh.generate(3)
        else:
            gmsh.model.occ.addRectangle(0, 0, 0, 2, 1)
            gmsh.model.occ.synchronize()
            gmsh.option.setNumber("Mesh.CharacteristicLengthMax", 0.2)
            if kind == "quads":
                gmsh.option.setNumber("Mesh.RecombineAll", 1)
            gmsh.model.mesh.generate(2)
            if kind == "p2":
                gmsh.model.mesh.setOrder(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return path


@functools.lru_cache(maxsize=None)
def solved_on(name, h, levels, **options):
    """A cached solve on a scene with a mesh hierarchy of `levels` uniform refinements."""
    return solve(scene(name, h, levels=levels), **options)


def cli_bad_input(args, out, capsys):
    """`membranes solve --quiet [--h 0.3] --out OUT ARGS` must reject its input: exit code 2,
    one stderr line 'membranes: error: …', nothing written to OUT. Returns the line. (--h 0.3
    keeps a valid run cheap; it is left out where ARGS give --mesh or --h themselves.)"""
    from membranes.app.cli import main
    size = [] if "--mesh" in args or "--h" in args else ["--h", "0.3"]
    code = main(["solve", "--quiet"] + size + ["--out", str(out)] + args)
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("membranes: error: ") and "\n" not in err
    assert not out.exists()
    return err


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def mpirun(args, processes=2, timeout=120, extra=(), unset=(), environ=None):
    """`mpirun [extra] -n processes python args…` (oversubscribed, as root too) from a test
    run serially, in the repository: the environment without this process's own MPI
    variables (it is an MPI singleton: they would confuse the new mpirun) nor the variables
    `unset`, with the variables `environ` (a dict), one BLAS thread, the repository on the
    path. Returns the CompletedProcess (text output captured)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("OMPI_", "PMIX_")) and k not in unset}
    env.update(environ or {})
    env.update(OMP_NUM_THREADS="1", PYTHONPATH=ROOT)
    return subprocess.run([shutil.which("mpirun"), "--allow-run-as-root", "--oversubscribe",
                           *extra, "-n", str(processes), sys.executable, *map(str, args)],
                          cwd=ROOT, capture_output=True, text=True, timeout=timeout, env=env)


def aspect_ratios(mesh):
    """Longest edge over smallest altitude, h_K² / (2 |K|), of every owned cell."""
    from membranes.fem.meshes import cell_vertices, stretches
    return stretches(cell_vertices(mesh))
