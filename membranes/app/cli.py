"""Command line: ``membranes solve ...``, ``membranes scenes``, ``membranes report`` and
``membranes stability`` (docs/cli.md).

Exit codes: 0 converged, 1 a dolfinx that is not a 0.5 release (one line) or an unexpected
error (its traceback), 2 bad input (one-line message on stderr, nothing written to --out;
also a stdout that cannot be written, `writing_stdout`, and an allocation that fails during
the run, `_out_of_memory`),
3 the solver did not converge (the outputs are written, with converged = false and a reason),
129 hung up (SIGHUP: the terminal or ssh session has gone; nothing written), 130 interrupted
(Ctrl-C; nothing written), 141 the reader of stdout went away (`membranes
solve ... | head`: silent, as the shell's tools; nothing written if the run had not ended),
143 terminated (SIGTERM: a batch scheduler's time limit, or mpirun passing Ctrl-C on; nothing
written).
Progress: one line per Newton step on stderr (``--quiet`` silences it).
``mpirun -n P membranes solve ...`` runs the same code on P processes: dolfinx distributes
the mesh, PETSc the solves; rank 0 prints, every rank writes its part of the solution.
"""

import argparse
import contextlib
import json
import os
import sys
import time

from . import interrupts
from .logs import quiet_jit_logging

EXIT_BAD_INPUT = 2
EXIT_NOT_CONVERGED = 3
EXIT_HUNG_UP = 129        # the shell's code for a run ended by SIGHUP (128 + SIGHUP)
EXIT_INTERRUPTED = 130    # by Ctrl-C (128 + SIGINT)
EXIT_BROKEN_PIPE = 141    # by a write to a pipe no process reads (128 + SIGPIPE)
EXIT_TERMINATED = 143     # and by SIGTERM (128 + SIGTERM)


# seconds a process that met an error waits for the others to meet it too (`_leave`)
AGREE_SECONDS = 10.0

# the Krylov presets (membranes.linalg.krylov.PRESETS, named here: that module imports PETSc,
# which `membranes --help` does not need; tests/test_lean.py checks that the two agree)
SOLVERS = ("paper", "direct", "amg")
DATA_OPTIONS = ("mu1", "mu2", "g", "f1", "f2", "mesh", "domain")
VALUE_OPTIONS = ("--f1", "--f2", "--mu1", "--mu2", "--g", "--h", "--levels", "--tol",
                 "--petsc-options", "--gamma-lin", "--gamma-alg", "--max-vertices",
                 "--coarse-tol", "--nu", "--max-linear-its", "--max-newton")


class BadInput(ValueError):
    pass


@contextlib.contextmanager
def writing_stdout():
    """Around writes to stdout: a closed pipe raises BrokenPipeError (`main` ends silently,
    EXIT_BROKEN_PIPE); a stdout that cannot be written otherwise (a full disk, /dev/full) is
    an output that cannot be written: BadInput, one line, EXIT_BAD_INPUT (stdout pointed at
    /dev/null first: what is left in its buffer would fail again at the exit)."""
    try:
        yield
    except BrokenPipeError:
        raise
    except OSError as e:
        _stdout_to_devnull()
        raise BadInput(f"standard output cannot be written: {e.strerror or e}") from None


def emit(text):
    """Print `text` on stdout, flushed (`writing_stdout`)."""
    with writing_stdout():
        print(text, flush=True)


def _stdout_to_devnull():
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):     # (a stdout that is no file: nothing left to flush)
        pass


class _Once(argparse._StoreAction):
    """An option that takes a value, refused when given twice (argparse would keep the last
    value and drop the first without a word): `--h 0.3 ... --h 0.1` is a slip."""

    def __call__(self, parser, namespace, values, option_string=None):
        _given_once(self, namespace)
        super().__call__(parser, namespace, values, option_string)


class _OnceTrue(argparse._StoreTrueAction):
    """A flag (`--quiet`), refused when given twice like the options with values."""

    def __call__(self, parser, namespace, values, option_string=None):
        _given_once(self, namespace)
        super().__call__(parser, namespace, values, option_string)


class _OnceBoolean(argparse.BooleanOptionalAction):
    """`--nested` / `--no-nested`: one of them, once."""

    def __call__(self, parser, namespace, values, option_string=None):
        _given_once(self, namespace)
        super().__call__(parser, namespace, values, option_string)


