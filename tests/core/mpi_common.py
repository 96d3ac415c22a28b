"""What the MPI scripts of tests/core share (each is run as a script from this folder)."""

import json
import sys


def print_agreed(comm, out):
    """Print `out` (a JSON-able dict of global figures) as one JSON line on rank 0, after
    checking that every rank computed the same figures (their JSON texts are compared, so NaN
    agrees with NaN); where they differ every rank exits with status 1. Collective."""
    text = json.dumps(out, sort_keys=True)
    if any(other != text for other in comm.allgather(text)):
        if comm.rank == 0:
            print("the ranks disagree on the global figures", file=sys.stderr)
        sys.exit(1)
    if comm.rank == 0:
        print(text, flush=True)
