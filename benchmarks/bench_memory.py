"""Benchmark (issue 28): the peak memory of ours per process on 1, 2 and 4 processes.

A distributed run shares the mesh, the matrices and the estimators out over the processes, so
the largest peak of one process should fall roughly like 1/P above the fixed part every
process has (interpreter, dolfinx, PETSc): the target is (largest per-process peak at P = 4)
/ (serial peak) ≤ 0.4.

The disk scene (§9), `scenes.disk(h=H0, levels=J)`, H0 = 0.2 unless a size says `J:H0`;
the default sizes 6 and 6:0.132 have 435 201 and 931 329 vertices on T_J (about 4.4e5 and
9.3e5). Ours with the API's defaults, `solve(problem)`, runs once per size and number of
processes P (`--procs`, default 1 2 4), each in a fresh process (`mpirun --oversubscribe
-n P` for P > 1: the machine may have fewer cores; the memory does not depend on them). The
peak is `resource.getrusage`'s maximum resident set of each process at the end of the run
(mesh hierarchy included; benchmarks/fresh.py).

Before each launch the run's memory, summed over its processes, is estimated (model.checks's
bytes per vertex, or the figure measured by the larger runs made so far, whichever is
larger) and the run is skipped with a message if that exceeds `--margin` (0.8) of the
machine's MemAvailable at that moment.

Printed per size and P: the largest per-process peak, the sum over the processes, both
relative to the serial peak, and the sum per 1e5 vertices; then, where the largest P is above
1 and both runs were made, the ratio at the largest P against the target. Nothing is
asserted.

Usage: `.venv/bin/python benchmarks/bench_memory.py [--sizes J[:H0] ...] [--procs P ...]
[--blas-threads T] [--timeout S] [--margin F]`; a smoke run: `--sizes 2 3`.
"""

import argparse
import sys

import fresh

DEFAULT_SIZES = ("6", "6:0.132")
TARGET = 0.4          # largest per-process peak at P = 4 over the serial peak


def main(args):
    guard = fresh.MemoryGuard(args.margin)
    print(f"BLAS threads: {fresh.blas_threads(args.blas_threads)}", flush=True)
    print(f"Software: {fresh.software()}", flush=True)
    if not args.no_warmup:
        # the JIT cache warm
        r = fresh.launch("ours", "1", 1, args.timeout, args.blas_threads)
        if "failed" in r:
            print(f"warm-up: failed: {r['failed']}", file=sys.stderr)
    rows = {}
    for s in args.sizes:
        n = fresh.vertices(s)
        for p in args.procs:
            skip = guard.room(n, p)
            if skip:
                print(f"size {s} ({n} vertices), P = {p}: {skip}", flush=True)
                continue
            r = fresh.launch("ours", s, p, args.timeout, args.blas_threads)
            if "failed" in r:
                print(f"size {s}, P = {p}: failed: {r['failed']}", flush=True)
                continue
            guard.measured(r)
            rows[s, p] = r
            print(f"size {s} ({r['vertices']} vertices), P = {p}: peaks "
                  f"{', '.join(f'{g:.3f}' for g in r['peaks_gib'])} GiB, method "
                  f"{r['method_s']:.2f} s, process {r['process_s']:.2f} s, converged "
                  f"{r['converged']}", flush=True)
    print()
    print("| size | vertices | P | largest peak per process GiB | sum over processes GiB "
          "| largest / serial | sum / serial | GiB per 1e5 vertices (sum) |")
    print("|---|---|---|---|---|---|---|---|")
    for s in args.sizes:
        serial = rows.get((s, 1))
        for p in args.procs:
            r = rows.get((s, p))
            if r is None:
                print(f"| {s} | | {p} | not run | | | | |")
                continue
            top, total = max(r["peaks_gib"]), sum(r["peaks_gib"])
            rel = (f"{top / max(serial['peaks_gib']):.3f} | "
                   f"{total / max(serial['peaks_gib']):.3f}") if serial else "— | —"
            print(f"| {s} | {r['vertices']} | {p} | {top:.3f} | {total:.3f} | {rel} | "
                  f"{total / r['vertices'] * 1e5:.3f} |")
    print()
    last = max(args.procs)
    for s in args.sizes:
        serial, par = rows.get((s, 1)), rows.get((s, last))
        if serial and par and last > 1:
            ratio = max(par["peaks_gib"]) / max(serial["peaks_gib"])
            print(f"size {s} ({serial['vertices']} vertices): largest per-process peak at "
                  f"P = {last} / serial peak = {max(par['peaks_gib']):.3f} / "
                  f"{max(serial['peaks_gib']):.3f} = {ratio:.3f} (target <= {TARGET}: "
                  f"{'met' if ratio <= TARGET else 'not met'})")


def parse(argv=None):
    parser = argparse.ArgumentParser(
        description="Peak memory per process of ours on 1, 2, 4 processes (issue 28); the "
                    "module notes say what is measured.")
    args = fresh.parse_common(parser, argv, DEFAULT_SIZES, (1, 2, 4))
    args.procs = sorted(set(args.procs))
    return args


if __name__ == "__main__":
    main(parse())
