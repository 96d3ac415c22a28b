"""Set-ups kept between solves (membranes.app.setups): a run that takes a kept flux
equilibration is the run without it.

The kept equilibration is the object a fresh set-up builds, and its solves are the same
operations in the same order, so the iterates, counts and η agree to round-off (asserted at
1e-12 relative; in practice they are equal). Where the second problem integrates its data
with other measures (a data jump across an interface: the composite rule of §7), the kept
equilibration must take them, or the interior patches lose their compatibility (§5): without
`use_data_measures` η moves by about 1e-5 relative on the radial scene below, far above the
tolerance. Run as a script under mpirun, `compare()` checks the same on P processes.
"""

import json
import os
from dataclasses import replace

import numpy as np
import pytest
from mpi4py import MPI

from membranes import Setups, scenes, solve
from membranes.fem.hierarchy import build_hierarchy

ROUND_OFF = 1e-12


def rel(a, b):
    return abs(a - b) / abs(b)


def compare(comm=MPI.COMM_WORLD):
    """Solve the disk for two μ2 with a kept set-up and without; the radial scene without and
    then with its interface. Returns the largest relative η differences, the counts' equality
    and the store's size and hits."""
    disk = scenes.disk(h=0.3, levels=2, comm=comm)
    kept = Setups()
    eta, same_counts = 0.0, True
    for mu2 in (1.0, 4.0):
        problem = replace(disk, mu2=mu2, exact=None)
        a, b = solve(problem, setups=kept), solve(problem)
        eta = max(eta, rel(a.estimates["eta"], b.estimates["eta"]),
                  rel(a.estimates["eta_disc"], b.estimates["eta_disc"]))
        same_counts &= (a.newton_iterations, a.linear_iterations) == \
            (b.newton_iterations, b.linear_iterations)
    radial = scenes.radial(h=0.3, levels=1, comm=comm)
    assert radial.interface is not None
    solve(replace(radial, interface=None), setups=kept)
    a, b = solve(radial, setups=kept), solve(radial)
    measures = rel(a.estimates["eta"], b.estimates["eta"])
    out = dict(eta=eta, same_counts=same_counts, measures=measures, kept=len(kept),
               hits=kept.hits)
    kept.clear()
    out["cleared"] = len(kept)
    return out


def check(out):
    assert out["eta"] <= ROUND_OFF
    assert out["same_counts"]
    assert out["measures"] <= ROUND_OFF
    assert out["kept"] == 2 and out["hits"] == 2          # one set-up per mesh, taken again
    assert out["cleared"] == 0


def test_kept_setup_gives_the_run_without_it():
    check(compare())


def test_progress_says_the_setup_was_kept():
    """The second solve's progress line says that it took the kept equilibration."""
    disk, kept, lines = scenes.disk(h=0.3, levels=1), Setups(), []
    for mu2 in (1.0, 2.0):
        lines.append([])
        solve(replace(disk, mu2=mu2, exact=None), setups=kept, progress=lines[-1].append)
    said = [[line for line in run if "estimators set up in" in line] for run in lines]
    assert len(said[0]) == len(said[1]) == 1
    assert not said[0][0].endswith("(flux equilibration kept from an earlier solve)")
    assert said[1][0].endswith(" s (flux equilibration kept from an earlier solve)")
    kept.clear()


