"""Bad input: one-line error and exit code 2 from the CLI, ValueError from the API, and nothing
written to the output folder."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from membranes import Problem, scenes, solve
from membranes.fem.hierarchy import build_hierarchy
from membranes.fem.mesh_files import read_msh
from membranes.fem.meshes import unit_disk
from membranes.model.expressions import Formula

from .conftest import cli_bad_input, mpirun, scene, write_msh


@pytest.fixture(scope="module")
def bad_meshes(tmp_path_factory):
    d = tmp_path_factory.mktemp("meshes")
    garbage = d / "garbage.msh"
    garbage.write_text("this is not a mesh\n")
    return {"missing": str(d / "missing.msh"),
            "directory": str(d),
            "garbage": str(garbage),
            "quads": str(write_msh(d / "quads.msh", "quads")),
            "p2": str(write_msh(d / "p2.msh", "p2")),
            "box": str(write_msh(d / "box.msh", "box"))}


def _balanced(terms):
    """The sum of `terms`, parenthesised as a balanced tree: nested about log2(n) deep."""
    while len(terms) > 1:
        terms = [f"({a} + {b})" for a, b in zip(terms[::2], terms[1::2])] + \
            ([terms[-1]] if len(terms) % 2 else [])
    return terms[0]


def _series(n):
    """A Fourier series of n terms, 23 n - 2 parts (`expressions.MAX_PARTS` is 20000)."""
    return _balanced([f"sin({k}*x)*cos({k}*y)/{k**2}" for k in range(1, n + 1)])


CLI_CASES = {
    "mu1 zero": ["--mu1", "0"],
    "mu2 negative": ["--mu2", "-2"],
    "g zero": ["--g", "0"],
    "g negative": ["--g", "-0.1"],
    "mu1 nan": ["--mu1", "nan"],
    "g inf": ["--g", "inf"],
    "mu1 not a number": ["--mu1", "abc"],
    "expr syntax": ["--f1", "sin(x"],
    "expr unknown name": ["--f1", "z + 1"],
    "expr unknown function": ["--f2", "tan(x)"],
    "expr attribute": ["--f1", "x.real"],
    "expr wrong arity": ["--f1", "sin(x, y)"],
    "expr not finite": ["--f1", "1/(x - x)"],
    "expr nan": ["--f2", "sqrt(x - 5)"],
    "levels negative": ["--levels", "-1"],
    "h zero": ["--h", "0"],
    "h nan": ["--h", "nan"],
    "unknown option": ["--bogus"],
    "coarse tol zero": ["--coarse-tol", "0"],
    "coarse unknown": ["--coarse", "never"],
    "data with disk scene": ["--scene", "disk", "--f1", "1"],
    # an option given twice: argparse kept the last value and dropped the first unsaid
    "option twice": ["--h", "0.3", "--h", "0.2"],
    "option twice, = form": ["--h=0.3", "--h", "0.3"],
    "formula twice": ["--f1", "-1", "--f1", "-2"],
    "nested and no-nested": ["--levels", "1", "--nested", "--no-nested"],
    # finite data whose scale overflows double precision (theory §11: the solution scales with
    # f / mu and g): in the weighted loads, and in the estimators only
    "loads overflow": ["--f1", "-1e300"],
    "tiny modulus overflows": ["--f1", "-1", "--mu1", "1e-300"],
    "g overflows": ["--g", "1e300"],
    "estimators overflow": ["--f1", "-1", "--mu1", "1e300"],
    # ... and whose scale underflows it: residuals at round-off square to 0, and the adaptive
    # run stopped after one step with λ = 0 and η = 0 at g = 1e-161 (probe C)
    "g underflows": ["--g", "1e-200"],
    "data underflow": ["--f1", "-1e-160", "--g", "1e-161"],
    # ... or whose forces (mu u) underflow in the estimators' squares: eta = 0 (probe stiff2)
    "estimators underflow": ["--f1", "-1e-170", "--mu1", "1e-40", "--mu2", "1e-40",
                             "--g", "1e-130"],
    # formulas that raised RecursionError, OverflowError or a C compile error (probe B)
    "expr too deep": ["--f1", "+".join(["x"] * 1500)],
    "expr unary too deep": ["--f1", "-" * 1500 + "x"],
    "expr constant too large": ["--f1", "min(2**10**10, x)"],
    "expr huge integer": ["--f1", "1" + "0" * 400],
    "expr inf inside": ["--f1", "min(1e400, x) - 1"],
    "expr inf number in a finite part": ["--f1", "tanh(1e400)"],
    # a long formula kept shallow by parentheses: minutes in the C compiler (probe F)
    "expr too large": ["--f1", _series(1000)],
}
MESH_CASES = ("missing", "directory", "garbage", "quads", "p2", "box")
# what each is refused for (a later check refused some of them too, for another reason)
MESH_REASONS = {"missing": r"does not exist$", "directory": r"is not a file$",
                "garbage": r"is not a gmsh \.msh file nor an XDMF file",
                "quads": r"is not a linear triangular mesh \(cells: Quadrilateral 4\)$",
                "p2": r"is not a linear triangular mesh \(cells: Triangle 6\)$",
                "box": r"is 3D; a 2D triangular mesh is required$"}


@pytest.mark.parametrize("case", sorted(CLI_CASES))
def test_cli_bad_values(case, tmp_path, capsys):
    err = cli_bad_input(CLI_CASES[case], tmp_path / "out", capsys)
    assert "Traceback" not in err
    if "overflow" in case:
        assert "overflow double precision" in err
    if "underflow" in case:
        assert "underflow double precision" in err


def test_estimators_underflow_is_refused_before_the_coarse_levels(tmp_path, capsys):
    """Forces whose squares underflow the estimators (μ u ≈ 1e-170) are refused on T_0 of a
    nested run, before its first Newton step, not after the coarse levels' solves when the
    certificate is set up on T_J: no Newton line precedes the error."""
    from membranes.app.cli import main
    out = tmp_path / "out"
    args = CLI_CASES["estimators underflow"]
    assert main(["solve", "--h", "0.3", "--levels", "2", "--out", str(out)] + args) == 2
    err = capsys.readouterr().err
    assert "estimators underflow double precision" in err.strip().splitlines()[-1]
    assert "Newton" not in err and "setting up" not in err
    assert not out.exists()


@pytest.mark.parametrize("command", [["report", "--h", "0.3", "--h", "0.2"],
                                     ["stability", "--cases", "tiny", "--cases", "grazing"],
                                     ["solve", "--no-estimators", "--no-estimators"]])
def test_cli_option_given_twice(command, tmp_path, capsys):
    """`report` and `stability` refuse an option given twice too, and every command a flag
    given twice (no run, nothing written)."""
    from membranes.app.cli import main
    out = tmp_path / "out"
    assert main(command + ["--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"membranes: error: argument {command[1]}: given more than once"
    assert not out.exists()


@pytest.mark.parametrize("command", [["solve", "--lev", "1"], ["solve", "--no-est"],
                                     ["report", "--lev", "1"]])
def test_cli_abbreviated_option_is_unknown(command, tmp_path, capsys):
    """An abbreviation is an unknown option (argparse would take `--lev` for --levels, and a
    later `--levels` would then be 'given more than once')."""
    from membranes.app.cli import main
    out = tmp_path / "out"
    assert main(command + ["--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("membranes: error: unrecognized arguments: " + command[1])
    assert not out.exists()


@pytest.mark.parametrize("given, said", [(["--levels", "1"], "--levels 1"),
                                         (["--levels=1"], "--levels=1"),
                                         (["--f1", "-1+y", "--g", "2"], "--f1 -1+y --g 2")])
def test_cli_unknown_option_said_as_given(given, said, tmp_path, capsys):
    """An option a command does not take is quoted as it was typed: `stability --levels 1`
    said "--levels=1", the form the parser sees (a value may start with '-')."""
    from membranes.app.cli import main
    out = tmp_path / "out"
    assert main(["stability", "--out", str(out)] + given) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"membranes: error: unrecognized arguments: {said}"
    assert not out.exists()


@pytest.mark.parametrize("case", MESH_CASES)
def test_cli_bad_meshes(case, bad_meshes, tmp_path, capsys):
    err = cli_bad_input(["--mesh", bad_meshes[case]], tmp_path / "out", capsys)
    assert bad_meshes[case] in err


def test_cli_process_exit_code_and_clean_stderr(tmp_path):
    """The installed entry point, as a user runs it: exit 2, one stderr line, no traceback."""
    out = tmp_path / "out"
    exe = [sys.executable, "-m", "membranes.app.cli"]
    proc = subprocess.run(exe + ["solve", "--mu1", "-1", "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "mu1" in proc.stderr
    assert not out.exists()
    proc = subprocess.run(exe + ["solve", "--f1", "exp(", "--out", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0
    assert not out.exists()


@pytest.mark.parametrize("processes", [1, 2])
def test_a_jit_cache_that_cannot_be_made_is_refused_before_meshing(processes, tmp_path):
    """The folder dolfinx compiles forms into ($XDG_CACHE_HOME/fenics) cannot be created
    (here under a file; a home folder that is read-only or missing, as on some compute nodes
    and in containers, alike): one line naming it and XDG_CACHE_HOME, exit 2, nothing written,
    before gmsh runs; it was three chained tracebacks and exit 1 at the first compilation."""
    (tmp_path / "file").write_text("")
    out = tmp_path / "out"
    args = ["-m", "membranes.app.cli", "solve", "--h", "0.3", "--levels", "0", "--out",
            str(out)]
    cache = {"XDG_CACHE_HOME": str(tmp_path / "file")}
    proc = subprocess.run([sys.executable] + args, capture_output=True, text=True,
                          env=dict(os.environ, OMP_NUM_THREADS="1", **cache)) \
        if processes == 1 else mpirun(args, processes, environ=cache)
    folder = tmp_path / "file" / "fenics"
    assert proc.returncode == 2, proc.stderr
    ours = proc.stderr if processes == 1 else \
        proc.stderr.split("-" * 10)[0]         # (mpirun's own note on the exit code follows)
    assert ours == (f"membranes: error: the JIT cache folder {folder} cannot be written (Not "
                    f"a directory): dolfinx compiles the forms there; set XDG_CACHE_HOME to a "
                    f"writable folder\n")
    assert not out.exists()


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs Linux's /dev/full")
@pytest.mark.parametrize("args", [["scenes"], ["--help"], ["--version"],
                                  ["solve", "--h", "0.4", "--levels", "0", "--quiet"]],
                         ids=["scenes", "help", "version", "solve"])
def test_a_stdout_that_cannot_be_written_is_one_line(args, tmp_path):
    """stdout on a full disk (/dev/full fails every write with ENOSPC): one stderr line
    naming it, exit 2, as for an output folder that cannot be written; it was a traceback
    and exit 1 (and for --help the failed flush again at the interpreter's exit). A solve's
    outputs, written before its summary line, are complete."""
    out = tmp_path / "out"
    if args[0] == "solve":
        args = args + ["--out", str(out)]
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "membranes.app.cli"] + args, stdout=full,
                              stderr=subprocess.PIPE, text=True, env=dict(os.environ,
                                                                          OMP_NUM_THREADS="1"))
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == ("membranes: error: standard output cannot be written: No space "
                           "left on device\n")
    if args[0] == "solve":
        assert sorted(os.listdir(out)) == ["history.csv", "solution.h5", "solution.xdmf",
                                           "summary.json"]



@pytest.mark.parametrize("encoding", ["latin-1", "ascii"])
def test_a_stdout_without_a_character_gets_its_escape(encoding):
    """stdout in an encoding without μ (a Latin-1 or ASCII locale): `membranes scenes`
    prints it as an escape and exits 0, as Python prints on stderr; it said "membranes:
    error: 'latin-1' codec can't encode character '\\u03bc' …" and exited 2, as bad input."""
    proc = subprocess.run([sys.executable, "-m", "membranes.app.cli", "scenes"],
                          capture_output=True, env=dict(os.environ, PYTHONIOENCODING=encoding))
    assert (proc.returncode, proc.stderr) == (0, b""), proc.stderr
    assert b"\\u03bc1 = 1, \\u03bc2 = 2" in proc.stdout


def test_a_run_that_does_not_converge_exits_3_with_its_outputs(tmp_path, capsys):
    """docs/cli.md: a run that does not converge exits with 3, says so in one stderr line
    after its JSON line, and writes its outputs all the same, with converged = false and the
    reason (only bad input and interrupts leave --out empty)."""
    from membranes.app.cli import EXIT_NOT_CONVERGED, main
    out = tmp_path / "out"
    code = main(["solve", "--quiet", "--h", "0.3", "--max-newton", "1", "--out", str(out)])
    captured = capsys.readouterr()
    assert code == EXIT_NOT_CONVERGED == 3
    line = json.loads(captured.out)
    with open(out / "summary.json") as f:
        summary = json.load(f)
    assert line["converged"] is False and summary["converged"] is False
    assert captured.err == f"membranes: not converged: {summary['reason']}\n"
    assert sorted(p.name for p in out.iterdir()) == ["history.csv", "solution.h5",
                                                     "solution.xdmf", "summary.json"]


def test_an_error_of_several_lines_is_said_in_one(monkeypatch, capsys):
    """Exit 2 comes with one stderr line: an error whose text has line breaks and runs of
    spaces (PETSc's and gmsh's messages have them) is joined into one line, the words kept."""
    from membranes.app import cli, driver

    def failing_solve(problem, **kwargs):
        raise ValueError("first line\n   second  line\n")

    monkeypatch.setattr(driver, "solve", failing_solve)
    assert cli.main(["solve", "--quiet", "--h", "0.4"]) == cli.EXIT_BAD_INPUT
    assert capsys.readouterr().err == "membranes: error: first line second line\n"


def test_a_home_path_is_expanded(tmp_path, monkeypatch, capsys):
    """`--out=~/x` (the shell expands a `~` that starts a word, not one after `=`): the
    outputs go into the home folder's x, as the shell's `--out ~/x` puts them; they went
    into a folder named `~` in the working folder. The same for every path option."""
    from membranes.app import cli
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    parse = cli._parser().parse_args
    home = str(tmp_path / "home")
    assert parse(["solve", "--out=~/a", "--mesh=~/m.msh"]).out == home + "/a"
    assert parse(["solve", "--mesh=~/m.msh"]).mesh == home + "/m.msh"
    assert parse(["report", "--out=~/r"]).out == home + "/r"
    assert parse(["stability", "--out=~/s"]).out == home + "/s"
    assert cli.main(["solve", "--quiet", "--h", "0.4", "--out=~/a"]) == 0
    assert sorted(os.listdir(tmp_path / "home" / "a")) == [
        "history.csv", "solution.h5", "solution.xdmf", "summary.json"]
    assert os.listdir(tmp_path) == ["home"]


@pytest.mark.parametrize("kind", ["numpy", "petsc"])
def test_running_out_of_memory_is_one_line(kind, monkeypatch, capsys):
    """An allocation that fails during the run, numpy's MemoryError or PETSc's own error
    (under `ulimit -v`, which the size checks do not count: the run's failures were a
    traceback, exit 1, or hypre's MPI_Abort): one line naming it and the process's limits,
    exit 2. PETSc's is met for real, under an address-space limit set here for a moment."""
    import resource

    from petsc4py import PETSc

    from membranes.app import cli, driver

    def failing_solve(problem, **kwargs):
        if kind == "numpy":
            raise MemoryError("Unable to allocate 8 GiB")
        soft, hard = resource.getrlimit(resource.RLIMIT_AS)
        with open("/proc/self/status") as f:
            size = next(int(line.split()[1]) for line in f if line.startswith("VmSize"))
        resource.setrlimit(resource.RLIMIT_AS, ((size << 10) + (64 << 20), hard))
        try:
            PETSc.Vec().createSeq(1 << 27)          # 1 GiB of doubles
        finally:
            resource.setrlimit(resource.RLIMIT_AS, (soft, hard))

    monkeypatch.setattr(driver, "solve", failing_solve)
    assert cli.main(["solve", "--quiet", "--h", "0.4"]) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    what = "Unable to allocate 8 GiB" if kind == "numpy" else "PETSc could not allocate memory"
    assert err == f"membranes: error: out of memory ({what})\n"


# (argv after `solve`; the scene and its arguments `scenes.make` gets; the arguments `solve`
# gets besides the problem) for one run of each kind, every option given a value other than
# its default
OPTIONS_TO_SOLVE = {
    "exact": (["--h", "0.4", "--levels", "1", "--no-nested", "--newton", "inexact", "--cfun",
               "fb", "--solver", "paper", "--system", "eliminated", "--petsc-options",
               "-ksp_gmres_restart 50", "--nu", "5", "--max-linear-its", "500", "--tol", "1e-9",
               "--max-newton", "7", "--initial-guess", "zero", "--max-vertices", "100000",
               "--quiet"],
              ("disk", {"levels": 1, "h": 0.4, "max_vertices": 100000}),
              dict(newton="inexact", cfun="fb", solver="paper", system="eliminated",
                   petsc_options={"ksp_gmres_restart": "50"}, nu=5, max_linear_its=500,
                   tol=1e-9, max_newton=7, estimators=True, progress=False, gamma_lin=None,
                   gamma_alg=None, alg_flux=None, initial_guess="zero", nested=False,
                   max_vertices=100000, coarse="residual", coarse_tol=None)),
    "adaptive estimated": (
        ["--f1", "-1", "--f2", "-x*y", "--domain", "square", "--h", "0.4", "--levels", "1",
         "--gamma-lin", "0.2", "--gamma-alg", "0.1", "--alg-flux", "multilevel", "--coarse",
         "estimated", "--quiet"],
        ("user", {"levels": 1, "h": 0.4, "f1": "-1", "f2": "-x*y", "domain": "square",
                  "max_vertices": None}),
        dict(newton=None, cfun="min", solver="amg", system=None, petsc_options={}, nu=None,
             max_linear_its=None, tol=None, max_newton=100, estimators=True, progress=False,
             gamma_lin=0.2, gamma_alg=0.1, alg_flux="multilevel", initial_guess="paper",
             nested=None, max_vertices=None, coarse="estimated", coarse_tol=None)),
    "adaptive residual": (
        ["--scene", "square", "--h", "0.4", "--levels", "1", "--nested", "--coarse",
         "residual", "--coarse-tol", "1e-5", "--newton", "adaptive"],
        ("square", {"levels": 1, "h": 0.4, "max_vertices": None}),
        dict(newton="adaptive", cfun="min", solver="amg", system=None, petsc_options={},
             nu=None, max_linear_its=None, tol=None, max_newton=100, estimators=True,
             progress=True, gamma_lin=None, gamma_alg=None, alg_flux=None,
             initial_guess="paper", nested=True, max_vertices=None, coarse="residual",
             coarse_tol=1e-5)),
}


@pytest.mark.parametrize("case", sorted(OPTIONS_TO_SOLVE))
def test_each_option_reaches_its_argument_of_solve(case, monkeypatch, capsys):
    """`membranes solve` hands each option to the argument of `scenes.make` or `solve` of its
    name, with its value: the tests of bad input see only the options `check_method` refuses,
    so an option dropped or handed to another argument on its way to `solve` went unseen.
    `solve` is replaced by one that records its arguments and stops the run; with --quiet
    nothing but the stop's error line is printed (no mesh line either)."""
    from membranes.app import cli, driver
    from membranes.model import scenes
    argv, made, expected = OPTIONS_TO_SOLVE[case]
    calls, make = {}, scenes.make

    def recording_make(name, **kwargs):
        calls["make"] = (name, {k: v for k, v in kwargs.items()
                                if k not in ("comm", "progress")})
        return make(name, **kwargs)

    def recording_solve(problem, **kwargs):
        calls["solve"] = kwargs
        raise ValueError("stopped by the test")

    monkeypatch.setattr(scenes, "make", recording_make)
    monkeypatch.setattr(driver, "solve", recording_solve)
    assert cli.main(["solve"] + argv) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert calls.get("make") == made, err
    assert calls["solve"] == expected
    if "--quiet" in argv:
        assert err == "membranes: error: stopped by the test\n"
    else:
        assert err.splitlines()[-1] == "membranes: error: stopped by the test"
        assert err.splitlines()[-2].startswith("mesh and 1 uniform refinement(s) made in ")


# ## The same classes through the API: ValueError

@pytest.mark.parametrize("kwargs", [
    {"mu1": 0}, {"mu2": -1}, {"g": 0}, {"g": float("nan")}, {"mu1": float("inf")},
    {"f1": "sin(x"}, {"f1": "q"}, {"f2": "log(x)"}, {"f1": "1/0"}, {"f2": "sqrt(-1 - x)"},
    {"levels": -1}, {"h": -0.1}, {"h": float("nan")},
])
def test_api_user_scene(kwargs):
    with pytest.raises(ValueError):
        scenes.user(**{"h": 0.3, **kwargs})


@pytest.mark.parametrize("case", MESH_CASES)
def test_api_meshes(case, bad_meshes):
    with pytest.raises(ValueError, match=r"^mesh file .*" + MESH_REASONS[case]):
        read_msh(bad_meshes[case])


def test_api_problem_and_solve_options():
    base = scene("disk", 0.1)
    with pytest.raises(ValueError, match="mu1"):
        Problem("p", base.hierarchy, -1.0, 1.0, 0.1, 0.0, 0.0)
    with pytest.raises(ValueError, match="g"):
        Problem("p", base.hierarchy, 1.0, 1.0, float("inf"), 0.0, 0.0)
    with pytest.raises(ValueError, match="f1"):
        Problem("p", base.hierarchy, 1.0, 1.0, 0.1, "1/(x*0)", 0.0)
    with pytest.raises(ValueError, match="f2"):
        Problem("p", base.hierarchy, 1.0, 1.0, 0.1, 0.0, float("nan"))
    with pytest.raises(ValueError, match="levels"):
        build_hierarchy(unit_disk(0.5), -2)
    for kwargs in ({"cfun": "max"}, {"newton": "sloppy"}, {"system": "half"},
                   {"solver": "magic"}, {"tol": 0.0}, {"max_newton": 0}):
        with pytest.raises(ValueError):
            solve(base, **kwargs)
    with pytest.raises(ValueError, match="scene"):
        scenes.make("cube")
    with pytest.raises(ValueError, match="problem must be a membranes.Problem"):
        solve(base.mesh)
    two = scene("disk", 0.4, levels=1)
    for kwargs, message in (({"coarse": "never"}, "coarse"),
                            ({"coarse_tol": 1.5}, "coarse_tol"),
                            ({"coarse_tol": 1e-3, "newton": "exact"}, "coarse_tol"),
                            ({"coarse_tol": 1e-3, "coarse": "estimated"}, "coarse_tol"),
                            # (was silently ignored, while coarse_tol was refused)
                            ({"coarse": "estimated", "newton": "exact"}, "coarse applies"),
                            ({"coarse": "estimated", "nested": False}, "coarse applies")):
        with pytest.raises(ValueError, match=message):
            solve(two, **kwargs)


def test_formula_accepts_the_documented_language():
    f = Formula("-1 + 0.5*sin(pi*x)*cos(y) + exp(-x**2) - sqrt(abs(y)) + min(x, y, 0) "
                "+ max(x, 2*y) + tanh((x - 0.3)/0.01)", "f1")
    import numpy as np
    p = np.array([[0.3, -0.2], [0.1, 0.4]])
    x, y = p
    expected = (-1 + 0.5 * np.sin(np.pi * x) * np.cos(y) + np.exp(-x ** 2) - np.sqrt(np.abs(y))
                + np.minimum(np.minimum(x, y), 0) + np.maximum(x, 2 * y)
                + np.tanh((x - 0.3) / 0.01))
    assert np.allclose(f.numpy(p), expected, rtol=1e-15, atol=1e-15)


def test_formula_tanh_builds_the_same_in_ufl():
    """tanh (a steep layer without exp's overflow): UFL's build integrates to the closed form
    ∫_0^1 ∫_0^1 tanh(3x) = ln(cosh 3)/3; a rule exact for degree 12 on cells of size h = 1/32
    errs by O((3h)^13) ≈ 1e-13 on tanh(3x), far below the tolerance 1e-10."""
    import numpy as np
    import ufl
    from dolfinx import fem
    from dolfinx.mesh import create_unit_square
    from mpi4py import MPI
    mesh = create_unit_square(MPI.COMM_SELF, 32, 32)
    f = Formula("tanh(3*x)", "f1")
    dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": 12})
    value = fem.assemble_scalar(fem.form(f.ufl(ufl.SpatialCoordinate(mesh)) * dx))
    assert value == pytest.approx(np.log(np.cosh(3.0)) / 3.0, rel=1e-10)


def _filled(X, value):
    X.set(value)
    return X


@pytest.mark.parametrize("guess,message", [
    ("warm", "unknown initial guess"),
    (np.zeros(5), "iterate layout"),
    (lambda disc: _filled(disc.vector3(), np.nan), "non-finite"),
    (lambda disc: _filled(disc.vector3(), 1e155), r"up to 1e\+155, beyond 1e\+150"),
])
def test_bad_initial_guess(guess, message):
    """A named guess that does not exist, an array of the wrong size, NaN, values whose
    squares overflow (a probe's 1e155 made a nested run's coarse residual inf, and the run
    went on to a refusal that blamed the data): ValueError."""
    with pytest.raises(ValueError, match=message):
        solve(scenes.disk(h=0.3), newton="exact", initial_guess=guess, estimators=False)


def test_loads_infinite_at_a_quadrature_point():
    """1/(x - 0.5) on the square at h = 0.25, J = 2: the data's sample points miss x = 0.5
    (its vertices lie at 0.5 ± 6.7e-16), a quadrature point of T_2 does not, and the load
    vector holds inf. Said as such, not as data to rescale ("the data overflow double
    precision", a probe's, 2026-12-03)."""
    with pytest.raises(ValueError, match="the loads are infinite at some quadrature points"):
        solve(scenes.user(f1="1/(x-0.5)", domain="square", h=0.25, levels=2))


GUESS_ON_SOME_PROCESSES = """
import numpy as np
from mpi4py import MPI
from petsc4py import PETSc
from membranes import scenes, solve
comm = MPI.COMM_WORLD
problem = scenes.disk(h=0.3)
n = problem.mesh.topology.index_map(0).size_local
# the global size of the iterate layout, but its local sizes on process 0 only
X = PETSc.Vec().createMPI((3 * n + 3 * (comm.rank == 1) - 3 * (comm.rank == 2), PETSc.DECIDE),
                          comm=comm)
X.set(0.0)

def nan_on_the_last(disc):
    Y = disc.vector3()
    Y.array[:] = np.nan if comm.rank == comm.size - 1 else 0.0
    return Y

said = []
for guess in (X, nan_on_the_last):
    try:
        solve(problem, newton="exact", estimators=False, nested=False, initial_guess=guess)
        said.append(None)
    except ValueError as e:
        said.append(str(e))
said = comm.gather(said, root=0)
print(repr(said) if comm.rank == 0 else "", flush=True)
"""


def test_bad_initial_guess_on_some_processes_only():
    """Under mpirun -n 3, a guess that is bad on some processes only: a Vec whose local sizes
    are the iterate layout's on process 0 only (the others raised, process 0 waited for ever
    in the next collective), and a guess with NaN on the last process only (refused there,
    accepted on the others, which summed the processes' verdicts instead of requiring all).
    Every process raises the same ValueError."""
    import ast

    proc = mpirun(["-c", GUESS_ON_SOME_PROCESSES], processes=3)
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    layout, nan = zip(*said)
    assert all(m is not None and "iterate layout" in m for m in layout), said
    assert all(m == "the initial guess has non-finite values" for m in nan), said


GUESS_FAILING_ON_ONE = """
from mpi4py import MPI
from membranes import scenes, solve
comm = MPI.COMM_WORLD
problem = scenes.disk(h=0.3, levels=1)

def guess(disc):
    X = disc.vector3()                    # (collective: made on every process)
    if comm.rank == 1:
        raise FileNotFoundError("guess_1.npy")
    return X
try:
    solve(problem, initial_guess=guess)
    said = None
except Exception as e:
    said = f"{type(e).__name__}: {e}"
said = comm.gather((said, solve(problem).converged), root=0)
print(repr(said) if comm.rank == 0 else "", flush=True)
"""


def test_an_initial_guess_function_failing_on_one_process():
    """Under mpirun -n 3, a guess function that raises on process 1 only (its own file
    missing): the others waited in the next collective for ever (a probe's, 2026-12-03).
    Process 1 raises its exception, the others a RuntimeError naming it, and a next solve
    runs on all."""
    import ast

    proc = mpirun(["-c", GUESS_FAILING_ON_ONE], processes=3, timeout=300)
    assert proc.returncode == 0, proc.stderr
    said = ast.literal_eval(proc.stdout.strip().splitlines()[-1])
    named = "RuntimeError: the initial guess function failed on process 1: " \
        "FileNotFoundError: guess_1.npy"
    assert said == [(named, True), ("FileNotFoundError: guess_1.npy", True), (named, True)]


# ## Refused at once (issue 29): each case of the table, as a user runs it

REFUSED_AT_ONCE = {
    "levels beyond memory": (["--scene", "disk", "--levels", "12"], "2.5e10 vertices"),
    "h beyond memory": (["--scene", "disk", "--h", "1e-5"], "3.6e10 vertices"),
    "output folder in /proc": (["--scene", "disk", "--h", "0.3", "--out", "/proc/x"],
                               "output folder /proc/x cannot be written"),
    "malformed PETSc option": (["--scene", "disk", "--h", "0.3", "--petsc-options",
                                "-pc_type=vertex_amg"], "'-pc_type=vertex_amg' is not -name"),
    "misspelt PETSc option": (["--scene", "disk", "--h", "0.3", "--petsc-options",
                               "-ksp_gmres_restartt 50"], "-ksp_gmres_restartt is not used"),
    "below --max-vertices": (["--scene", "square", "--h", "0.1", "--levels", "2",
                              "--max-vertices", "500"], "more than the limit --max-vertices"),
    # the estimate overflowed: ZeroDivisionError (h ** 2 = 0), a garbled message, or a loop
    # over 1e20 levels that never ended (probe B)
    "h underflows": (["--scene", "disk", "--h", "1e-300"], "more than 1e308 vertices"),
    "levels overflow": (["--scene", "disk", "--levels", "600"], "more than 1e308 vertices"),
    "levels absurd": (["--scene", "disk", "--levels", "99999999999999999999"],
                      "more than 1e308 vertices"),
}


@pytest.mark.parametrize("case", sorted(REFUSED_AT_ONCE))
def test_refused_at_once_by_the_installed_command(case, tmp_path):
    """Exit 2, one stderr line naming the cause, no traceback, the output folder absent, and
    back in seconds: the mesh is never built (gmsh alone needs minutes for the first two; the
    bound is generous, the in-process test below shows that gmsh is not called)."""
    import time
    args, expected = REFUSED_AT_ONCE[case]
    out = "/proc/x" if "/proc/x" in args else str(tmp_path / "out")
    extra = [] if "--out" in args else ["--out", out]
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "membranes.app.cli", "solve", "--quiet"] + args
                          + extra, capture_output=True, text=True, timeout=120)
    elapsed = time.perf_counter() - started
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert err.startswith("membranes: error: ") and "\n" not in err, err
    assert expected in err and "Traceback" not in err
    assert proc.stdout == ""
    assert not os.path.exists(out) and os.listdir(tmp_path) == []
    assert elapsed < 20.0


