"""The API is quiet about JIT compilation (membranes.app.logs): a user's script that solves
with a new formula gets no setuptools build lines on stderr, while its own root-logger
records still pass."""

import os
import subprocess
import sys
import uuid

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCRIPT = """
import logging
from membranes import scenes, solve
sol = solve(scenes.user(f1="-1 + {c}*x", domain="square", h=0.4), estimators=False)
logging.getLogger().warning("mine %s", sol.converged)
"""


def test_a_new_formula_compiles_without_build_lines():
    # a coefficient no earlier run used: its forms are compiled in this process
    c = "0." + str(uuid.uuid4().int)[:12]
    done = subprocess.run([sys.executable, "-c", SCRIPT.format(c=c)], capture_output=True,
                          text=True, cwd=ROOT, timeout=300,
                          env={**os.environ, "PYTHONPATH": ROOT, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stderr.splitlines()
    assert "WARNING:root:mine True" in lines, lines[-5:]
    assert not [line for line in lines if line.startswith("INFO:root:")], lines[:5]


def test_the_filter_drops_only_distutils_chatter_below_warning():
    """setuptools' distutils logs its build steps as INFO records: those are dropped; its
    warnings and errors, and every record made elsewhere, whatever its level, pass."""
    import logging

    from membranes.app.logs import _DistutilsChatter
    chatter = _DistutilsChatter()

    def passes(level, pathname):
        return chatter.filter(logging.LogRecord("root", level, pathname, 1, "m", None, None))

    distutils = "/venv/lib/python3/site-packages/setuptools/_distutils/log.py"
    assert [passes(level, distutils) for level in (logging.DEBUG, logging.INFO,
            logging.WARNING, logging.ERROR)] == [False, False, True, True]
    assert [passes(level, "/home/me/notebook.py") for level in (logging.DEBUG, logging.INFO,
            logging.WARNING)] == [True, True, True]


def test_the_filter_is_installed_once():
    """Every `solve` and every command calls `quiet_jit_logging`: the root logger gets one
    filter however often it is called (not one more per run of a long-lived process)."""
    import logging

    from membranes.app.logs import _DistutilsChatter, quiet_jit_logging
    root = logging.getLogger()
    for _ in range(3):
        quiet_jit_logging()
    assert sum(isinstance(f, _DistutilsChatter) for f in root.filters) == 1