def test_other_data_drop_the_scene_description_and_exact_solution():
    """A problem of the README's parameter study, replace(problem, mu2=5, exact=None), is
    described by its own data in summary.json, not the scene's (mu1 = mu2 = 1, exact
    solution); keeping the scene's exact solution with other data is refused (its energy
    error would be that of the wrong solution: effectivity 0.07 on this disk); a copy on
    another hierarchy, or with the same values, is the scene itself."""
    disk = scenes.disk(h=0.5, levels=1)
    other = replace(disk, mu2=5, exact=None)
    assert other.description == "unit disk, mu1 = 1, mu2 = 5, g = 0.05, f1 of scene disk, " \
        "f2 of scene disk"
    with pytest.raises(ValueError, match="exact solution of scene 'disk' does not solve"):
        replace(disk, mu2=5)
    for same in (replace(disk, mu2=1), replace(disk, hierarchy=disk.hierarchy.up_to(0))):
        assert same.description == disk.description and same.exact is disk.exact
    user = scenes.user(f1="-1", domain="square", h=0.5)
    assert replace(user, f1="-2").description == \
        "unit square, mu1 = 1, mu2 = 1, g = 0.05, f1 = -2, f2 = 0"
    sol = solve(other, newton="exact", estimators=False)
    assert sol.summary()["description"] == other.description


def test_a_mesh_moved_in_place_is_set_up_anew():
    """mesh.geometry.x is writable: a mesh whose vertices were moved after its set-up (here
    the square stretched to 2 × 1) is another mesh for the patch blocks of §5, though the
    same object. The kept equilibration gave there another σ_disc than a fresh set-up (η
    2.7 % higher on this square); the moved mesh must be set up anew, and the run is then
    the run without kept set-ups, to round-off."""
    square = scenes.user(f1="-3", domain="square", h=0.25, levels=1)
    kept = Setups()
    solve(square, setups=kept)
    for mesh in square.hierarchy.meshes:
        mesh.geometry.x[:, 0] *= 2.0
    a, b = solve(square, setups=kept), solve(square)
    assert rel(a.estimates["eta"], b.estimates["eta"]) <= ROUND_OFF
    assert kept.hits == 0 and len(kept) == 1
    assert (a.newton_iterations, a.linear_iterations) == \
        (b.newton_iterations, b.linear_iterations)
    assert rel(solve(square, setups=kept).estimates["eta"], b.estimates["eta"]) <= ROUND_OFF
    assert kept.hits == 1                          # taken again while the mesh stays put
    kept.clear()


def test_a_solve_inside_a_solve_with_the_same_store_is_refused():
    """A solve called from another's progress callback with the same store rebound the kept
    equilibration to its own data measures (here the radial scene without its interface),
    and the outer solve's σ_disc then failed its divergence check (RuntimeError, defect
    1e-5). The inner solve is refused, the outer one stops with its error, and the store
    serves the next solve as before."""
    radial, kept = scenes.radial(h=0.3, levels=1), Setups()

    def progress(line):
        if "estimators set up" in line:
            solve(replace(radial, interface=None), setups=kept)

    with pytest.raises(ValueError, match="setups is in use by a solve that has not ended"):
        solve(radial, setups=kept, progress=progress)
    a, b = solve(radial, setups=kept), solve(radial)
    assert kept.hits == 1 and rel(a.estimates["eta"], b.estimates["eta"]) <= ROUND_OFF
    kept.clear()