def _given_once(action, namespace):
    given = namespace.__dict__.setdefault("_given", set())
    if action.dest in given:
        raise argparse.ArgumentError(action, "given more than once")
    given.add(action.dest)


class _Version(argparse.Action):
    """`membranes --version`: membranes's version, then the software's (membranes.app.versions),
    printed once; exit code 0."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from mpi4py import MPI

        from .versions import one_line, software
        versions = software()
        if MPI.COMM_WORLD.rank == 0:
            emit(f"membranes {versions.pop('membranes')}\n{one_line(versions)}")
        parser.exit()


class _Parser(argparse.ArgumentParser):
    """argparse with every option taken once, no abbreviations (`--lev 2` is an unknown
    option, not --levels), errors as BadInput and help printed by process 0 only."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        self.register("action", None, _Once)
        self.register("action", "store", _Once)
        self.register("action", "store_true", _OnceTrue)

    def error(self, message):
        raise BadInput(message)

    def _print_message(self, message, file=None):
        from mpi4py import MPI
        if MPI.COMM_WORLD.rank == 0:
            with writing_stdout() if file is sys.stdout else contextlib.nullcontext():
                super()._print_message(message, file)


def _parser():
    p = _Parser(prog="membranes",
                description="Contact of two elastic membranes: semismooth Newton on P1 "
                            "finite elements with guaranteed error bounds (FEniCSx).")
    p.add_argument("--version", action=_Version, help="the versions of membranes and of the "
                   "software it runs on (dolfinx, petsc4py, MPI, ...), then exit")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    s = sub.add_parser("solve", help="solve a scene and write summary, history and solution")
    s.add_argument("--scene", choices=("disk", "square", "user"),
                   help="disk (default) or square with known exact solutions, or user data "
                        "(implied by --mu1/--mu2/--g/--f1/--f2/--mesh/--domain)")
    s.add_argument("--mesh", metavar="FILE", type=os.path.expanduser,
                   help="2D triangular mesh file, gmsh .msh or XDMF (user scene)")
    s.add_argument("--domain", choices=("disk", "square"),
                   help="domain of the user scene when no --mesh is given (default disk)")
    s.add_argument("--h", type=float, help="gmsh target size of the coarse mesh (default 0.05)")
    s.add_argument("--levels", type=int, default=0,
                   help="uniform refinements of the coarse mesh; the run computes on the "
                        "finest (default 0)")
    s.add_argument("--mu1", type=float, help="modulus of membrane 1 (> 0, default 1)")
    s.add_argument("--mu2", type=float, help="modulus of membrane 2 (> 0, default 1)")
    s.add_argument("--g", type=float, help="boundary value of membrane 1 (> 0, default 0.05)")
    s.add_argument("--f1", metavar="EXPR", help="load of membrane 1, formula in x, y "
                   "(pi sin cos exp tanh sqrt abs min max; default 0)")
    s.add_argument("--f2", metavar="EXPR", help="load of membrane 2 (default 0)")
    s.add_argument("--newton", choices=("exact", "inexact", "adaptive"),
                   help="adaptive (default): Krylov and Newton stopped by the estimators; "
                        "exact (default with --no-estimators or --solver direct): linear "
                        "solves to 2e-12; inexact: to the previous nonlinear residual "
                        "(theory §8)")
    s.add_argument("--gamma-lin", type=float, metavar="G",
                   help="adaptive: stop Newton at eta_lin <= G eta_disc (default 0.3)")
    s.add_argument("--gamma-alg", type=float, metavar="G",
                   help="adaptive: stop Krylov at eta_alg <= G max(eta_disc, eta_lin) "
                        "(default 0.3)")
    s.add_argument("--alg-flux", choices=("nu", "multilevel"),
                   help="algebraic flux of the estimators (theory §6; default nu)")
    s.add_argument("--cfun", choices=("min", "fb"), default="min",
                   help="C-function of the complementarity rows (theory §3): min (default) "
                        "or fb (Fischer-Burmeister)")
    s.add_argument("--solver", choices=SOLVERS, default="amg",
                   help="amg (default): eliminated system, FGMRES + mean/gap BoomerAMG; "
                        "paper: full system, GMRES + ILU(0) (block Jacobi on several "
                        "processes); direct: MUMPS")
    s.add_argument("--system", choices=("full", "eliminated"),
                   help="Newton system instead of the solver's: full 3N or eliminated 2N")
    s.add_argument("--petsc-options", metavar="STRING",
                   help='PETSc options on top of the solver\'s, e.g. "-ksp_gmres_restart 50"')
    s.add_argument("--nu", type=int, metavar="N",
                   help="record (and for adaptive, estimate) the Krylov iterate every N steps "
                        "(default 10; not with a direct solve)")
    s.add_argument("--max-linear-its", type=int, metavar="N",
                   help="Krylov iterations allowed per Newton step (default 10000; not with "
                        "a direct solve)")
    s.add_argument("--tol", type=float,
                   help="exact, inexact: stop at ||R_lin|| / ||(F, 0)|| <= TOL (default 1e-10)")
    s.add_argument("--max-newton", type=int, default=100, metavar="N",
                   help="Newton steps allowed per level (default 100); exit 3 beyond them")
    s.add_argument("--initial-guess", choices=("paper", "zero"), default="paper",
                   help="X^0: paper (u1 = g, u2 = 0, lambda = 0; default) or zero")
    s.add_argument("--nested", action=_OnceBoolean, default=None,
                   help="nested iteration: solve on T_0, prolong the solution to T_1 as its "
                        "initial guess, ..., up to T_J (default with --levels >= 1)")
    s.add_argument("--coarse", choices=("residual", "estimated"),
                   help="adaptive with --nested: leave each coarse level at ||R_lin|| / "
                        "||(F, 0)|| <= --coarse-tol without estimators (residual, default) "
                        "or by the adaptive criteria with estimators on every level "
                        "(estimated); the finest level is certified either way")
    s.add_argument("--coarse-tol", type=float, metavar="TOL",
                   help="--coarse residual: the coarse levels' tolerance (default 1e-6)")
    s.add_argument("--out", metavar="DIR", type=os.path.expanduser,    # (--out=~/x too)
                   help="write summary.json, history.csv, solution.xdmf and solution.h5 there")
    s.add_argument("--max-vertices", type=int, metavar="N",
                   help="refuse a computational mesh of more than N vertices (default: "
                        "refuse a run that needs more memory than the processes have)")
    s.add_argument("--no-estimators", action="store_true",
                   help="no certificate: skip the estimators of theory §7 (Newton then "
                        "exact by default; not with --newton adaptive)")
    s.add_argument("--quiet", action="store_true", help="no progress lines")
    sub.add_parser("scenes", help="list the scenes")
    from .report import add_parser as add_report_parser
    add_report_parser(sub)
    from .stability import add_parser as add_stability_parser
    add_stability_parser(sub)
    return p