# method options that `solve` refuses: refused by the command line before the mesh too (they
# were refused only after gmsh and the refinement had run, probe I); a negative number in
# exponent notation is a value, not an unknown option
METHOD_REFUSED = {
    "tol with adaptive": (["--tol", "1e-8"], "tol applies to newton 'exact' and 'inexact'"),
    "nu below 1": (["--nu", "-1"], "nu must be a positive integer"),
    "gamma out of range": (["--gamma-lin", "-1e-1"], "gamma_lin must lie in (0, 1)"),
    "nested on one level": (["--nested"], "nested iteration needs a mesh hierarchy"),
    "multilevel on one level": (["--alg-flux", "multilevel"], "needs a mesh hierarchy"),
    "adaptive direct": (["--newton", "adaptive", "--solver", "direct"],
                        "the adaptive variant stops a Krylov solver"),
    "alg flux without estimators": (["--no-estimators", "--alg-flux", "nu"],
                                    "alg_flux applies to runs with estimators only"),
    "coarse-tol negative": (["--levels", "1", "--coarse-tol", "-1e-6"],
                            "--coarse-tol must lie in (0, 1), got -1e-06"),
    "max-linear-its exponent": (["--max-linear-its", "-1e3"], "invalid int value: '-1e3'"),
    # refused by Newton only, after the mesh and the estimators' set-up (probe cliopts)
    "amg on the full system": (["--system", "full"],
                               "mean/gap preconditioner works on the eliminated system"),
    "inexact direct": (["--newton", "inexact", "--solver", "direct"],
                       "the inexact Newton variant needs an iterative Krylov preset"),
    # a traceback from PETSc once the run had started (OverflowError, exit 1)
    "Krylov limit beyond PETSc's integers": (["--max-linear-its", str(2 ** 63)],
                                             "max_linear_its must be at most"),
    "coarse on one level": (["--coarse", "residual"],
                            "--coarse applies to the adaptive variant with nested iteration"),
    "coarse without nesting": (["--levels", "1", "--no-nested", "--coarse", "residual"],
                               "--coarse applies to the adaptive variant with nested"),
    # ... or ignored without a word: a direct solve has no Krylov iterations
    "nu with direct": (["--solver", "direct", "--nu", "5"], "nu applies to iterative Krylov"),
    "Krylov limit with preonly": (["--solver", "paper", "--petsc-options",
                                   "-ksp_type preonly -pc_type lu", "--max-linear-its", "50"],
                                  "max_linear_its applies to iterative Krylov"),
    "inexact preonly": (["--newton", "inexact", "--solver", "paper", "--petsc-options",
                         "-ksp_type preonly -pc_type lu"], "not 'paper' with -ksp_type preonly"),
}


