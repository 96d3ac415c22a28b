"""The README's Python example runs as printed: its code block is executed, and what it
computes is checked (a converged, certified disk run; the sweep's η one per μ2, each the η
of a run without kept set-ups, to round-off)."""

import os
from dataclasses import replace

import pytest
from mpi4py import MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process")
def test_readme_python_example(capsys):
    with open(os.path.join(ROOT, "README.md")) as f:
        text = f.read()
    start = text.index("```python\n") + len("```python\n")
    code = text[start:text.index("```", start)]
    scope = {}
    exec(compile(code, "README.md", "exec"), scope)
    sol, problem, etas = scope["sol"], scope["problem"], scope["etas"]
    assert sol.converged and sol.estimates["bound"]
    assert len(etas) == 3
    from membranes import solve
    fresh = solve(replace(problem, mu2=5, exact=None)).estimates["eta"]
    assert abs(etas[-1] - fresh) <= 1e-12 * fresh
