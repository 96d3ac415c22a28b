"""The package as `pip install /path/to/membranes` installs it, used outside the source tree:
the wheel holds every module of membranes/ and forms/ (pyproject.toml lists the packages by
hand, so a new subpackage missing there would work in the tree and fail installed), the
`membranes` command, and a numpy requirement that keeps numpy 2 out (Debian's petsc4py and
dolfinx 0.5.2 do not load under it); installed elsewhere, it runs from an unrelated folder
and its warm-up stamp (a hash of forms/ and membranes/ found from warmup.py's own path) is
the source tree's."""

import json
import os
import shutil
import subprocess
import sys
import zipfile

import numpy as np
import pytest
from mpi4py import MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1,
                                reason="builds and runs the package in processes of its own")


def _modules():
    """Paths in the wheel ('/'-separated) of every module of membranes/ and forms/ (they hold
    no other files: the code reads nothing else from its own folders); forms/ is the package
    membranes.forms."""
    found = set()
    for package, into in (("membranes", "membranes"), ("forms", "membranes/forms")):
        for folder, _, files in os.walk(os.path.join(ROOT, package)):
            found |= {into + "/" + os.path.relpath(os.path.join(folder, f), os.path.join(
                ROOT, package)).replace(os.sep, "/") for f in files if f.endswith(".py")}
    return found


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    """A wheel built, as pip builds it, from a copy of the sources (a build in the tree would
    leave build/ and *.egg-info there)."""
    tmp = tmp_path_factory.mktemp("install")
    src = tmp / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for package in ("membranes", "forms"):
        shutil.copytree(os.path.join(ROOT, package), src / package, ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(os.path.join(ROOT, name), src / name)
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps",
                           "--no-build-isolation", "--disable-pip-version-check", "-q",
                           "-w", str(tmp / "wheel"), str(src)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (path,) = (tmp / "wheel").iterdir()
    return path


def test_wheel_holds_every_file_the_code_needs(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        info = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        entry_points = z.read(info).decode()
    shipped = {n for n in names if n.split("/")[0] == "membranes"}
    assert not any(n.startswith("forms/") for n in names)      # (no top-level `forms`)
    assert _modules() <= shipped, sorted(_modules() - shipped)
    assert "membranes/app/render.py" in shipped          # run by its path as a script
    assert "membranes = membranes.app.cli:command" in entry_points


def test_wheel_version_is_the_package_version(wheel):
    """pyproject.toml reads the version from membranes.__version__ (written once): the
    wheel's metadata and `membranes --version` say the same."""
    import membranes
    with zipfile.ZipFile(wheel) as z:
        info = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        metadata = z.read(info).decode()
    assert f"\nVersion: {membranes.__version__}\n" in metadata
    assert os.path.basename(wheel).startswith(f"membranes-{membranes.__version__}-")


def test_numpy_requirement_keeps_numpy_2_out(wheel):
    """An unbounded `numpy` let `pip install '.[dev]'` (matplotlib, contourpy) replace the
    system's numpy 1.24 by numpy 2, and then petsc4py fails to import."""
    from packaging.requirements import Requirement
    with zipfile.ZipFile(wheel) as z:
        info = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
        metadata = z.read(info).decode()
    requires = [Requirement(line.split(":", 1)[1].strip()) for line in metadata.splitlines()
                if line.startswith("Requires-Dist:")]
    (numpy,) = [r for r in requires if r.name == "numpy" and r.marker is None]
    assert not numpy.specifier.contains("2.0.0")
    assert numpy.specifier.contains(np.__version__)      # the numpy dolfinx runs with here


def test_installed_package_runs_outside_the_tree(wheel, tmp_path):
    """Installed into a folder of its own and run from another one, with nothing of the
    source tree on the path: the modules are the installed ones, the warm-up stamp is the one
    the source tree computes (same code, same hash), and a solve converges."""
    site, work = tmp_path / "site", tmp_path / "work"
    work.mkdir()
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps",
                           "--disable-pip-version-check", "-q", "--target", str(site),
                           str(wheel)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env["PYTHONPATH"] = str(site)

    def run(*args):
        proc = subprocess.run([sys.executable, *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stdout

    from membranes.app.warmup import stamp
    where = json.loads(run("-c", "import json, membranes.forms; "
                           "from membranes.app.warmup import stamp; "
                           "print(json.dumps([membranes.__file__, membranes.forms.__file__, "
                           "str(stamp(['disk', 'square']))]))"))
    assert where[0] == str(site / "membranes" / "__init__.py")
    assert where[1] == str(site / "membranes" / "forms" / "__init__.py")
    assert where[2] == str(stamp(["disk", "square"]))
    summary = json.loads(run("-m", "membranes.app.cli", "solve", "--scene", "disk", "--h",
                             "0.5", "--levels", "1", "--out", "out", "--quiet"))
    assert summary["converged"] and summary["eta"] >= summary["energy_error"] > 0
    assert sorted(os.listdir(work / "out")) == ["history.csv", "solution.h5", "solution.xdmf",
                                                 "summary.json"]


def test_a_forms_module_of_the_users_does_not_shadow_ours(tmp_path):
    """A user's own forms.py (a natural name for one's UFL forms) beside their script, from
    the source tree (installed, the forms are membranes/forms/: the test above): the script's
    solve converges. The UFL forms were a top-level package `forms`, which the script's folder
    shadowed: `from membranes import solve` met "'forms' is not a package"."""
    (tmp_path / "forms.py").write_text("raise ImportError('the user forms.py was imported')\n")
    (tmp_path / "script.py").write_text("from membranes import scenes, solve\n"
                                        "print(solve(scenes.disk(h=0.5, levels=0)).converged)\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_"))}
    env.update(PYTHONPATH=ROOT, OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "script.py"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert (proc.returncode, proc.stdout) == (0, "True\n"), proc.stderr[-3000:]


def test_dolfinx_release_is_checked_first():
    """The code is written against dolfinx 0.5's API: 0.5.x is taken, another release is
    refused with an ImportError naming both (its `name` dolfinx, as for a missing module)."""
    from membranes.fem import require_dolfinx
    for version in ("0.5.2", "0.5.0", "0.5.3.dev0"):
        require_dolfinx(version)
    for version in ("0.9.0", "0.6.0.dev0", "0.4.1", "1.5.0", "5.0"):
        with pytest.raises(ImportError, match=rf"needs dolfinx 0\.5\.x .*found dolfinx "
                                              rf"{version.replace('.', '[.]')} ") as e:
            require_dolfinx(version)
        assert e.value.name == "dolfinx"


@pytest.mark.parametrize("command", [["solve", "--h", "0.3"], ["scenes"]])
def test_cli_on_another_dolfinx_says_so_in_one_line(command, tmp_path):
    """A dolfinx of another release (here 0.5.2 relabelled 0.9.0 before membranes is
    imported): the command line ends at once with one line, exit 1 (not bad input), and
    writes nothing."""
    script = ("import sys, dolfinx; dolfinx.__version__ = '0.9.0'; "
              "from membranes.app.cli import main; sys.exit(main(sys.argv[1:]))")
    out = tmp_path / "out"
    extra = ["--out", str(out)] if command[0] == "solve" else []
    proc = subprocess.run([sys.executable, "-c", script, *command, *extra], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "membranes: error: membranes needs dolfinx 0.5.x (Debian bookworm's python3-dolfinx "
        "0.5.2), found dolfinx 0.9.0 (README, Set-up)"]
    assert proc.stdout == ""
    assert not out.exists()


def test_setup_stops_on_another_dolfinx(tmp_path):
    """`.ci/setup` (copied, its system Python replaced by one whose dolfinx says 0.9.0) stops
    with one line before it makes a venv."""
    (tmp_path / ".ci").mkdir()
    with open(os.path.join(ROOT, ".ci", "setup")) as f:
        text = f.read()
    fake = tmp_path / "python3"
    fake.write_text('#!/bin/bash\ncase "$*" in *"print(dolfinx.__version__)"*) echo 0.9.0 ;;\n'
                    '  *) exec /usr/bin/python3 "$@" ;;\nesac\n')
    fake.chmod(0o755)
    assert text.count("SYS_PY=/usr/bin/python3\n") == 1
    (tmp_path / ".ci" / "setup").write_text(text.replace("SYS_PY=/usr/bin/python3\n",
                                                         f"SYS_PY={fake}\n"))
    proc = subprocess.run(["bash", str(tmp_path / ".ci" / "setup")], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        "setup: membranes needs dolfinx 0.5.x (Debian bookworm's python3-dolfinx 0.5.2), "
        "this system's python3-dolfinx is 0.9.0"]
    assert not (tmp_path / ".venv").exists()