def _scene_arguments(args):
    given = [k for k in DATA_OPTIONS if getattr(args, k) is not None]
    scene = args.scene or ("user" if given else "disk")
    if scene != "user" and given:
        raise BadInput(f"--{given[0]} applies to --scene user only (scene {scene} has its "
                       f"own data)")
    if args.mesh is not None and args.h is not None:
        raise BadInput("give --mesh or --h, not both")
    if args.mesh is not None and args.domain is not None:
        raise BadInput("give --mesh or --domain, not both")
    if args.levels < 0:
        raise BadInput(f"--levels must be a non-negative integer, got {args.levels}")
    if args.max_newton < 1:
        raise BadInput(f"--max-newton must be at least 1, got {args.max_newton}")
    if args.coarse_tol is not None and not (0.0 < args.coarse_tol < 1.0):
        raise BadInput(f"--coarse-tol must lie in (0, 1), got {args.coarse_tol}")
    if args.max_vertices is not None and args.max_vertices < 1:
        raise BadInput(f"--max-vertices must be a positive integer, got {args.max_vertices}")
    kwargs = {"levels": args.levels}
    if args.h is not None:
        kwargs["h"] = args.h
    if scene == "user":
        for k in DATA_OPTIONS:
            if getattr(args, k) is not None:
                kwargs[k] = getattr(args, k)
    return scene, kwargs


