"""The benchmark scripts' command lines: a bad argument is one error line and exit 2, before
anything is built or run (probe I: the child `fresh.py`, bench_convergence.py and
bench_commit.py answered with tracebacks, or ran on a negative level count)."""

import os
import subprocess
import sys

import pytest
from mpi4py import MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BENCH = os.path.join(ROOT, "benchmarks")

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one process")

CASES = {
    "fresh without size": (["fresh.py", "ours"], "expected a method and a size"),
    "fresh unknown method": (["fresh.py", "bogus", "1"], "unknown method 'bogus'"),
    "fresh bad size": (["fresh.py", "ours", "x"], "size 'x' is not J or J:H0"),
    "scaling negative timeout": (["bench_scaling.py", "--sizes", "1", "--timeout", "-1"],
                                 "--timeout must be a positive number"),
    "convergence negative levels": (["bench_convergence.py", "--levels", "-1"],
                                    "must be non-negative integers"),
    "convergence zero h0": (["bench_convergence.py", "--h0", "0"],
                            "--h0 must be a positive number"),
    "convergence beyond memory": (["bench_convergence.py", "--eff-levels", "14"],
                                  "2.6e10 vertices"),
    "commit unknown": (["bench_commit.py", "--commit", "zzzz"],
                       "'zzzz' is not a commit of this repository"),
    "commit no repeat": (["bench_commit.py", "--repeat", "0"], "--repeat must be at least 1"),
    "flux without levels": (["bench_flux.py", "--sizes", "0"], "needs J >= 1 in every size"),
    "flux unknown scene": (["bench_flux.py", "--scenes", "cube"], "invalid choice: 'cube'"),
    "quadrature gap zero h": (["quadrature_gap.py", "--h", "0"], "--h must be positive"),
    "quadrature gap negative level": (["quadrature_gap.py", "--levels", "-1"],
                                      "the levels and --depth non-negative"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_benchmark_arguments(case):
    args, expected = CASES[case]
    env = dict(os.environ, PYTHONPATH=ROOT)
    proc = subprocess.run([sys.executable, os.path.join(BENCH, args[0])] + args[1:],
                          capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert ": error: " in last and expected in last, proc.stderr
    assert proc.stdout == ""


def test_quadrature_gap_integrates_the_disk_data():
    """The independent quadrature of benchmarks/quadrature_gap.py against an exact value: over
    the cells of T_1 (h0 = 0.2), ∫ f1 = -10 g |{r² ≤ 1/2}| - 8 g (|Ω_h| - |{r² ≤ 1/2}|), the
    inner disk (area π/2) lying inside the polygon Ω_h. What the chords miss of the circle,
    length L = √2 π, cut into pieces of size s = h/2^8 (h ≈ 0.1 here), is about L s²/(12 R)
    ≈ 8e-8 of area, times the jump 2 g: rtol 1e-7 of the total (about 1.2) leaves room."""
    import importlib.util
    import math

    from membranes import scenes
    from membranes.fem.meshes import cell_vertices, triangle_areas
    spec = importlib.util.spec_from_file_location("quadrature_gap",
                                                  os.path.join(BENCH, "quadrature_gap.py"))
    gap = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gap)
    tris = cell_vertices(scenes.disk(h=0.2, levels=1).hierarchy.finest)
    area = triangle_areas(tris).sum()
    total = gap.accurate_integrals(tris, 1, 8, gap.gauss()).sum()
    inner = math.pi / 2
    exact = -10 * gap.G * inner - 8 * gap.G * (area - inner)
    assert abs(total - exact) <= 1e-7 * abs(exact)
