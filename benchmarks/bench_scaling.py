"""Benchmark (issue 31): ours against the SNES VI peers on the disk, serial and on P
processes, side by side in one run.

The disk scene (§9), `scenes.disk(h=H0, levels=J)`, H0 = 0.2 unless a size says `J:H0`.
The default sizes 5, 6 and 6:0.132 have 109 057, 435 201 and 931 329 vertices on T_J (about
1.1e5, 4.4e5, 9.3e5; the meshes of BENCHMARKS.md). For each size, each number of processes
P (`--procs`) and each method, one fresh process (`mpirun --oversubscribe -n P` for P > 1;
benchmarks/fresh.py says what each method runs):

* ours: `solve(problem)` with the API's defaults (adaptive, 'amg' preset, nested, ν flux,
  final certificate);
* nested: the nested peer, `nested_peer(problem)` (SNES vinewtonrsls, CG + BoomerAMG,
  rtol 1e-8; §10);
* certified: the nested peer, then our estimators set up and evaluated once at its final
  iterate (what it costs the peer to give the guarantee ours gives);
* plain: the plain peer, `plain_peer(problem)` (slow: `--no-plain` leaves it out).

Measured per run: the whole process's wall time (here, around the subprocess: start-up, mesh
hierarchy, method, energy error), the method's own wall time (its solver's clock, without
the mesh hierarchy), the peak resident memory of every process, the final energy error, η
where certified, Newton (SNES) steps. The methods alternate run by run (and the order is
reversed every other repeat), so that the machine's drift is shared among them; `--repeat N`
runs every (P, method) N times and the figures are the medians. Printed: a table, then the
ratios ours / nested peer (process and method time), ours / certified nested peer, energy
error ours / peer, peak memory ours / peer, the certificate's own cost against the peers
(the certified peer's set-up and evaluation, and its peak against the nested peer's: the
floors of a certified run's ratios), the
speed-up of ours on P processes (each also repeat by repeat), and where the method time
goes: the coarse levels, the solve on T_J, the estimator set-up and the estimates
(`fresh.phases_of_ours`, `fresh.phases_of_peer`).
Nothing is asserted: the figures depend on the machine and on what else runs on it.

Before each launch the run's memory is estimated (fresh.MemoryGuard) and the run is skipped
with a message if it would not fit in the memory available.

Usage: `.venv/bin/python benchmarks/bench_scaling.py [--sizes J[:H0] ...] [--procs P ...]
[--repeat N] [--no-plain] [--blas-threads T] [--timeout S] [--margin F]`; a smoke run:
`--sizes 2 3`. `--blas-threads 1` gives every process one BLAS thread (OpenBLAS otherwise
starts one per core in each, which oversubscribes the cores on P processes).
"""

import argparse
import statistics
import sys

import fresh

DEFAULT_SIZES = ("5", "6", "6:0.132")
LABELS = {"ours": "ours", "nested": "nested peer", "certified": "certified nested peer",
          "plain": "plain peer"}


def median(runs, key):
    values = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(values) if values else None


def peak(r):
    return max(r["peaks_gib"])


def summarise(runs):
    """The medians of one (size, P, method)'s successful runs."""
    ok = [r for r in runs if "failed" not in r and "skipped" not in r]
    if not ok:
        return None
    out = {k: median(ok, k) for k in ("process_s", "method_s", "mesh_s", "energy_error",
                                      "eta", "newton", "linear", "system_s", "page_faults")}
    # the estimators' share of the method time: ours, set-up and evaluations; the
    # certified peer, its certificate
    shares = [sum(r["estimator_s"]) if r.get("estimator_s") else r.get("certificate_s")
              for r in ok]
    out["estimators_s"] = None if None in shares else statistics.median(shares)
    out["peak_gib"] = statistics.median(peak(r) for r in ok)
    out["peak_sum_gib"] = statistics.median(sum(r["peaks_gib"]) for r in ok)
    out["vertices"] = ok[0]["vertices"]
    out["per_level"] = ok[0]["per_level"]
    out["phases"] = {k: statistics.median(r["phases"][k] for r in ok)
                     for k in ok[0].get("phases", {})}
    out["converged"] = all(r["converged"] for r in ok)
    out["runs"] = len(ok)
    return out


def fmt(x, spec):
    return "—" if x is None else format(x, spec)


