"""Lean runs: a run imports only what it uses (docs/architecture.md, "Lean runs"). Each case
runs in a fresh interpreter and lists the modules it imported."""

import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def imported(code):
    """The module names a fresh interpreter has imported after running `code`."""
    script = code + "\nimport sys, json\nprint(json.dumps(sorted(sys.modules)))\n"
    env = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", script], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return set(json.loads(run.stdout.strip().splitlines()[-1]))


def test_no_estimators_imports_no_estimator():
    """User data (no exact solution) solved without estimators: no estimator module, not even
    the energy error, and neither the report, the peers nor the pictures."""
    modules = imported(
        "from membranes.model import scenes\n"
        "from membranes.app.driver import solve\n"
        "p = scenes.make('user', h=0.4, f1='-1', f2='1', g='0.05')\n"
        "s = solve(p, estimators=False, newton='exact', solver='direct', progress=False)\n"
        "assert s.converged\n")
    assert "membranes.nonlinear.newton" in modules                     # (it did run)
    assert not {m for m in modules if m.startswith("membranes.estimation.")}
    assert not modules & {"forms.equilibration", "forms.estimators", "membranes.app.peer",
                          "membranes.app.report", "membranes.app.render", "pyvista",
                          "matplotlib"}


def test_default_run_imports_only_its_flux():
    """The defaults on the disk (ν flux): the flux equilibration and the energy error, but not
    the multilevel flux, the peers, the report or the pictures."""
    modules = imported(
        "from membranes.model import scenes\n"
        "from membranes.app.driver import solve\n"
        "s = solve(scenes.disk(h=0.4, levels=1), progress=False)\n"
        "assert s.converged and s.summary()['eta'] > 0\n")
    assert {"membranes.estimation.equilibration", "membranes.estimation.energy_error"} \
        <= modules
    assert not modules & {"membranes.estimation.multilevel", "membranes.app.peer",
                          "membranes.app.report", "membranes.app.render", "pyvista",
                          "matplotlib"}


def test_help_imports_neither_dolfinx_nor_petsc():
    """`membranes --help`, `--version` (and any refusal by the argument parser) read no mesh
    and solve nothing: no dolfinx, UFL or PETSc (they were half a second and half the memory of
    `--help`), and not the `solve` driver behind `import membranes`."""
    modules = imported(
        "from membranes.app import cli\n"
        "for argv in (['--help'], ['--version'], ['solve', '--help'], ['report', '--help'],\n"
        "             ['stability', '--help']):\n"
        "    try:\n"
        "        cli.main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "assert cli.main(['solve', '--no-such-option']) == cli.EXIT_BAD_INPUT\n")
    assert "membranes.app.cli" in modules                                 # (it did run)
    assert not modules & {"dolfinx", "ufl", "petsc4py", "petsc4py.PETSc", "gmsh",
                          "membranes.app.driver", "membranes.linalg.krylov"}


def test_solvers_of_the_command_line_are_the_presets():
    """cli.SOLVERS names the Krylov presets without importing PETSc: the same ones."""
    from membranes.app.cli import SOLVERS
    from membranes.linalg.krylov import PRESETS
    assert SOLVERS == tuple(PRESETS)


def test_import_membranes_imports_what_a_name_asks_for():
    """`import membranes` is the package only; `from membranes import solve` then brings the
    driver (and its dolfinx and PETSc), still without an estimator or the report."""
    bare = imported("import membranes\nassert membranes.__version__\n")
    assert not bare & {"dolfinx", "petsc4py", "ufl", "membranes.app.driver"}
    named = imported("import membranes\nfrom membranes import Problem, Setups, Solution, "
                     "scenes, solve\nassert membranes.solve is solve and callable(solve)\n"
                     "assert scenes.disk and Problem and Setups and Solution\n")
    assert {"membranes.app.driver", "membranes.model.scenes", "dolfinx"} <= named
    assert not {m for m in named if m.startswith("membranes.estimation.")}
    assert not named & {"membranes.app.report", "membranes.app.peer", "pyvista", "matplotlib"}


def _run(code):
    """The last line of what a fresh interpreter prints after running `code`, as JSON."""
    env = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1")
    run = subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_solve_with_out_summarises_once(tmp_path):
    """`membranes solve --out DIR`: summary.json and the JSON line are one summary, made once
    (it measures the cells of T_J and T_0: twice was a second pass over the finest mesh)."""
    out = str(tmp_path / "out")
    calls = _run(
        "import json, sys\n"
        "from membranes.app import cli\n"
        "from membranes.app.solution import Solution\n"
        "calls, summary = [], Solution.summary\n"
        "Solution.summary = lambda self: calls.append(1) or summary(self)\n"
        "code = cli.main(['solve', '--scene', 'user', '--f1', '-1', '--h', '0.4', "
        f"'--no-estimators', '--quiet', '--out', {out!r}])\n"
        "assert code == 0\n"
        "print(json.dumps(len(calls)))\n")
    assert calls == 1
    with open(os.path.join(out, "summary.json")) as f:
        assert json.load(f)["converged"] is True


def test_every_dependency_is_imported():
    """What pyproject.toml lists as dependencies `pip install` pulls in: the package imports
    each of them (threadpoolctl stayed listed after its last use had gone)."""
    import re

    import tomllib
    from packaging.requirements import Requirement
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        names = [Requirement(r).name for r in tomllib.load(f)["project"]["dependencies"]]
    sources = ""
    for package in ("membranes", "forms"):
        for folder, _, files in os.walk(os.path.join(ROOT, package)):
            for name in files:
                if name.endswith(".py"):
                    with open(os.path.join(folder, name)) as f:
                        sources += f.read()
    for name in names:
        module = name.replace("-", "_")
        assert re.search(rf"^\s*(import|from)\s+{module}\b", sources, re.M), name