def _check_before_meshing(args, scene, kwargs, comm):
    """Refuse at once what cannot work, before any mesh is built: an output folder that cannot
    be written, method options that `solve` would refuse (PETSc options PETSc would not use,
    --tol with adaptive Newton, a γ or --nu out of range, …: `driver.check_method`), and a
    mesh whose run needs more memory than the processes have (or more vertices than
    --max-vertices). Returns the parsed PETSc options."""
    from ..model import checks, folders
    from ..model.petsc_options import parse_petsc_options
    from ..model.scenes import DEFAULT_H
    from .driver import MEMORY_METHOD, check_method
    petsc_options = parse_petsc_options(args.petsc_options)
    if args.out is not None:
        from .outputs import FILES
        folders.check_output_folder(args.out, comm, names=FILES)
    *_, coarse, _ = check_method(
        args.levels, newton=args.newton, cfun=args.cfun, solver=args.solver,
        system=args.system, petsc_options=petsc_options, nu=args.nu,
        max_linear_its=args.max_linear_its, tol=args.tol, max_newton=args.max_newton,
        estimators=not args.no_estimators, alg_flux=args.alg_flux, gamma_lin=args.gamma_lin,
        gamma_alg=args.gamma_alg, nested=args.nested, coarse=args.coarse or "residual",
        coarse_tol=args.coarse_tol, comm=comm)
    if args.coarse is not None and coarse is None:   # (the API lets its default pass)
        raise BadInput("--coarse applies to the adaptive variant with nested iteration only")
    domain = scene if scene in ("disk", "square") else kwargs.get("domain", "disk")
    checks.check_request(kwargs.get("h", DEFAULT_H), args.levels, domain, kwargs.get("mesh"),
                         args.max_vertices, comm=comm, estimators=not args.no_estimators,
                         processes=comm.size, replicated=False, alg_flux=args.alg_flux,
                         **MEMORY_METHOD[args.solver])
    return petsc_options


def _solve(args):
    scene, kwargs = _scene_arguments(args)
    quiet_jit_logging()
    from mpi4py import MPI

    from ..model import folders, scenes
    from .driver import solve
    from .outputs import room_for, write_outputs
    world = MPI.COMM_WORLD
    petsc_options = _check_before_meshing(args, scene, kwargs, world)
    say = (lambda line: None) if args.quiet or world.rank != 0 else \
        (lambda line: print(line, file=sys.stderr, flush=True))
    t = time.perf_counter()
    problem = scenes.make(scene, comm=world, max_vertices=args.max_vertices, progress=say,
                          **kwargs)
    fine = problem.hierarchy.meshes[-1].topology
    say(f"mesh and {args.levels} uniform refinement(s) made in {time.perf_counter() - t:.2f} "
        f"s: the finest mesh has {fine.index_map(0).size_global:,} vertices and "
        f"{fine.index_map(2).size_global:,} cells on {world.size} process(es)")
    if args.out is not None:           # (before the run: the disk may be full already)
        folders.check_output_room(args.out, room_for(problem.mesh), world)
    sol = solve(problem, newton=args.newton, cfun=args.cfun, solver=args.solver,
                system=args.system, petsc_options=petsc_options, nu=args.nu,
                max_linear_its=args.max_linear_its, tol=args.tol, max_newton=args.max_newton,
                estimators=not args.no_estimators, progress=not args.quiet,
                gamma_lin=args.gamma_lin, gamma_alg=args.gamma_alg, alg_flux=args.alg_flux,
                initial_guess=args.initial_guess, nested=args.nested,
                max_vertices=args.max_vertices, coarse=args.coarse or "residual",
                coarse_tol=args.coarse_tol)
    summary = sol.summary()          # collective (reductions): every rank computes it
    if args.out is not None:
        say(f"writing the outputs into {args.out}")
        write_outputs(sol, args.out, summary)     # (the same summary: made once)
    if world.rank == 0:
        keys = ("scene", "n_vertices", "n_cells", "h", "newton", "cfun", "solver", "system",
                "processes", "converged", "newton_iterations", "linear_iterations",
                "wall_time_s", "energy_error", "eta", "effectivity", "nested")
        line = {k: summary[k] for k in keys}
        line["newton_per_level"] = [r["newton_iterations"] for r in summary["per_level"]]
        emit(json.dumps(line))
        if not sol.converged:
            print(f"membranes: not converged: {sol.reason}", file=sys.stderr)
    return 0 if sol.converged else EXIT_NOT_CONVERGED


