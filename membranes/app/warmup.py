"""Compile the forms of the built-in scenes once, so that no timed run pays for it.

dolfinx turns every UFL form into C code the first time it meets it (FFCx generates the
code, a C compiler builds it, cffi loads it) and keeps the result in its cache,
``$XDG_CACHE_HOME/fenics`` (``~/.cache/fenics`` by default). A form is identified by its UFL
signature: the element, the integrand with the numbers written into it, the quadrature
degree. It does not depend on the mesh or its size (a form over the whole mesh is always
assembled as tagged chunks of cells, `estimation.cell_forms.chunks`, one chunk on a small
mesh), so compiling on a mesh of a few dozen cells serves every later run on the same scene,
at any h and any level and on any number of processes.

The first compilation of the disk scene's forms takes tens of seconds (BENCHMARKS.md), all of
it inside the wall time that `solve` and the report measure. This
module runs, on a tiny mesh of each built-in scene that `membranes report` and the demos use
(disk and square), every path that compiles a form of its own: the three Newton variants
with both C-functions, every Krylov preset, the ν and the multilevel algebraic flux, energy
errors, the SNES VI peers and their certificate. `make demo` and `make test` run it after the
set-up (`python -m membranes.app.warmup`).

When it has run, it leaves a stamp in the cache folder named after a hash of the code that
defines the forms (`forms/` and `membranes/`) and of the dolfinx version; while that stamp is
there, the warm-up returns at once. Deleting the cache deletes the stamp with it; changing the
code changes the hash. `--force` runs it regardless.

What it cannot warm: forms whose numbers only the user knows — a user scene's formulas f1,
f2 and the parameters of a radial scene are written into the generated code, so a new formula
compiles its load forms on first use (a second or two each).
"""

import hashlib
import sys
import time
from pathlib import Path

from mpi4py import MPI

# (scene, (h, levels)) of the tiny meshes: T_0 of a few dozen cells and one refinement, so
# that nested iteration, prolongations and the multilevel flux all run.
TINY = {"disk": (0.5, 1), "square": (0.5, 1)}


def warm_scene(name, comm=MPI.COMM_SELF):
    """Run every compiling path once on a tiny mesh of scene `name`; returns the seconds."""
    from ..model import scenes
    from .driver import solve
    from .peer import certify, nested_peer, plain_peer
    t = time.perf_counter()
    h, levels = TINY[name]
    problem = scenes.make(name, h=h, levels=levels, comm=comm)
    runs = [dict(newton="adaptive", solver="amg", errors="iterates"),
            dict(newton="adaptive", solver="paper", nested=False, alg_flux="multilevel"),
            dict(newton="exact", solver="amg", cfun="fb"),
            dict(newton="inexact", solver="paper", nested=False),
            dict(newton="exact", solver="direct")]
    for options in runs:
        solve(problem, **options)
    # η_lin and η_rec alone (schedule.LevelEstimates's gate), which a tiny run need not reach
    from ..estimation.estimators import Estimators
    from ..fem.discretisation import discretise
    disc = discretise(problem)
    gate = Estimators(disc)
    gate.linearisation(disc.vector3())
    gate.recovered(disc.vector3())
    certify(nested_peer(problem))
    plain_peer(problem)
    return time.perf_counter() - t


def stamp(names):
    """The stamp file of a warm-up of scenes `names` with the code as it is now."""
    import dolfinx

    import membranes.forms
    package = Path(__file__).resolve().parents[1]
    forms = Path(membranes.forms.__file__).resolve().parent    # (beside it in the source tree)
    digest = hashlib.sha1(dolfinx.__version__.encode())
    for path in sorted(forms.glob("*.py")):
        digest.update(f"forms/{path.name}".encode())
        digest.update(path.read_bytes())
    for path in sorted(p for p in package.rglob("*.py") if forms not in p.parents):
        digest.update(f"membranes/{path.relative_to(package).as_posix()}".encode())
        digest.update(path.read_bytes())
    from ..fem.jit import cache_folder
    return Path(cache_folder()) / f"membranes-warm-{'-'.join(names)}-{digest.hexdigest()[:16]}"


def main(argv=None):
    """`python -m membranes.app.warmup [--force] [SCENE ...]` (default: every scene of TINY)."""
    from .logs import quiet_jit_logging
    argv = list(sys.argv[1:] if argv is None else argv)
    force = "--force" in argv
    names = [a for a in argv if a != "--force"] or list(TINY)
    for name in names:
        if name not in TINY:
            raise SystemExit(f"warmup: unknown scene {name!r} (choose from: {', '.join(TINY)})")
    done = stamp(names)
    if done.exists() and not force:
        print(f"warmup: forms already compiled ({done.name})", file=sys.stderr)
        return 0
    quiet_jit_logging()
    t = time.perf_counter()
    for name in names:
        seconds = warm_scene(name)
        print(f"warmup: {name}: {seconds:.1f} s", file=sys.stderr)
    done.parent.mkdir(parents=True, exist_ok=True)
    done.touch()
    print(f"warmup: forms compiled in {time.perf_counter() - t:.1f} s (cache {done.parent})",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
