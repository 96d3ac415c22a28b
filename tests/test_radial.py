"""The radial family of exact solutions (scenes.radial; groundwork for §11's cases):
contact disk, near-total contact, grazing contact and no contact, for any μ1, μ2, g. Every
case converges with min and Fischer–Burmeister, complementarity holds at round-off (fb: at its
tolerance), and the guaranteed bound holds at the final iterate."""

import pytest

from membranes import scenes, solve


@pytest.mark.parametrize("kwargs", [{"rho": 0.5}, {"rho": 0.95}, {"rho": 0.0},
                                    {"contact": False}, {"rho": 0.5, "mu1": 1e-3}],
                         ids=["contact", "near-total", "grazing", "none", "stiff"])
@pytest.mark.parametrize("cfun", ["min", "fb"])
def test_radial_cases(kwargs, cfun):
    run = solve(scenes.radial(h=0.1, **kwargs), cfun=cfun, newton="exact", solver="direct")
    assert run.converged, run.reason
    s = run.summary()
    assert run.complementarity_violation() <= 1e-10
    assert s["bound_guaranteed"] and s["eta"] >= run.energy_error


def test_radial_bad_parameters():
    for kwargs in ({"rho": 1.0}, {"rho": -0.1}, {"mu1": 0.0}, {"g": float("nan")}):
        with pytest.raises(ValueError):
            scenes.radial(h=0.3, **kwargs)
