"""What every literate demo of demos/ starts with: its two options, a print on rank 0 and
matplotlib where it can be imported."""

import argparse
import os
import sys

from mpi4py import MPI


def options(name, description, out_help):
    """Parse the demo's command line: --quick (a coarse mesh that runs in seconds; also the
    environment variable MEMBRANES_DEMO_QUICK=1, which the tests set) and --out (default
    out/demos/NAME; made if missing; one error line and exit 2 where it cannot be
    written). Silences the JIT's log lines, so that stderr keeps only the demo's own lines.
    Returns (out, quick)."""
    from .logs import quiet_jit_logging
    quiet_jit_logging()
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help="a coarse mesh (seconds)")
    parser.add_argument("--out", default=os.path.join("out", "demos", name),
                        type=os.path.expanduser, help=out_help)
    args = parser.parse_args()
    from ..model.folders import check_output_folder
    try:            # an unwritable or empty --out: one line and exit 2, as the CLI
        check_output_folder(args.out, MPI.COMM_WORLD)
    except ValueError as e:
        if MPI.COMM_WORLD.rank == 0:
            print(f"{parser.prog}: error: {e}", file=sys.stderr, flush=True)
        sys.exit(2)
    os.makedirs(args.out, exist_ok=True)
    return args.out, args.quick or os.environ.get("MEMBRANES_DEMO_QUICK") == "1"


def figure_class():
    """matplotlib's Figure, or None where matplotlib cannot be imported: it is no dependency
    of the package (a plain `pip install` lacks it), so a demo then says so in one line and
    goes on to its outputs without its picture. The advice pins numpy, as
    `membranes.app.report.check_matplotlib` does."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:
        import numpy as np
        say(f"picture skipped: matplotlib cannot be imported ({e}): pip install matplotlib "
            f"numpy=={np.__version__}")
        return None
    return Figure


def say(*line):
    """print(*line) on process 0 of COMM_WORLD only, flushed."""
    if MPI.COMM_WORLD.rank == 0:
        print(*line, flush=True)