CASES = {**{("size", k): v for k, v in REFUSED_AT_ONCE.items()},
         **{("method", k): (["--scene", "disk", "--h", "0.3"] + v[0], v[1])
            for k, v in METHOD_REFUSED.items()}}


@pytest.mark.parametrize("case", sorted(CASES), ids=lambda c: f"{c[0]}: {c[1]}")
def test_refused_before_the_mesh_is_built(case, tmp_path, capsys, monkeypatch):
    """The cases above in process, with gmsh and the refinement made to fail: the checks
    refuse them before either is called, in one line, and write nothing."""
    from membranes.app.cli import main
    from membranes.fem import hierarchy, meshes

    def never(*args, **kwargs):
        raise AssertionError("the mesh was built")
    monkeypatch.setattr(meshes, "on_rank0", never)
    monkeypatch.setattr(hierarchy, "refine", never)
    args, expected = CASES[case]
    out = tmp_path / "out"
    extra = [] if "--out" in args else ["--out", str(out)]
    assert main(["solve", "--quiet"] + args + extra) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("membranes: error: ") and "\n" not in err, err
    assert expected in err
    assert not out.exists()


def test_api_refuses_the_same_with_the_same_message(capsys):
    """The API raises ValueError with the CLI's message."""
    from membranes.app.cli import main
    for args, call in (
            (["--levels", "12"], lambda: scenes.disk(levels=12)),
            (["--h", "0.3", "--petsc-options", "-ksp_gmres_restartt 50"],
             lambda: solve(scenes.disk(h=0.3), petsc_options="-ksp_gmres_restartt 50")),
            (["--h", "0.3", "--petsc-options", "-pc_type=vertex_amg"],
             lambda: solve(scenes.disk(h=0.3), petsc_options="-pc_type=vertex_amg"))):
        assert main(["solve", "--quiet", "--scene", "disk"] + args) == 2
        cli = capsys.readouterr().err.strip()
        with pytest.raises(ValueError) as e:
            call()
        if "--levels" in args:     # the scene checks with the leanest method: fewer bytes
            assert cli.split(" and needs")[0] == "membranes: error: " + \
                str(e.value).split(" and needs")[0]
        else:
            assert cli == "membranes: error: " + str(e.value)