def test_setups_must_be_a_store():
    with pytest.raises(ValueError, match="setups must be a membranes.Setups"):
        solve(scenes.disk(h=0.5), setups={})


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
@pytest.mark.parametrize("processes", [2, 3])
def test_kept_setup_on_several_processes(processes):
    from .conftest import mpirun  # (not at the top: this file runs as a script too)
    proc = mpirun([os.path.abspath(__file__)], processes=processes, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    check(json.loads(proc.stdout.strip().splitlines()[-1]))


def moved_on_one_process(comm=MPI.COMM_WORLD):
    """The square solved with a kept set-up, then some of its interior vertices that the last
    process alone holds moved by 3 % towards the centre (a deformation of its own part only:
    the other processes' vertices stay where they were) and solved again, with the kept
    store and without. Returns the number of moved vertices, the relative η difference, the
    counts' equality and every process's hits, gathered."""
    square = scenes.user(f1="-3", domain="square", h=0.125, comm=comm)
    kept = Setups()
    solve(square, setups=kept)
    x = square.mesh.geometry.x
    others = comm.gather({tuple(p) for p in x[:, :2]} if comm.rank < comm.size - 1 else set())
    others = comm.bcast(set().union(*others) if comm.rank == 0 else None)
    moved = 0
    if comm.rank == comm.size - 1:
        for k, p in enumerate(x[:, :2]):
            if min(p.min(), 1 - p.max()) > 1e-12 and tuple(p) not in others:
                x[k, :2] = 0.5 + 0.97 * (p - 0.5)
                moved += 1
    a, b = solve(square, setups=kept), solve(square)
    out = dict(moved=comm.allreduce(moved), eta=rel(a.estimates["eta"], b.estimates["eta"]),
               same_counts=(a.newton_iterations, a.linear_iterations) ==
               (b.newton_iterations, b.linear_iterations), hits=comm.gather(kept.hits))
    kept.clear()
    return out


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="launches mpirun itself")
def test_a_mesh_moved_on_one_process_is_set_up_anew_on_all():
    """Whether the kept set-up is taken is decided by all processes together: where the
    vertices moved on one process only, every process sets up anew (a process that took its
    kept blocks would combine them with the other's new ones: another η than a fresh
    set-up's), and the run is the run without kept set-ups, to round-off."""
    from .conftest import mpirun  # (not at the top: this file runs as a script too)
    proc = mpirun([os.path.abspath(__file__), "moved"], processes=2, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["moved"] > 0 and out["hits"] == [0, 0]
    assert out["eta"] <= ROUND_OFF and out["same_counts"]


if __name__ == "__main__":
    import sys
    result = moved_on_one_process() if sys.argv[1:] == ["moved"] else compare()
    if MPI.COMM_WORLD.rank == 0:
        print(json.dumps(result))


def test_a_hierarchy_of_another_domain_drops_the_scene_exact_solution_and_c_pf():
    """The disk's exact solution and C_PF h_Ω = 1/j_{0,1} hold on the unit disk only (§7, §9).
    On another domain the first gave the energy error of the wrong solution and the second
    could be too small for a bound (a larger domain): a copy on such a hierarchy must give
    both anew, and without them the bounding box's constant is used. Another hierarchy of the
    same scene domain (or a truncation of the same one) keeps both."""
    disk = scenes.disk(h=0.5, levels=1)
    square = scenes.user(h=0.5, domain="square")
    for kw, names in (({}, "exact=None, poincare=None"), ({"exact": None}, "poincare=None")):
        with pytest.raises(ValueError, match=f"own domain only.*give {names}"):
            replace(disk, hierarchy=square.hierarchy, **kw)
    other = replace(disk, hierarchy=square.hierarchy, exact=None, poincare=None)
    assert other.poincare_constant() == pytest.approx(1.0 / (np.pi * np.sqrt(2.0)), rel=1e-12)
    assert other.description.startswith("unit square, ") and other.domain == "square"
    assert replace(other, poincare=0.3).poincare == 0.3
    # values given anew for the new domain in the same copy are taken (the message's "or
    # values for the new domain"); only the scene's own objects are refused
    from membranes.model.problem import ExactSolution
    mine = ExactSolution(lambda x: 0.05 + 0 * x[0], lambda x: 0 * x[0], lambda x: 0 * x[0])
    given = replace(disk, hierarchy=square.hierarchy, exact=mine, poincare=0.3)
    assert given.exact is mine and given.poincare_constant() == 0.3
    assert given.description.endswith(", exact solution given")
    # a hierarchy built outside the scenes names no domain: taken for another one
    mine = build_hierarchy(disk.mesh, 0)
    with pytest.raises(ValueError, match="own domain only"):
        replace(disk, hierarchy=mine)
    for same in (scenes.disk(h=0.4).hierarchy, disk.hierarchy.up_to(0)):
        kept = replace(disk, hierarchy=same)
        assert kept.exact is disk.exact and kept.poincare == disk.poincare
        assert kept.description == disk.description
