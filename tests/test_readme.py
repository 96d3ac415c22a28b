"""The README's Python example runs as printed: its code block is executed, and what it
computes is checked (a converged, certified disk run; the sweep's η one per μ2, each the η
of a run without kept set-ups, to round-off). docs/cli.md's option tables are those of the
command line: every option documented, every documented option there, with its choices."""

import os
import re
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


def test_cli_md_tables_are_the_options_of_the_command_line():
    from membranes.app.cli import _parser
    with open(os.path.join(ROOT, "docs", "cli.md")) as f:
        text = f.read()
    commands = next(a for a in _parser()._actions if a.dest == "command").choices
    for name, after in (("solve", "report"), ("report", "stability"), ("stability", "scenes")):
        section = text[text.index(f"## `membranes {name}`"):text.index(f"## `membranes {after}`")]
        cells = [re.split(r"(?<!\\)\|", line)[1] for line in section.splitlines()
                 if line.startswith("| `--")]         # (a cell's \| is no column)
        documented = {o for cell in cells for o in re.findall(r"--[a-z][a-z0-9-]*", cell)}
        actions = [a for a in commands[name]._actions if "--help" not in a.option_strings]
        assert documented == {o for a in actions for o in a.option_strings}, name
        for a in actions:
            if a.choices:
                cell = next(c for c in cells if f"`{a.option_strings[0]} " in c)
                listed = re.search(r"\{([^}]*)\}|(\w+\\\|\w+)", cell).group(0)
                assert set(re.findall(r"\w+", listed)) == set(a.choices), a.option_strings


def test_sections_cited_are_the_repositorys_own():
    """The code and documents cite the theory's sections as §N of docs/theory.md, which a clone
    holds, never by the section numbers of the design notes outside the repository, written
    "DESIGN" and "§N" (issue 32)."""
    import subprocess
    files = subprocess.run(["git", "ls-files", "*.py", "*.md"], cwd=ROOT, capture_output=True,
                           text=True, check=True).stdout.split()
    if not files:
        pytest.skip("not a git checkout")
    pattern, cited = "DESIGN " + "§", []          # (not spelt out: this file would match)
    for name in files:
        with open(os.path.join(ROOT, name), encoding="utf-8") as f:
            cited += [f"{name}:{i}" for i, line in enumerate(f, 1) if pattern in line]
    assert not cited, cited