# ## A run that names no Newton variant gets one that can run

def test_default_variant_is_one_that_can_run(tmp_path, capsys):
    """Without `newton`, adaptive (§8) where it can run, exact Newton without the estimators
    (adaptive stops by them) or with the direct solver (no Krylov iterations to stop); a
    variant asked for that cannot run is still refused."""
    from membranes.app import cli
    base = scene("disk", 0.3)
    assert solve(base).options["newton"] == "adaptive"
    plain = solve(base, estimators=False)
    assert plain.options["newton"] == "exact" and plain.estimates is None
    direct = solve(base, solver="direct")
    assert direct.options["newton"] == "exact" and direct.estimates["eta"] > 0
    with pytest.raises(ValueError, match="needs the estimators"):
        solve(base, newton="adaptive", estimators=False)
    with pytest.raises(ValueError, match="not 'direct'"):
        solve(base, newton="adaptive", solver="direct")
    assert cli.main(["solve", "--scene", "disk", "--h", "0.3", "--no-estimators",
                     "--quiet"]) == 0
    assert '"newton": "exact"' in capsys.readouterr().out


def test_solve_defaults_are_the_documented_ones():
    """`membranes solve` with no option runs what docs/cli.md's table gives as defaults:
    the disk scene (left to `_scene_arguments`) at the scene's h, T_0 itself (--levels 0),
    Newton-min with the amg solver, at most 100 Newton steps a level, the paper's initial
    guess; the variant and nesting are left to `solve` (None). Exact values."""
    from membranes.app import cli
    args = cli._parser().parse_args(["solve"])
    assert (args.levels, args.cfun, args.solver, args.max_newton, args.initial_guess) == \
        (0, "min", "amg", 100, "paper")
    assert (args.scene, args.h, args.newton, args.nested, args.out) == (None,) * 5
    assert cli._scene_arguments(args) == ("disk", {"levels": 0})