def _scenes():
    from mpi4py import MPI

    from ..model.scenes import NEEDS, SCENES
    if MPI.COMM_WORLD.rank == 0:                  # (under mpirun: printed once)
        emit("\n".join(f"{name:8s} {fn.__doc__.strip().splitlines()[0]}\n"
                       f"{'':8s} needs: {NEEDS[name]}" for name, fn in SCENES.items()))
    return 0


def _glue_values(argv):
    """["--f1", "-1+y"] -> ["--f1=-1+y"]: a formula or number may start with '-'."""
    out, it = [], iter(argv)
    for a in it:
        nxt = next(it, None) if a in VALUE_OPTIONS else None
        if nxt is not None:
            out.append(f"{a}={nxt}")
        else:
            out.append(a)
    return out


def _unglued(message, argv, glued):
    """A parser's message with the options `_glue_values` joined written as they were given
    (`membranes stability --levels 1`: "unrecognized arguments: --levels 1", not
    "--levels=1")."""
    given = iter(argv)
    for item in glued:
        a = next(given)
        if item != a:                   # (glued: `a` and the next argument)
            message = message.replace(item, f"{a} {next(given)}")
    return message


def _leave(errors, code, say):
    """After an error on several processes: the errors of the API are collective (every
    process meets them at the same point), but one met by some processes only would leave
    them waiting in MPI_Finalize for processes that wait in a collective for them, and the
    run would hang. So the processes that met an error wait AGREE_SECONDS on a barrier of
    their own communicator `errors`: if the others do not join, this process says why (if it
    has not) and ends itself with `code` without MPI_Finalize (mpirun then ends the rest)."""
    if errors is None:
        return
    request, end = errors.Ibarrier(), time.monotonic() + AGREE_SECONDS
    while time.monotonic() < end:
        if request.Test():
            return
        time.sleep(0.01)
    say()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def command():
    """The `membranes` console script and `python -m membranes.app.cli`: `main` in a process
    that exits right after it, so that a signal met once the run's outputs are in place is
    said and the exit goes on (`interrupts.settle`), not a KeyboardInterrupt in the
    interpreter's exit (exit -2, the outputs whole)."""
    interrupts.process_ends = True
    return main()


def main(argv=None):
    _standard_streams()
    # the handlers first: MPI's start (mpi4py's import, a few tenths of a second) would
    # otherwise meet Ctrl-C with a traceback
    previous = interrupts.install()
    world = errors = None
    try:
        from mpi4py import MPI
        world = MPI.COMM_WORLD
        interrupts.among(world.rank, world.size)
        errors = world.Dup() if world.size > 1 else None
        return _ended(argv, world, errors)
    except BrokenPipeError:   # stdout or stderr read by a process that has gone (`| head`),
        return _pipe_closed(errors)     # met by the run or by the line that says its end
    except KeyboardInterrupt as e:   # Ctrl-C, SIGTERM, SIGHUP: one line, staged outputs gone
        return _signalled(e, world, errors)      # (also in MPI's start, before `_ended`)
    finally:
        interrupts.restore(previous)
        if errors is not None:
            errors.Free()


def _standard_streams():
    """A process started with stdin, stdout or stderr closed (`>&-`) gets /dev/null in its
    place, as though what it reads or prints were discarded: Python leaves sys.stdout None,
    on which ufl's import failed (a traceback, exit 1), and a file opened later would take
    the free descriptor and receive what is printed. A character stdout's encoding lacks
    (μ, λ, § under a Latin-1 or ASCII locale) is printed as an escape (`\\u03bc`), as Python
    does on stderr: it was a UnicodeEncodeError, a ValueError, said as bad input (exit 2)."""
    for fd, name, mode in ((0, "stdin", "r"), (1, "stdout", "w"), (2, "stderr", "w")):
        try:
            os.fstat(fd)
        except OSError:
            devnull = os.open(os.devnull, os.O_RDWR)
            if devnull != fd:
                os.dup2(devnull, fd)
                os.close(devnull)
            if getattr(sys, name) is None:
                setattr(sys, name, open(fd, mode, closefd=False))
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")


