"""The ``paper_motion`` sampler profile (global camera motion, sensor-model randomisation), the camera-motion
stress regimes, the shake of the layer motion, and the ``plain_if`` simulator preset.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from polspike.pipeline.manifest import MANIFESTS_DIR, dump_manifest, load_manifest
from polspike.pipeline.sampler import sample_manifest
from polspike.pipeline.sampler_motion import CAMERA_RANGES, SENSOR_PRESETS

W, H = 64, 40


@pytest.fixture(scope="module")
def drawn() -> dict:
    return sample_manifest(300, 7, profile="paper_motion", width=W, height=H, test_fraction=0.0)


def _cam(desc: str) -> tuple[str, float] | None:
    m = re.search(r"camera (pan|shake|rotation|zoom) (-?[0-9.]+)", desc)
    return (m.group(1), float(m.group(2))) if m else None


def test_camera_motion_and_sensor_draws_stay_in_their_ranges(drawn):
    kinds = {"pan": 0, "shake": 0, "rotation": 0, "zoom": 0, None: 0}
    sensors = {}
    for g in drawn["groups"]:
        t, r = g["layers"]["transmission"]["motion"], g["layers"]["reflection"]["motion"]
        cam = _cam(g["description"])
        kinds[cam[0] if cam else None] += 1
        sensors[g["spike_sim"]["preset"]] = sensors.get(g["spike_sim"]["preset"], 0) + 1
        if cam is None:
            continue
        kind, v = cam
        if kind == "pan":
            lo, hi = CAMERA_RANGES["pan_view_per_s"]
            assert lo - 0.005 <= v <= hi + 0.005, g["name"]
        elif kind == "shake":
            lo, hi = CAMERA_RANGES["shake_rms_view_per_s"]
            assert lo <= t["shake_per_s"] == r["shake_per_s"] <= hi and t["shake_seed"] == r["shake_seed"]  # one camera
        elif kind == "rotation":
            # the layer's own rotation is within +-30 deg/s: the sum lies within the camera's range widened by it
            lo, hi = CAMERA_RANGES["rotate_deg_per_s"]
            d = t["rotate_deg_per_s"] - r["rotate_deg_per_s"]  # camera part cancels
            assert abs(d) <= 60.0 + 1e-6
            assert lo - 30.0 - 1e-6 <= abs(t["rotate_deg_per_s"]) <= hi + 30.0 + 1e-6
        elif kind == "zoom":
            lo, hi = CAMERA_RANGES["zoom_per_s"]
            assert lo <= abs(v) <= hi + 1e-6
        if kind != "shake":
            assert "shake_per_s" not in t and "shake_per_s" not in r
    # every kind and every sensor preset is drawn, near its probability (300 groups, 4 sigma)
    assert all(n > 0 for n in kinds.values()), kinds
    assert set(sensors) == {p for p, _ in SENSOR_PRESETS}
    for p, w in SENSOR_PRESETS:
        assert abs(sensors[p] - 300 * w) < 4 * math.sqrt(300 * w * (1 - w)), sensors
    # pans reach fast speeds: the log-uniform draw puts about 18 % above 1.5 view/s
    fast = [v for k, v in (c for c in map(_cam, (g["description"] for g in drawn["groups"])) if c) if k == "pan" and v > 1.5]
    assert len(fast) >= 5


def test_camera_motion_draws_stay_in_their_stated_ranges():
    """2000 draws of :func:`camera_motion`: pans 0.05-3 view widths/s (isotropic in pixels), shakes 0.5-1.5 view/s rms,
    rotations 30-90 deg/s either way, zooms 0.2-1 1/s either way; every kind near its probability.
    """
    from polspike.pipeline.sampler_motion import CAMERA_MOTIONS, camera_motion

    rng = np.random.default_rng(5)
    aspect = 1.6
    n = {k: 0 for k, _ in CAMERA_MOTIONS}
    pans = []
    for _ in range(2000):
        c = camera_motion(rng, aspect)
        n[c["kind"]] += 1
        vx, vy = c["translate_per_s"][0], c["translate_per_s"][1] / aspect
        v = math.hypot(vx, vy)
        if c["kind"] == "pan":
            assert 0.05 - 1e-3 <= v <= 3.0 + 1e-3
            pans.append(v)
        else:
            assert v == 0.0
        assert c["shake_per_s"] == 0.0 or (c["kind"] == "shake" and 0.5 <= c["shake_per_s"] <= 1.5 and c["shake_seed"] > 0)
        assert c["rotate_deg_per_s"] == 0.0 or (c["kind"] == "rotate" and 30.0 <= abs(c["rotate_deg_per_s"]) <= 90.0)
        assert c["zoom_per_s"] == 0.0 or (c["kind"] == "zoom" and 0.2 <= abs(c["zoom_per_s"]) <= 1.0)
    for k, w in CAMERA_MOTIONS:
        assert abs(n[k] - 2000 * w) < 4 * math.sqrt(2000 * w * (1 - w)), n
    # log-uniform: the median pan is the geometric mean of the bounds, sqrt(0.05 * 3) = 0.39 view/s
    assert np.median(pans) == pytest.approx(math.sqrt(0.05 * 3.0), rel=0.15)
    assert max(pans) > 2.5


def test_pan_is_added_to_both_layers_on_top_of_their_own_motion(drawn):
    """A camera pan's velocity is the one thing both layers share: T - R = the layers' own motion (each < 1 view/s)."""
    seen = 0
    for g in drawn["groups"]:
        cam = _cam(g["description"])
        if not cam or cam[0] != "pan":
            continue
        t, r = (np.array(g["layers"][k]["motion"]["translate_per_s"]) * [1.0, H / W] for k in ("transmission", "reflection"))
        # each layer = camera + own (|own| <= 1 view/s): |layer| >= camera - 1 view/s
        assert np.hypot(*t) >= cam[1] - 1.0 - 1e-3 and np.hypot(*r) >= cam[1] - 1.0 - 1e-3
        seen += 1
    assert seen > 50


def test_paper_motion_draws_are_deterministic_for_a_seed(drawn):
    again = sample_manifest(40, 7, profile="paper_motion", width=W, height=H, test_fraction=0.0)
    assert again["groups"] == drawn["groups"][:40]  # one stream per seed: the first 40 groups of the 300
    assert sample_manifest(40, 8, profile="paper_motion", width=W, height=H, test_fraction=0.0)["groups"] != drawn["groups"][:40]


def test_paper_profile_is_unchanged_by_the_motion_profile():
    """``paper`` (the shipped paper.toml) draws no camera motion beyond its 0.25 view/s pan and only default / noisy."""
    m = sample_manifest(60, 3, profile="paper", width=W, height=H)
    assert {g["spike_sim"]["preset"] for g in m["groups"]} <= {"default", "noisy"}
    assert not any("shake_per_s" in g["layers"]["transmission"]["motion"] for g in m["groups"])


def test_stress_camera_regimes_parse_and_carry_their_speeds():
    groups = {g.name: g for g in load_manifest(MANIFESTS_DIR / "stress.toml").groups}
    cams = {n.split("_cam-")[1]: g for n, g in groups.items() if "_cam-" in n}
    assert set(cams) == {"pan1p1", "pan3", "shake1", "naturalpan1p1", "brightrefl"}
    for tag, v in (("pan1p1", 1.1), ("pan3", 3.0), ("naturalpan1p1", 1.1)):
        for lay in cams[tag].scene["layers"].values():  # a camera pan: both layers, horizontal, at the stated speed
            assert lay["motion"]["translate_per_s"] == [v, 0.0], tag
    for lay in cams["shake1"].scene["layers"].values():
        assert lay["motion"]["shake_per_s"] == 1.0 and lay["motion"]["translate_per_s"] == [0.0, 0.0]
    sh = [lay["motion"]["shake_seed"] for lay in cams["shake1"].scene["layers"].values()]
    assert sh[0] == sh[1] > 0
    nat = cams["naturalpan1p1"].scene["layers"]
    assert all(lay["source"].startswith("skimage:") for lay in nat.values())
    # R/T of mean radiances: weak natural reflection 0.2, near-normal bright reflection 8
    def ratio(sc):
        t, r = sc["layers"]["transmission"], sc["layers"]["reflection"]
        return (r["brightness"] * 0.25 + r.get("offset", 0.0)) / (t["brightness"] * 0.25)
    assert ratio(cams["naturalpan1p1"].scene) == pytest.approx(0.2, rel=0.02)
    assert ratio(cams["brightrefl"].scene) == pytest.approx(8.0, rel=0.1)
    assert cams["brightrefl"].scene["pane"]["tilt_deg"] <= 10.0


def test_shake_offset_is_a_random_walk_of_the_stated_rms_speed():
    from generator.layers import SHAKE_KNOT_S, shake_offset

    t = np.arange(0, 4001) * SHAKE_KNOT_S  # 8 s, 160 correlation times
    dx, dy = shake_offset(1.0, 11, t, aspect=1.6)
    v = np.stack([np.diff(dx), np.diff(dy) / 1.6], 1) / SHAKE_KNOT_S  # view widths / s, both axes
    rms = float(np.sqrt((v**2).sum(1).mean()))
    assert 0.85 < rms < 1.15  # 1 view width/s rms
    assert 0.7 < np.sqrt((v[:, 1] ** 2).mean() / (v[:, 0] ** 2).mean()) < 1.4  # isotropic in pixels
    # a random walk, not a drift: the offset after 8 s is of order rms sqrt(2 tau t) = 0.9 view, far below 8
    assert math.hypot(dx[-1], dy[-1] / 1.6) < 3.0
    assert (float(dx[1234]), float(dy[1234])) == shake_offset(1.0, 11, float(t[1234]), 1.6)  # one walk, any t
    assert shake_offset(1.0, 11, 0.0, 1.0) == (0.0, 0.0)
    assert shake_offset(1.0, 11, 1.234, 1.6) == shake_offset(1.0, 11, 1.234, 1.6)  # deterministic
    assert shake_offset(1.0, 12, 1.234, 1.6) != shake_offset(1.0, 11, 1.234, 1.6)


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_plain_if_preset_scales_each_increment(engine):
    """plain_if: no noise but the multiplicative increment noise, so the spike count over n steps at constant g has
    variance n g^2 sigma^2 (the sum of n increments g (1 + sigma z)), plus at most 1/4 of quantisation.
    """
    import dataclasses

    from spike_sim.config import PLAIN_IF, preset
    from spike_sim.integrate_fire import simulate_constant

    assert preset("plain_if") is PLAIN_IF and not PLAIN_IF.shot_noise
    g, n, sigma = 0.5, 2000, PLAIN_IF.increment_sigma
    cfg = dataclasses.replace(PLAIN_IF, width=50, height=40)
    counts = simulate_constant(np.full((40, 50), g, np.float32), n, cfg, seed=3, engine=engine).sum(0).astype(np.float64)
    want = n * g * g * sigma * sigma  # 20 spikes^2
    assert abs(counts.mean() - n * g) < 1.0
    assert 0.85 * want < counts.var() < 1.15 * want + 0.25


def test_sampled_camera_pan_moves_the_ground_truth_by_speed_dt_width(tmp_path):
    """A tiny ``paper_motion`` group whose T layer holds still on its own under a sampled camera pan (and whose sensor is the plain_if preset): rendered
    (analytic tier) and simulated, its T ground truth between two output frames shifts by v dt W pixels
    (horizontal) and v_y dt H (vertical), v in view fractions per second.
    """
    from skimage.registration import phase_cross_correlation

    from polspike.pipeline.dataset import build_dataset
    from spike_sim.store import open_group

    m = sample_manifest(6, 16, profile="paper_motion", width=W, height=H, duration_s=0.1, test_fraction=0.0)
    g = next(g for g in m["groups"] if g["name"] == "train_003")
    mo = g["layers"]["transmission"]["motion"]
    assert "camera pan" in g["description"] and mo["rotate_deg_per_s"] == 0.0 and mo["zoom_per_s"] == 0.0
    assert not g["layers"]["transmission"].get("sprites")
    assert g["pane"]["model"] == "thin_slab" and g["spike_sim"]["preset"] == "plain_if"  # a parallel plate shifts rays without turning them: T maps linearly
    vx, vy = mo["translate_per_s"]
    assert abs(vx) > 0.8  # a fast pan: over 5 px in 0.1 s at 64 px
    path = tmp_path / "m.toml"
    path.write_text(dump_manifest(m))
    build_dataset(path, tmp_path / "ds", groups=["train_003"])
    with open_group(tmp_path / "ds" / "groups" / "train_003") as sg:
        times = sg.array("output/times_s")
        a, b = 0, len(times) - 1
        T0, T1 = sg.gt_frame("T", a), sg.gt_frame("T", b)
        assert sg.array("spikes").shape[0] > 0
    dt = float(times[b] - times[a])
    crop = (slice(6, H - 6), slice(8, W - 8))  # away from the mirrored border
    shift, _, _ = phase_cross_correlation(T1[crop], T0[crop], upsample_factor=20)  # (rows, cols): T1 = T0 moved by shift
    assert shift[1] == pytest.approx(vx * dt * W, abs=0.3)
    assert shift[0] == pytest.approx(vy * dt * H, abs=0.3)
