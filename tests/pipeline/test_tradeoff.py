"""bench tradeoff on a tiny scene: table, plot, and the expected ordering of errors."""

from __future__ import annotations

import json
import math

import pytest
from _mitsuba_common import require_mitsuba


@pytest.fixture(autouse=True)
def _mitsuba_works():
    """The one skip policy (_mitsuba_common.require_mitsuba): skip only when mitsuba is not installed; under CI
    an installed Mitsuba whose import or backend fails is a failure, not a skip.
    """
    require_mitsuba()


@pytest.mark.mitsuba
def test_tradeoff_tiny(tiny_scene, tmp_path):
    from polspike.pipeline.tradeoff import Candidate, default_candidates, run_tradeoff

    ref = Candidate("ref full 32spp", "full", 32, variant="llvm")
    run_tradeoff([tiny_scene], tmp_path, default_candidates(quick=True), ref=ref, keyframe_rates_hz=(25.0, 200.0), spike_steps=140)
    assert (tmp_path / "pareto.png").is_file() and (tmp_path / "tradeoff.md").is_file()
    rows = {r["candidate"]: r for r in json.loads((tmp_path / "tradeoff.json").read_text())["rows"]}
    a, f = rows["analytic"], rows["full 4spp llvm"]
    for r in (a, f):
        assert math.isfinite(r["radiance_err_p99"]) and math.isfinite(r["spike_frame_rmse"]) and r["per_frame_s"] > 0
    # a 4-spp path-traced frame carries its own noise on top of the reference's
    assert f["radiance_err_p99"] > a["radiance_err_p99"]
    # interpolating between keyframes: the faster the keyframes, the smaller the error
    k25, k200 = rows["keyframes 25 Hz (full tier cost model)"], rows["keyframes 200 Hz (full tier cost model)"]
    assert k200["radiance_err_p99"] < k25["radiance_err_p99"]
    assert k200["per_1s_group_s"] > k25["per_1s_group_s"]
    # simulator step: point-sampling the polarizer inside a 50 us step vs the closed-form integral.
    # Oracle: the step mean of cos 2phi over a step of half-width h is cos(2 phi_m) sin(2h)/(2h), so one mid-step
    # sample errs by at most 1/2 |S_lin| (1 - sinc(2h)) ~ 1/2 |S_lin| (2h)^2 / 6; k sub-samples by ~ k^-2 of that.
    s1, s4 = rows["simulator: 1 point sample(s) per step vs closed form"], rows["simulator: 4 point sample(s) per step vs closed form"]
    pol = tiny_scene.polarizer
    h = math.pi * pol.rate_hz / 20000.0  # half the rotation during one step, radians
    assert 0 < s1["radiance_err_p99"] <= 0.5 * 1.0 * (2 * h) ** 2 / 6 * 1.05
    assert s4["radiance_err_p99"] < s1["radiance_err_p99"] / 8
    assert s1["spike_frame_rmse"] < 1e-3 * s1["spike_noise_rmse"]  # far below the spike noise: the closed form costs nothing in accuracy terms
