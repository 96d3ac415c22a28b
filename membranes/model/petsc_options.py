"""PETSc options checked before a run starts (issue 29; the size and output-folder checks are
in `membranes.model.checks`).

A token that is not ``-name [value]`` is refused by `parse_petsc_options`; an option PETSc
never queries (a misspelt name, or one that does not apply to the solver configured) is found
through PETSc's own record of the options it read (`unused_petsc_options`, PetscOptionsUsed),
and `check_petsc_options_used` refuses it before the solve by configuring a throw-away KSP
(and inner PC) with the run's options. Every check raises ValueError with a one-line message;
the command line turns it into exit code 2.
"""

import ctypes
import numbers
import shlex
from collections.abc import Mapping

# ## PETSc options
#
# An option is '-' and a name (a letter, then letters, digits and '_'), followed by at most
# one value, any token that is not itself an option (so -1e-3 is a value). What is not of
# that form is refused here rather than passed on: PETSc would store "-pc_type=vertex_amg" as
# an option of that whole name and never read it.

def _valid_name(name):
    return bool(name) and name[0].isalpha() and name.replace("_", "a").isalnum() and \
        name.isascii()


def option_value(name, value):
    """The value of option -`name` as PETSc's database takes it: None, a string, a bool or
    a real number (numpy's as Python's: np.int64(50) was refused as no number, and summary
    .json's options are Python values)."""
    if value is None or isinstance(value, (str, bool)):
        return value
    if isinstance(value, numbers.Real):
        return value.item() if hasattr(value, "item") else value
    raise ValueError(f"PETSc option -{name}: value {value!r} is not a string or number")


def _is_option(token):
    return token[:1] == "-" and token[1:2].isalpha()


def parse_petsc_options(options):
    """PETSc options as a dict {name: value or None}, names without their '-' and in lower
    case (PETSc ignores the case of option names: -KSP_RTOL is -ksp_rtol): from a string
    ("-ksp_type gmres -ksp_monitor -pc_factor_shift_amount -1e-3") or a dict (whose names
    may carry the '-'). ValueError for a token that is not -name [value]: '-pc_type=ilu',
    'pc_type' where an option is expected, a value after a value, a name with other
    characters, a name given twice (in any case); for a value that is not a string, number or
    bool; for options that are neither a string nor a mapping (a list of tokens read as the
    text of the list)."""
    if options is None:
        return {}
    if isinstance(options, Mapping):
        out = {}
        for name, value in options.items():
            bare = str(name)[1:] if str(name).startswith("-") else str(name)
            if not _valid_name(bare):
                raise ValueError(f"PETSc option {name!r} is not a valid option name "
                                 f"(a letter, then letters, digits and '_')")
            if bare.lower() in out:                       # (-KSP_TYPE and -ksp_type)
                raise ValueError(f"PETSc options: -{bare.lower()} is given more than once")
            out[bare.lower()] = option_value(bare, value)
        return out
    if not isinstance(options, str):
        raise ValueError(f"PETSc options must be a string '-name value ...' or a dict, got "
                         f"{type(options).__name__}")
    try:
        tokens = shlex.split(str(options))
    except ValueError as e:
        raise ValueError(f"PETSc options {options!r}: {e}") from None
    out, name = {}, None
    for token in tokens:
        if _is_option(token):
            name = token[1:]
            if not _valid_name(name):
                fix = f" (write '-{name.replace('=', ' ', 1)}')" if "=" in name else ""
                raise ValueError(f"PETSc options: {token!r} is not -name [value]{fix}")
            name = name.lower()
            if name in out:        # (PETSc would keep the last and drop the first unsaid)
                raise ValueError(f"PETSc options: -{name} is given more than once")
            out[name] = None
        elif "=" in token:
            raise ValueError(f"PETSc options: {token!r} is not -name [value] "
                             f"(write '-{token.lstrip('-').replace('=', ' ', 1)}')")
        elif name is not None and out[name] is None:
            out[name] = token
        else:
            raise ValueError(f"PETSc options: value {token!r} follows no option "
                             f"(an option is -name [value])")
    return out


def _petsc_used():
    """PETSc's PetscOptionsUsed(options, name, &used) from the library petsc4py runs on (the
    same options database), or None where it cannot be found. petsc4py 3.18 has no binding for
    it (its Options has getAll, hasName, delValue, but no 'used')."""
    from petsc4py import PETSc  # noqa: F401  (loads the library)
    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "libpetsc" in line.split()[-1]}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            fn = ctypes.CDLL(path).PetscOptionsUsed
        except (OSError, AttributeError):
            continue
        fn.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.POINTER(ctypes.c_int)]
        fn.restype = ctypes.c_int
        return fn
    return None


def unused_petsc_options(options, prefix=""):
    """The names of `options` (names without '-') that PETSc's global options database holds
    under `prefix` but has never read: no PETSc object queried them. Call it at the end of a
    run, before the options are taken out of the database. None where PETSc's record cannot be
    read (`_petsc_used`)."""
    used = _petsc_used()
    if used is None:
        return None
    from petsc4py import PETSc
    held = PETSc.Options().getAll()
    unused = []
    for name in options:
        full = prefix + str(name).lstrip("-")
        flag = ctypes.c_int(0)
        if full in held and used(None, full.encode(), ctypes.byref(flag)) == 0 and \
                not flag.value:
            unused.append(str(name).lstrip("-"))
    return unused