def _ended(argv, world, errors):
    """Run the command; its exit code, also for an error (one line; a signal: `main`)."""
    try:
        try:
            code = _main(argv)
        except SystemExit:    # --help, --version: their text is out before the exit
            with writing_stdout():
                sys.stdout.flush()
            raise
        with writing_stdout():   # (a failed write is met here, not at the interpreter's exit)
            sys.stdout.flush()
        return code
    except BrokenPipeError:
        raise
    except Exception as e:
        interrupts.raise_pending()     # (an error met after a signal is the signal's)
        if isinstance(e, ValueError):  # BadInput and every data/mesh error of the API
            return _one_line(world, errors, e, EXIT_BAD_INPUT)
        if isinstance(e, MemoryError):   # a size beyond memory the checks let through
            return _out_of_memory(world, errors, str(e) or "an allocation failed")
        if "PetscMallocA()" in str(e):       # PETSc's (a petsc4py.PETSc.Error with its trace)
            return _out_of_memory(world, errors, "PETSc could not allocate memory")
        if isinstance(e, ImportError) and e.name == "dolfinx" \
                and str(e).startswith("membranes needs"):       # fem.require_dolfinx
            return _one_line(world, errors, e, 1)
        import traceback
        _leave(errors, 1, traceback.print_exc)
        raise


def _out_of_memory(world, errors, what):
    """A size beyond memory met during the run (the checks before it count what the node
    has, not a process's own limits, `checks.own_limits`): said as bad input, in one line."""
    from ..model.checks import own_limits
    limits = own_limits()
    return _one_line(world, errors, f"out of memory ({what})" +
                     (f"; this process's limits: {limits}" if limits else ""), EXIT_BAD_INPUT)


def _signalled(e, world, errors):
    """The exit code of the signal that raised `e`, said in one line by process 0 (`world`
    None: met in MPI's start)."""
    interrupts.caught()
    code, said = 128 + interrupts.signal_of(e), interrupts.said(e)   # (EXIT_HUNG_UP, …)
    if (world.rank if world is not None else _rank()) == 0:
        print(f"membranes: {said}", file=sys.stderr, flush=True)
    if errors is not None:  # the others may wait in a collective: no MPI_Finalize
        sys.stdout.flush()
        os._exit(code)
    return code


def _rank():
    """This process's rank in MPI_COMM_WORLD, 0 where MPI has not started."""
    MPI = sys.modules.get("mpi4py.MPI")
    try:
        return MPI.COMM_WORLD.rank if MPI is not None and MPI.Is_initialized() else 0
    except AttributeError:      # (mpi4py's import itself was interrupted)
        return 0


def _one_line(world, errors, error, code):
    """Say `error` in one line (process 0; every process meets the same error) and return
    `code`."""
    line = "membranes: error: " + " ".join(str(error).split())
    if world.rank == 0:
        print(line, file=sys.stderr, flush=True)
    _leave(errors, code,   # (alone, another process says it)
           lambda: world.rank != 0 and print(line, file=sys.stderr, flush=True))
    return code


def _pipe_closed(errors):
    """End silently with EXIT_BROKEN_PIPE, as the shell's tools do when the process reading
    their output has gone (`membranes scenes | head -1`). The error ended the run where it
    was met: outputs not yet staged are not written. Stdout is pointed at /dev/null, so that
    what is left in its buffer raises nothing at the interpreter's exit."""
    _stdout_to_devnull()
    _leave(errors, EXIT_BROKEN_PIPE, lambda: None)
    return EXIT_BROKEN_PIPE


def _main(argv=None):
    argv = sys.argv[1:] if argv is None else list(argv)
    glued = _glue_values(argv)
    try:
        args = _parser().parse_args(glued)
    except BadInput as e:
        raise BadInput(_unglued(str(e), argv, glued)) from None
    interrupts.take_back()           # (the signals PETSc's initialisation took)
    if args.command == "scenes":
        return _scenes()
    if args.command == "report":
        from .report import main as report_main
        quiet_jit_logging()
        return report_main(args)
    if args.command == "stability":
        from .stability import main as stability_main
        quiet_jit_logging()
        return stability_main(args)
    return _solve(args)


if __name__ == "__main__":
    sys.exit(command())