def table(sizes, procs, methods, stats):
    print("| size | vertices | P | method | steps (per level) | linear | method s | process s "
          "| estimators s | mesh s | peak GiB (largest, sum) | energy error | η | η/error "
          "| runs |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for s in sizes:
        for p in procs:
            for m in methods:
                r = stats.get((s, p, m))
                if r is None:
                    print(f"| {s} | | {p} | {LABELS[m]} | no successful run ||||||||||")
                    continue
                eff = r["eta"] / r["energy_error"] if r["eta"] and r["energy_error"] else None
                levels = "+".join(map(str, r["per_level"]))
                print(f"| {s} | {r['vertices']} | {p} | {LABELS[m]} | {r['newton']:g} "
                      f"({levels}) | {r['linear']:g} | {r['method_s']:.2f} | "
                      f"{r['process_s']:.2f} | {fmt(r['estimators_s'], '.2f')} | "
                      f"{r['mesh_s']:.2f} | {r['peak_gib']:.3f}, "
                      f"{r['peak_sum_gib']:.3f} | {fmt(r['energy_error'], '.4e')} | "
                      f"{fmt(r['eta'], '.4e')} | {fmt(eff, '.3f')} | "
                      f"{r['runs']}{'' if r['converged'] else ' NOT CONVERGED'} |")


PHASES = (("coarse", "coarse levels"), ("solve", "solve on T_J"),
          ("set-up", "estimator set-up"), ("estimates", "estimates"), ("rest", "rest"))


def phases(sizes, procs, methods, stats):
    """Where the method time goes (medians, rank 0's clock; `fresh.phases_of_ours`,
    `phases_of_peer`): the coarse levels, the Newton (SNES) steps on T_J, the estimators'
    set-up and the estimates (ours: the gates and full evaluations of T_J's iterates; the
    certified peer: one evaluation), the rest (T_J's discretisation); and the kernel's share
    of the method time, its system CPU seconds and minor page faults (`fresh.child`)."""
    print()
    print("| size | P | method | " + " | ".join(f"{label} s" for _, label in PHASES)
          + " | method s | of which system s | page faults |")
    print("|---|---|---|" + "---|" * (len(PHASES) + 3))
    for s in sizes:
        for p in procs:
            for m in methods:
                r = stats.get((s, p, m))
                if r is None or not r["phases"] or m == "plain":
                    continue
                cells = [fmt(r["phases"].get(k), ".2f") for k, _ in PHASES]
                print(f"| {s} | {p} | {LABELS[m]} | " + " | ".join(cells)
                      + f" | {r['method_s']:.2f} | {fmt(r.get('system_s'), '.2f')} | "
                      f"{fmt(r.get('page_faults'), ',.0f')} |")


def by_repeat(pairs, spec):
    """' (repeat by repeat: …)' for more than one ratio of `paired`, else ''."""
    if len(pairs) < 2:
        return ""
    return " (repeat by repeat: " + ", ".join(f"{x:{spec}}" for x in pairs) + ")"


def paired(runs, a, b, key):
    """Ratios a/b of `key` repeat by repeat (the two runs of a repeat are close in time)."""
    by = {}
    for r in runs:
        if "failed" not in r and "skipped" not in r:
            by.setdefault(r["repeat"], {})[r["method"], r["processes"]] = r
    return [rep[a][key] / rep[b][key] for rep in by.values() if a in rep and b in rep]


def certificate_floor(stats, s, p):
    """What the certificate alone costs, against the peers' method times: the certified
    peer's estimator set-up and evaluation (the median phases), which a certified run of ours
    pays as well (the same set-up, at least one evaluation). A ratio ours / peer below the
    certificate's own ratio cannot be reached by making Newton faster. Likewise the memory:
    the certified peer's peak is the mesh, the discretisation and the certificate's footprint
    (its SNES objects are freed before the set-up), which a certified run of ours holds as
    well. None without both peers' runs."""
    nested, certified = stats.get((s, p, "nested")), stats.get((s, p, "certified"))
    split = (certified or {}).get("phases") or {}
    if nested is None or split.get("set-up") is None or split.get("estimates") is None:
        return None
    cert = split["set-up"] + split["estimates"]
    return (f"the certificate alone (set-up {split['set-up']:.2f} s + one evaluation "
            f"{split['estimates']:.2f} s) is {cert / nested['method_s']:.3f} of the nested "
            f"peer's method time and {cert / certified['method_s']:.3f} of the certified "
            f"peer's, and the certified peer's peak {certified['peak_gib']:.3f} GiB is "
            f"{certified['peak_gib'] / nested['peak_gib']:.3f} of the nested peer's: the "
            f"floors of a certified run's ratios (up to the machine's spread)")


def ratios(sizes, procs, methods, stats, runs):
    print()
    for s in sizes:
        sized = [r for r in runs if r["size"] == s]
        for p in procs:
            ours = stats.get((s, p, "ours"))
            if ours is None:
                continue
            head = f"size {s} ({ours['vertices']} vertices), P = {p}:"
            for m in methods[1:]:
                peer = stats.get((s, p, m))
                if peer is None:
                    continue
                each = by_repeat(paired(sized, ("ours", p), (m, p), "method_s"), ".3f")
                print(f"{head} ours / {LABELS[m]}: method time "
                      f"{ours['method_s'] / peer['method_s']:.3f}{each}, process time "
                      f"{ours['process_s'] / peer['process_s']:.3f}; energy error "
                      f"{ours['energy_error'] / peer['energy_error']:.4f}; peak "
                      f"{ours['peak_gib'] / peer['peak_gib']:.3f}")
            floor = certificate_floor(stats, s, p)
            if floor is not None:
                print(f"{head} " + floor)
        serial = stats.get((s, 1, "ours"))
        for p in procs:
            par = stats.get((s, p, "ours"))
            if p == 1 or serial is None or par is None:
                continue
            # (repeat by repeat too: on a shared machine one median hides the spread)
            each = by_repeat(paired(sized, ("ours", 1), ("ours", p), "method_s"), ".2f")
            print(f"size {s}: speed-up of ours on {p} processes: method time "
                  f"{serial['method_s'] / par['method_s']:.2f}{each}, process time "
                  f"{serial['process_s'] / par['process_s']:.2f}; largest peak per process "
                  f"{par['peak_gib'] / serial['peak_gib']:.3f} of the serial one")


def main(args):
    methods = [m for m in ("ours", "nested", "certified", "plain")
               if m != "plain" or not args.no_plain]
    guard = fresh.MemoryGuard(args.margin)
    print(f"BLAS threads: {fresh.blas_threads(args.blas_threads)}", flush=True)
    print(f"Software: {fresh.software()}", flush=True)
    if not args.no_warmup:
        # forms JIT-compiled into the disk cache before anything is measured, as for any run
        # after the first
        for m in methods:
            r = fresh.launch(m, "1", 1, args.timeout, args.blas_threads)
            if "failed" in r:
                print(f"warm-up {m}: failed: {r['failed']}", file=sys.stderr)
    runs = []
    for s in args.sizes:
        n = fresh.vertices(s)
        for rep in range(args.repeat):
            order = methods if rep % 2 == 0 else methods[::-1]
            for p in args.procs:
                for m in order:
                    skip = guard.room(n, p)
                    if skip:
                        r = {"method": m, "size": s, "processes": p, "skipped": skip}
                    else:
                        r = fresh.launch(m, s, p, args.timeout, args.blas_threads)
                        guard.measured(r)
                    r["repeat"] = rep
                    runs.append(r)
                    if "failed" in r or "skipped" in r:
                        print(f"size {s}, P = {p}, {LABELS[m]}: "
                              f"{r.get('failed') or r.get('skipped')}", flush=True)
                    else:
                        print(f"size {s} ({r['vertices']} vertices), P = {p}, {LABELS[m]}: "
                              f"method {r['method_s']:.2f} s, process {r['process_s']:.2f} s, "
                              f"peak {peak(r):.3f} GiB, error {r['energy_error']:.4e}",
                              flush=True)
    stats = {}
    for s in args.sizes:
        for p in args.procs:
            for m in methods:
                stats[s, p, m] = summarise([r for r in runs if (r["size"], r["processes"],
                                                                r["method"]) == (s, p, m)])
    print()
    table(args.sizes, args.procs, methods, stats)
    ratios(args.sizes, args.procs, methods, stats, runs)
    phases(args.sizes, args.procs, methods, stats)


def parse(argv=None):
    parser = argparse.ArgumentParser(
        description="Ours against the SNES VI peers on the disk, serial and on P processes "
                    "(issue 31); the module notes say what is measured.")
    parser.add_argument("--repeat", type=int, default=1, metavar="N",
                        help="runs of each (P, method) per size (default 1)")
    parser.add_argument("--no-plain", action="store_true", help="leave out the plain peer")
    args = fresh.parse_common(parser, argv, DEFAULT_SIZES, (1, 2))
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    return args


if __name__ == "__main__":
    main(parse())