# options PETSc reads only inside a solve (KSPSolve's KSPConvergedReasonViewFromOptions): no
# trial set-up sees them read, but the run's solvers keep their options in the database while
# they live (membranes.linalg.preconditioners.put_options), so a solve reads them
READ_IN_SOLVE = ("ksp_converged_reason",)

_trials = iter(range(1 << 62))
# the PCs whose options a trial set-up on a small identity reads (their sub-solvers' and
# factorisations'), safely
SET_UP_PCS = ("bjacobi", "asm", "gasm", "lu", "cholesky", "ilu", "icc")


def _identity(comm, n=2):
    """The identity with n rows on each process of `comm` (AIJ: sequential on one process,
    MPI on several, as the run's matrices): the operator of a trial set-up."""
    from petsc4py import PETSc
    A = PETSc.Mat().createAIJ([(n, None), (n, None)], nnz=(1, 0), comm=comm)
    start, end = A.getOwnershipRange()
    for i in range(start, end):
        A.setValue(i, i, 1.0)
    A.assemble()
    return A


def unused_by_trial(options, kind="ksp", setup=False, comm=None):
    """The names of `options` that a throw-away PETSc KSP (or PC, `kind='pc'`) configured
    with them (setFromOptions) does not read: an option a solve configured the same way
    cannot read either, when its options are read at configuration (as the current
    solvers do: they take their options out of the database right after setFromOptions).
    With `setup` the KSP is also set up on a small identity matrix, so that the options read
    then count too: those of the sub-solvers a PC creates at its set-up (the paper preset's
    block Jacobi, -sub_pc_type) and of a factorisation (MUMPS's -mat_mumps_icntl_14).
    `comm` (a PETSc or mpi4py communicator; default one process): the run's, where the
    set-up must meet the run's distributed matrix type (PETSc has no ILU of an MPI matrix).
    Collective on it. PETSc errors (an unknown KSP type, a bad value) pass on as
    ValueError."""
    from petsc4py import PETSc
    prefix = f"membranes_check_{next(_trials)}_"
    database = PETSc.Options()
    for name, value in options.items():
        database[prefix + name] = value
    comm = PETSc.COMM_SELF if comm is None else comm
    obj = (PETSc.KSP() if kind == "ksp" else PETSc.PC()).create(comm)
    A = None
    try:
        obj.setOptionsPrefix(prefix)
        try:
            obj.setFromOptions()
            if kind == "ksp":     # PETSc checks the KSP's norm type against its PC side here
                obj.getNormType()  # (-ksp_type cg with the paper's right preconditioning)
            if setup and kind == "ksp":
                A = _identity(comm)
                obj.setOperators(A)
                obj.setUp()
        except PETSc.Error as e:
            message = str(e).strip().splitlines()[-1].split("] ", 1)[-1]
            if "mpiaij" in message and "factorization" in message.lower():
                message += (" (a matrix distributed over processes: for LU or Cholesky "
                            "use -pc_factor_mat_solver_type mumps, for ILU -pc_type "
                            "bjacobi -sub_pc_type ilu)")
            raise ValueError(f"PETSc options: {message}") from None
        return unused_petsc_options(options, prefix)
    finally:
        obj.destroy()
        if A is not None:
            A.destroy()
        for name in options:
            database.delValue(prefix + name)


def check_petsc_options_used(user, ksp_options, inner=None, comm=None):
    """Refuse the first of the user's options `user` (names without '-') that PETSc would not
    read: those whose name starts with a prefix of `inner` (a dict: prefix → the complete
    options of an inner PC, such as the mean/gap split's 'mean_' and 'gap_') go (without it)
    to a PC configured with those options, the others to a KSP configured with `ksp_options`
    (the complete options the solve applies, defaults included). ValueError naming it, in one
    line, with the KSP and PC types of the options it was for. `comm`: the run's (the trial
    set-up's, `unused_by_trial`); collective on it."""
    inner = inner or {}

    def prefix_of(name):
        return next((p for p in inner if name.startswith(p)), None)

    outer = [name for name in user if prefix_of(name) is None]
    # a set-up reads the options of the PC's sub-solvers and factorisation (SET_UP_PCS only:
    # PCMG with levels and no interpolation crashes in its set-up); not with the inner PCs of
    # a split (a Python PC, so the trial's PC is none: -pc_factor_levels, which the split
    # would not read, counts as unused)
    trial = {**ksp_options, "pc_type": "none"} if inner else ksp_options
    unused = unused_by_trial(trial, "ksp", setup=trial.get("pc_type") in SET_UP_PCS,
                             comm=comm)
    if unused is None:
        return
    unused = [name for name in outer if name in unused and name not in READ_IN_SOLVE]
    for prefix, pc_options in inner.items():
        mine = {name[len(prefix):] for name in user if prefix_of(name) == prefix}
        if mine:
            unused += [prefix + name for name in unused_by_trial(pc_options, "pc") or []
                       if name in mine]
    if unused:
        prefix = prefix_of(unused[0])
        options = inner[prefix] if prefix is not None else ksp_options
        what = " ".join(f"-{prefix or ''}{k} {v}" for k, v in options.items()
                        if k in ("ksp_type", "pc_type"))
        whose = "the solver" if prefix is None else f"the inner preconditioner '{prefix}'"
        raise ValueError(f"PETSc option -{unused[0]} is not used by {whose} of this run "
                         f"({what}): misspelt, or not an option of this KSP/PC")