def test_mesh_with_h_or_domain_names_the_options(tmp_path, capsys):
    """`--mesh` with `--h` or `--domain` is refused by the command line in its own words,
    naming the options as typed ('give --mesh or --h, not both'), not by the API's message
    about its arguments (mesh, h); exit 2, nothing written."""
    msh = str(write_msh(tmp_path / "t.msh", "triangles"))
    for extra, name in ((["--h", "0.3"], "--h"), (["--domain", "square"], "--domain")):
        err = cli_bad_input(["--mesh", msh] + extra, tmp_path / "out", capsys)
        assert err == f"membranes: error: give --mesh or {name}, not both"


@pytest.mark.parametrize("args, line", [
    (["--levels", "-1"], "--levels must be a non-negative integer, got -1"),
    (["--max-newton", "0"], "--max-newton must be at least 1, got 0"),
    (["--levels", "1", "--coarse-tol", "1"], "--coarse-tol must lie in (0, 1), got 1.0"),
    (["--max-vertices", "0"], "--max-vertices must be a positive integer, got 0")])
def test_counts_and_limits_are_refused_under_their_option_names(args, line, tmp_path, capsys):
    """A value out of range at the ends of its range (levels 0, max-newton 1, coarse-tol
    below 1, max-vertices 1 are the smallest or largest allowed) is refused by the command
    line with the option's own name, as typed; the API's later checks refuse them too, in
    the words of its arguments (max_newton, coarse_tol), which the user did not type."""
    assert cli_bad_input(args, tmp_path / "out", capsys) == f"membranes: error: {line}"


def test_no_room_for_the_outputs_is_refused_before_the_run(tmp_path, monkeypatch, capsys):
    """A filesystem without room for the outputs of the mesh built is refused before the
    solve starts (`membranes solve` checks the room once the mesh is made), not after a run
    whose outputs the writer then refuses: exit 2, one line, nothing written, no solve. The
    room asked for is made larger than any disk (2^62 bytes)."""
    from membranes.app import driver, outputs

    def no_solve(*args, **kwargs):
        raise AssertionError("solved before the room was checked")
    monkeypatch.setattr(outputs, "room_for", lambda mesh: 2 ** 62)
    monkeypatch.setattr(driver, "solve", no_solve)
    err = cli_bad_input([], tmp_path / "out", capsys)
    assert "MiB free, the outputs need about" in err


