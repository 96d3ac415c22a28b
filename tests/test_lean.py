"""Lean runs: a run imports only what it uses (README, "Lean runs"). Each case runs in a fresh
interpreter and lists the modules it imported."""

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