JSON_LINE_KEYS = ("scene", "n_vertices", "n_cells", "h", "newton", "cfun", "solver", "system",
                  "processes", "converged", "newton_iterations", "linear_iterations",
                  "wall_time_s", "energy_error", "eta", "effectivity", "nested",
                  "newton_per_level")


def test_the_json_line_holds_the_documented_keys(tmp_path, capsys):
    """`membranes solve` ends with one JSON line on stdout whose keys are those docs/cli.md
    lists, in its order, each with summary.json's value (the same summary, exact), and
    newton_per_level the Newton steps of each level of the nested run (J = 1: two)."""
    from membranes.app import cli
    out = tmp_path / "out"
    assert cli.main(["solve", "--quiet", "--h", "0.3", "--levels", "1", "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert len(stdout.splitlines()) == 1
    line = json.loads(stdout)
    assert tuple(line) == JSON_LINE_KEYS
    summary = json.loads((out / "summary.json").read_text())
    assert all(line[k] == summary[k] for k in JSON_LINE_KEYS[:-1])
    assert line["newton_per_level"] == [r["newton_iterations"] for r in summary["per_level"]]
    assert len(line["newton_per_level"]) == 2 and line["effectivity"] >= 1.0


def test_scenes_lists_each_scene_with_what_it_needs(capsys):
    """`membranes scenes` lists every scene of the API (radial too) on a line of its name and
    description, then a line of what it knows (docs/cli.md: 'Lists the scenes with what each
    knows (exact solution, data jump)')."""
    from membranes.app import cli
    assert cli.main(["scenes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[::2]] == ["disk", "square", "radial", "user"]
    assert all(line.split()[0] == "needs:" for line in lines[1::2]) and len(lines) == 8
    assert "exact solution -> energy error" in lines[1]
    assert lines[7].strip() == "needs: data only (no exact solution, no energy error)"


@pytest.mark.parametrize("out", ["", "  "])
def test_an_empty_output_folder_is_refused(out, tmp_path, monkeypatch, capsys):
    """`--out ""` (an unset shell variable) is the working folder to os.path.abspath: the
    outputs spilled into it. Every command and the API refuse an empty or blank path, and
    nothing appears in the working folder."""
    from membranes.app.cli import main
    from membranes.app.outputs import write_outputs

    from .conftest import solved
    monkeypatch.chdir(tmp_path)
    for args in (["solve", "--quiet", "--h", "0.3"], ["report", "--quiet", "--h", "0.5",
                 "--levels", "0"], ["stability", "--quiet", "--cases", "tiny"]):
        assert main(args + ["--out", out]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("membranes: error: the output folder is an empty or blank "
                              "path (") and err.endswith("): name a folder") and "\n" not in err
    with pytest.raises(ValueError, match="empty or blank path"):
        write_outputs(solved("disk", 0.3), out)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("option,value", [("nu", 2.5), ("nu", "10"), ("max_newton", True),
                                          ("max_linear_its", 10.0), ("max_newton", 0)])
def test_counts_must_be_integers(option, value):
    """Iteration counts of the API: a float was cut to an int without a word (nu = 2.5 ran
    with ν = 2), a bool taken as 1. Now a ValueError names the option; numpy integers pass."""
    problem = scenes.disk(h=0.5)
    with pytest.raises(ValueError, match=f"{option} must be a positive integer"):
        solve(problem, **{option: value})
    assert solve(problem, nu=np.int64(10), max_newton=np.int32(50)).converged


def test_scene_arguments_are_checked_before_meshing():
    """A levels of True was one refinement, a contact of 'no' meant contact, and an h given
    as text reached gmsh's description as a string ("Unknown format code 'g'"). Now levels
    and contact must be what they say, and h a number (text that reads as one is taken)."""
    with pytest.raises(ValueError, match="levels must be a non-negative integer, got True"):
        scenes.disk(h=0.3, levels=True)
    with pytest.raises(ValueError, match="contact must be True or False, got 'no'"):
        scenes.radial(h=0.3, contact="no")
    with pytest.raises(ValueError, match="mesh size h must be a number, got 'abc'"):
        scenes.disk(h="abc")
    assert scenes.disk(h="0.5").mesh.topology.index_map(0).size_global == \
        scenes.disk(h=0.5).mesh.topology.index_map(0).size_global


def test_data_given_as_numbers_are_checked_as_numbers():
    """f1 = nan as a float read as the unknown name 'nan'; None, True or a Python function as
    formulas that do not parse; mu1 = True as 1. Each is now refused for what it is."""
    with pytest.raises(ValueError, match="f1 must be finite, got nan"):
        scenes.user(h=0.3, f1=float("nan"))
    for bad in (None, True, len):
        with pytest.raises(ValueError, match="f2 must be a formula in x, y"):
            scenes.user(h=0.3, f2=bad)
    with pytest.raises(ValueError, match="mu1 must be a number, got True"):
        scenes.user(h=0.3, mu1=True)
    assert Formula(np.float64(-1.5), "f1").text == "-1.5"


# ## Probe B: formulas, and options of the API that must be named when they are wrong

def test_formula_parts_without_x_y_are_evaluated_as_on_the_mesh():
    """A part without x, y is evaluated in numpy's double arithmetic for UFL too: 1/exp(1000)
    is 0 to both (Python's floats raised OverflowError when the forms were built, after the
    numpy check had passed), and one that is not finite is refused when parsed. Long formulas
    are quoted shortened."""
    import ufl
    x = ufl.SpatialCoordinate(ufl.triangle)
    assert Formula("-1 + 1/exp(1000)", "f1").ufl(x) == -1.0
    assert Formula("min(2**10**10, 1) + x", "f1").numpy(np.array([[0.5], [0.0]]))[0] == 1.5
    for bad in ("2**10**10 * x", "1e400", "min(1e400, x)", "0**-1 + x", "(-8)**(1/3)",
                "tanh(1e400)", "x + 0*1" + "0" * 400):
        with pytest.raises(ValueError, match="is not finite in double precision"):
            Formula(bad, "f1")
    # a number that overflows is refused even where the part around it is finite (tanh(inf)
    # is 1: a typo, most likely), while an overflow of the arithmetic is numpy's, as on the
    # mesh
    assert Formula("tanh(exp(1000)) + x", "f1").numpy(np.array([[1.0], [0.0]]))[0] == 2.0
    with pytest.raises(ValueError, match="nested too deeply") as e:
        Formula("+".join(["x"] * 100000), "f1")
    assert len(str(e.value)) < 300
    assert Formula("+".join(["x"] * 400), "f1").numpy(np.array([[1.0], [0.0]]))[0] == 400.0
    assert Formula(Formula("x + 1"), "f2").text == "x + 1"


def test_formula_too_large_to_compile_is_refused():
    """A long formula kept shallow by parentheses passed the nesting limit, and its data forms
    then went to the C compiler, whose time and memory grow faster than the kernel beyond some
    20000 parts (docs/performance.md). Refused when parsed, with its size; a series of 800 terms
    is accepted. The counts are those of Python's syntax tree (`_series`)."""
    ok = Formula(_series(800), "f1")
    assert ok.numpy(np.array([[0.0], [0.3]]))[0] == 0.0          # every sin(k*0) is 0
    with pytest.raises(ValueError, match=r"f1: .* has 91998 parts .* more than 20000") as e:
        Formula(_series(4000), "f1")
    assert "\n" not in str(e.value) and len(str(e.value)) < 300
    with pytest.raises(ValueError, match="more than 20000"):
        scenes.user(h=0.3, f2=_series(1000))                          # 22998 parts


def test_formula_builds_the_same_data_in_ufl_as_in_numpy():
    """The UFL build of a formula is what the solver assembles; the numpy build is what the
    finiteness check sees. Each function of the language (and the arithmetic, pi, min and
    max of three arguments) is evaluated by dolfinx at three points of every cell of a mesh
    and compared with numpy's own functions at the same physical points, written out here
    independently of `Formula`. A builder of one side that computes another function (UFL's
    cos as sin, max as min) changed the data the user defined while the check saw the right
    ones. Tolerance: the generated C and numpy's libm may differ in the last bits (values are
    O(1), so 1e-12 is some 10^4 ulps and far below any wrong function)."""
    import ufl
    from dolfinx import fem
    from dolfinx.mesh import create_unit_square
    from mpi4py import MPI
    cases = [
        ("sin(pi*x) + y", lambda x, y: np.sin(np.pi * x) + y),
        ("cos(3*x + y)", lambda x, y: np.cos(3 * x + y)),
        ("exp(-x)*sqrt(y)", lambda x, y: np.exp(-x) * np.sqrt(y)),
        ("tanh(4*(x - y))", lambda x, y: np.tanh(4 * (x - y))),
        ("abs(x - 0.5)", lambda x, y: np.abs(x - 0.5)),
        ("min(x, 2*y, 0.7)", lambda x, y: np.minimum(np.minimum(x, 2 * y), 0.7)),
        ("max(x, 2*y, 0.7)", lambda x, y: np.maximum(np.maximum(x, 2 * y), 0.7)),
        ("x**2/(1 + y) - -y", lambda x, y: x ** 2 / (1 + y) + y),
    ]
    mesh = create_unit_square(MPI.COMM_SELF, 4, 4)
    xs = ufl.SpatialCoordinate(mesh)
    ref = np.array([[1 / 3, 1 / 3], [0.2, 0.6], [0.6, 0.2]])
    cells = np.arange(mesh.topology.index_map(2).size_local, dtype=np.int32)
    data = ufl.as_vector([Formula(text, "f1").ufl(xs) for text, _ in cases])
    values = fem.Expression(data, ref).eval(cells).reshape(len(cells), len(ref), len(cases))
    points = fem.Expression(xs, ref).eval(cells).reshape(len(cells), len(ref), 2)
    x, y = points[..., 0], points[..., 1]
    assert len(np.unique(np.round(x, 12))) > 5 and len(np.unique(np.round(y, 12))) > 5
    for i, (text, exact) in enumerate(cases):
        assert np.allclose(values[..., i], exact(x, y), rtol=1e-12, atol=1e-14), text


def test_formula_limits_are_inclusive():
    """MAX_DEPTH and MAX_PARTS are the largest formulas accepted ("at most"), and one level or
    one part more is refused. Depth of '-'*k + 'x' in Python's syntax tree: the Expression,
    k UnaryOps, the Name x and its Load context, k + 3 levels. Parts of a sum of n names
    (balanced, so shallow): n Names, n Loads, n - 1 BinOps and n - 1 Adds, 4n - 2; one name
    turned into '-x' adds a UnaryOp and its USub (20000 parts at n = 5000); one term a number
    instead of a name has no Load (4n - 3 parts: 20001 at n = 5001)."""
    from membranes.model import expressions
    assert expressions.MAX_DEPTH == 500 and expressions.MAX_PARTS == 20000
    one = np.array([[1.0], [0.0]])
    assert Formula("-" * 497 + "x", "f1").numpy(one)[0] == -1.0          # depth 500
    with pytest.raises(ValueError, match="nested too deeply"):
        Formula("-" * 498 + "x", "f1")                                    # depth 501
    largest = Formula(_balanced(["-x"] + ["x"] * 4999), "f1")            # 20000 parts
    assert largest.numpy(one)[0] == 4998.0
    with pytest.raises(ValueError, match=r"f1: .* has 20001 parts .* more than 20000"):
        Formula(_balanced(["1"] + ["x"] * 5000), "f1")


@pytest.mark.parametrize("text,message", [
    ("True + x", "True is not a number"),
    ("x*False", "False is not a number"),
    ("min(x)", r"min\(\) takes at least 2 argument"),
    ("max(y)", r"max\(\) takes at least 2 argument"),
    ("sin(x, y=1)", r"sin\(\) takes 1 argument"),
    ("min(x, y, key=abs)", r"min\(\) takes at least 2 argument"),
])
def test_formula_refuses_what_is_not_in_the_language(text, message):
    """Booleans are no numbers (True would be read as 1), min and max of one argument have no
    meaning in the language (numpy's minimum of one array raised TypeError later, on the
    mesh), and keyword arguments are not part of it (sin(x, y=1) was sin(x), the y=1 dropped
    unsaid). Each is refused when parsed, naming the problem."""
    with pytest.raises(ValueError, match=message) as e:
        Formula(text, "f1")
    assert str(e.value).startswith("f1: ") and "\n" not in str(e.value)


def test_formula_refuses_a_part_not_finite_under_a_sign():
    """A part without x, y that is not finite is refused wherever it stands, also under a
    unary minus or plus around a part with x, y: -min(2**10**10, x) is finite on the mesh to
    numpy (min(inf, x) = x), so only this check keeps the inf out of the C code of the forms
    (as the CLI case 'expr constant too large' does for min(2**10**10, x))."""
    for bad in ("-min(2**10**10, x)", "+(x * 2**10**10)", "1 - -(1/0 + y)"):
        with pytest.raises(ValueError, match="is not finite in double precision") as e:
            Formula(bad, "f1")
        assert str(e.value).startswith("f1: ")


def test_formula_numpy_gives_one_value_per_point():
    """`Formula.numpy` returns an array of length n for n points, also for a formula without
    x, y (a constant broadcast) and for one in y only: the caller indexes it by point."""
    points = np.array([[0.0, 0.5, 1.0, -2.0], [0.1, 0.2, 0.3, 0.4]])
    for text, expected in [("-1.5", [-1.5] * 4), ("2*pi", [2 * np.pi] * 4),
                           ("y - 1", [-0.9, -0.8, -0.7, -0.6])]:
        values = Formula(text, "f1").numpy(points)
        assert values.shape == (4,), text
        assert np.array_equal(values, np.array(expected)), text


def test_formula_change_changes_the_solution_and_folding_does_not():
    base = solve(scenes.user(h=0.5, f1="-1"), newton="exact", solver="direct")
    same = solve(scenes.user(h=0.5, f1="-1 + 1/exp(1000) + 0*x"), newton="exact",
                 solver="direct")
    other = solve(scenes.user(h=0.5, f1="-2"), newton="exact", solver="direct")
    assert same.estimates["eta"] == pytest.approx(base.estimates["eta"], rel=1e-12)
    assert other.estimates["eta"] > 1.5 * base.estimates["eta"]


def test_nan_loads_are_named_as_such():
    """Loads undefined at quadrature points (a builder, or a formula negative under sqrt
    only between the sample points) were reported as an overflow of double precision."""
    import dataclasses

    import ufl
    problem = dataclasses.replace(scenes.user(h=0.5), f1=lambda x: -ufl.sqrt(x[0] - 0.5))
    with pytest.raises(ValueError, match=r"not a number \(NaN\)"):
        solve(problem, newton="exact", estimators=False)


@pytest.mark.parametrize("kwargs,message", [
    ({"estimators": "no"}, "estimators must be True or False"),
    ({"estimators": 0}, "estimators must be True or False"),
    ({"newton": "exact", "tol": 2.0}, r"tol must lie in \(0, 1\)"),
    ({"newton": "exact", "tol": "abc"}, "tol must be a number, got 'abc'"),
    ({"newton": "exact", "tol": [1]}, "tol must be a number"),
    ({"gamma_lin": "abc"}, "gamma_lin must be a number"),
    ({"max_vertices": "a"}, "max_vertices must be a positive integer"),
])
def test_api_options_are_named_when_wrong(kwargs, message):
    """estimators='no' ran with the estimators; tol = 2 'converged' in no step; float('abc')
    and float([1]) gave messages (or a TypeError) naming no option."""
    with pytest.raises(ValueError, match=message):
        solve(scenes.disk(h=0.5), **kwargs)


@pytest.mark.parametrize("levels,kwargs,message", [
    (0, {"gamma_lin": 0.0}, r"gamma_lin must lie in \(0, 1\), got 0.0"),
    (0, {"gamma_alg": 0.0}, r"gamma_alg must lie in \(0, 1\), got 0.0"),
    (0, {"gamma_lin": 1.0}, r"gamma_lin must lie in \(0, 1\), got 1.0"),
    (0, {"newton": "exact", "tol": 1.0}, r"tol must lie in \(0, 1\), got 1.0"),
    (1, {"coarse_tol": 1.0}, r"coarse_tol must lie in \(0, 1\), got 1.0"),
    (1, {"nested": "no"}, "nested must be True, False or None, got 'no'"),
    (1, {"nested": 0}, "nested must be True, False or None, got 0"),
])
def test_method_limits_are_open_and_exact(levels, kwargs, message):
    """The ends of the open intervals are refused: γ = 0 is a Newton or Krylov test that only
    an exact solve meets, γ = 1 no reduction; tol = 1 and coarse_tol = 1 are met by any start
    (a run of no step, called converged). nested='no' is truthy: it ran nested. Refused by
    the method check, with no mesh."""
    from membranes.app.driver import check_method
    with pytest.raises(ValueError, match=message):
        check_method(levels, **kwargs)


@pytest.mark.parametrize("kwargs,message", [
    ({"newton": "exact", "gamma_lin": 0.1}, "gamma_lin applies to newton 'adaptive' only"),
    ({"newton": "exact", "gamma_alg": 0.1}, "gamma_alg applies to newton 'adaptive' only"),
    ({"newton": "inexact", "gamma_alg": 0.1}, "gamma_alg applies to newton 'adaptive' only"),
    ({"newton": "adaptive", "tol": 1e-8}, "tol applies to newton 'exact' and 'inexact'"),
])
def test_stopping_options_of_another_variant_are_refused(kwargs, message):
    """Each variant stops by its own test (§8): exact and inexact by tol, adaptive by γ_lin
    and γ_alg; the other's option would be ignored without a word, so it is refused."""
    from membranes.app.driver import check_method
    with pytest.raises(ValueError, match=message):
        check_method(0, **kwargs)


@pytest.mark.parametrize("levels,kwargs,expected", [
    (1, {}, ("residual", 1e-6)),
    (1, {"coarse_tol": 1e-3}, ("residual", 1e-3)),
    (1, {"coarse": "estimated"}, ("estimated", None)),
    (1, {"newton": "exact"}, (None, None)),
    (1, {"nested": False}, (None, None)),
    (0, {}, (None, None)),
])
def test_coarse_options_as_the_run_uses_them(levels, kwargs, expected):
    """(coarse, coarse_tol) as check_method completes them (and the summary reports them):
    the default 'residual' with 1e-6 where an adaptive nested run has coarse levels, no
    tolerance where 'estimated' stops them by the estimators, and neither where there are
    no coarse levels to leave (other variants, a single level)."""
    from membranes.app.driver import check_method
    assert check_method(levels, **kwargs)[-2:] == expected


def test_the_largest_krylov_limit_petsc_holds_is_accepted():
    """max_linear_its up to PETSc's largest integer (KSP's max_it is a PetscInt) is a valid
    limit; one more is refused."""
    from petsc4py import PETSc

    from membranes.app.driver import check_method
    largest = int(np.iinfo(PETSc.IntType).max)
    assert check_method(0, max_linear_its=largest)[0].max_it == largest
    with pytest.raises(ValueError, match="max_linear_its must be at most"):
        check_method(0, max_linear_its=largest + 1)


def test_scene_numbers_are_named_when_wrong():
    for levels in (None, "x", 2.5, float("inf")):
        with pytest.raises(ValueError, match="levels must be a non-negative integer"):
            scenes.disk(h=0.5, levels=levels)
    with pytest.raises(ValueError, match="rho must be a number, got 'x'"):
        scenes.radial(h=0.5, rho="x")
    with pytest.raises(ValueError, match="max_vertices must be a positive integer"):
        scenes.disk(h=0.5, max_vertices="a")


def test_unknown_domain_and_scene_are_named(monkeypatch):
    """The API's user scene on a domain other than the unit disk or square, and a scene name
    `make` does not know, are refused with a ValueError that lists the choices (the command
    line's --domain and --scene take the choices only), before any meshing: without the
    scene's own check the size estimate met the unknown domain first (a KeyError, a
    traceback on the command line's path)."""
    from membranes.fem import meshes

    def no_meshing(*args, **kwargs):
        raise AssertionError("meshed before the domain was checked")
    monkeypatch.setattr(meshes, "on_rank0", no_meshing)
    with pytest.raises(ValueError, match=r"unknown domain 'triangle' \(choose from: disk, "
                                         r"square\)"):
        scenes.user(h=0.5, domain="triangle")
    with pytest.raises(ValueError, match=r"unknown scene 'circle' \(choose from: disk, "
                                         r"square, radial, user\)"):
        scenes.make("circle", h=0.5)


def test_user_scene_refuses_a_mesh_with_h_or_domain(tmp_path):
    """The command line refuses --mesh with --h or --domain; the API ignored h and domain
    beside a mesh file without a word (a finer h had no effect)."""
    msh = str(write_msh(tmp_path / "t.msh", "triangles"))
    for extra in ({"h": 0.01}, {"domain": "square"}):
        with pytest.raises(ValueError, match="give mesh or"):
            scenes.user(mesh=msh, **extra)
    assert scenes.user(mesh=msh).domain == msh


def test_scene_range_errors_name_the_parameter(monkeypatch):
    """levels = -1 and ρ = 1 are refused by the scenes' own checks, with the message that names
    them, before any meshing (gmsh is replaced by a function that fails the test): the later
    checks (build_hierarchy's, a division by 1 - ρ² = 0 in the radial data's builders) refuse
    them too, but after gmsh has run, and for ρ with a message naming a builder, not ρ."""
    from membranes.fem import meshes

    def no_meshing(*args, **kwargs):
        raise AssertionError("meshed before the parameters were checked")
    monkeypatch.setattr(meshes, "on_rank0", no_meshing)
    with pytest.raises(ValueError, match="levels must be a non-negative integer, got -1"):
        scenes.disk(h=0.5, levels=-1)
    with pytest.raises(ValueError, match="levels must be a non-negative integer, got -1"):
        scenes.user(h=0.5, levels=-1)
    with pytest.raises(ValueError, match=r"rho must lie in \[0, 1\), got 1.0"):
        scenes.radial(h=0.5, rho=1.0)


def test_a_load_not_finite_at_a_cell_midpoint_only_is_refused():
    """Formula data are checked at the vertices *and* the cell midpoints of the mesh
    (problem._sample_points): a load finite at every vertex but infinite at one cell's
    midpoint, 1/((x - a)² + (y - b)²) with (a, b) that midpoint written to all 17 digits (so
    that the parsed numbers are the same doubles and x - a, y - b are exactly 0 there: 1/0 =
    inf), is refused with a message naming the formula and that point, not taken into the
    solve."""
    base = scene("square", 0.3)
    mesh = base.mesh
    x = mesh.geometry.x[:, :2]
    cells = mesh.geometry.dofmap.array.reshape(-1, 3)
    a, b = x[cells].mean(axis=1)[0]
    formula = f"1/((x - {a!r})**2 + (y - {b!r})**2)"
    vertices = (x[:, 0] - a) ** 2 + (x[:, 1] - b) ** 2
    assert vertices.min() > 0                        # finite at every vertex
    with pytest.raises(ValueError, match=f"f1 = .* is not finite on the mesh .*x = {a:.6g}"):
        Problem("p", base.hierarchy, 1.0, 1.0, 0.1, formula, 0.0)


def test_a_pressure_scale_that_underflows_is_refused():
    """κ = ℓ² (1/μ1 + 1/μ2)/2 on a square of side 1e-140 (ℓ = 1e-140, nearly the smallest
    mesh the size checks let through) with μ1 = μ2 = 1e200 is 1e-480: 0 in double precision,
    which would make the C-function ignore λ. Refused in one line, naming κ and ℓ."""
    from membranes.fem.meshes import structured_square
    mesh = structured_square(4, 4)
    mesh.geometry.x[:, :2] *= 1e-140
    with pytest.raises(ValueError, match=r"kappa = .* underflows double precision \(l = 1e-140"):
        solve(scenes.user(mesh=mesh, mu1=1e200, mu2=1e200, f1="-1", f2="1", g=1e-300),
              newton="exact", solver="direct")
