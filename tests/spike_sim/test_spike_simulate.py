"""simulate(): streaming, determinism for a seed, .dat round trip, ground truth, render-dir source."""

from __future__ import annotations

import dataclasses
import json

import numba
import numpy as np
import pytest

from polphysics.polarizer import PolarizerConfig
from spike_sim.config import IDEAL
from spike_sim.simulate import keyframes_from_arrays, keyframes_from_render, simulate
from spike_sim.store import open_group
from spike_sim.vidar_dat import read_dat


def _collect(src, cfg, seed, chunk, duration=0.02):
    chunks = []
    simulate(src, duration, seed, cfg, out=None, chunk_steps=chunk, spikes_sink=lambda n0, o: chunks.append((n0, o)))
    return np.concatenate([o for _, o in sorted(chunks, key=lambda c: c[0])])


def test_deterministic_for_a_seed_regardless_of_chunking_and_threads(keyframes, small_cfg):
    ref = _collect(keyframes, small_cfg, 11, 400)
    assert ref.shape == (400, 48)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        assert np.array_equal(_collect(keyframes, small_cfg, 11, 37), ref)
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(_collect(keyframes, small_cfg, 11, 1), ref)
    assert not np.array_equal(_collect(keyframes, small_cfg, 12, 400), ref)


def test_noise_free_counts_follow_the_closed_form_intensity(keyframes):
    """IDEAL sensor: spike count over the stream = floor(sum of step-mean intensities) +- float rounding."""
    from polphysics.polarizer import step_keyframe_weights

    cfg = dataclasses.replace(IDEAL, width=24, height=16)
    s = _collect(keyframes, cfg, 0, 128)
    counts = np.unpackbits(s, axis=1, bitorder="little").sum(0).reshape(16, 24)
    k_lo, W = step_keyframe_weights(0, 400, cfg.dt_s, keyframes.times_s, keyframes.polarizer, 0)
    K = keyframes.times_s.size
    S = np.stack([keyframes.stokes(k) for k in range(K)]).astype(np.float64)
    total = np.zeros((16, 24))
    for n in range(400):
        for j in range(3):
            k = min(k_lo[n] + j, K - 1)
            total += np.tensordot(W[n, j], S[k], axes=(0, 0)) if k_lo[n] + j < K else 0.0
    assert np.all(np.abs(counts - np.floor(total)) <= 1)
    assert np.mean(counts == np.floor(total)) > 0.95


def test_group_and_dat_round_trip_bit_exactly(tmp_path, keyframes, small_cfg):
    summ = simulate(keyframes, 0.03, 4, small_cfg, out=tmp_path / "g", dat_path=tmp_path / "g.dat", chunk_steps=250)
    g = open_group(tmp_path / "g")
    s = g.read()
    assert s.shape == (600, 16, 24)
    assert np.array_equal(read_dat(tmp_path / "g.dat", 16, 24), s)
    assert summ.mean_rate == pytest.approx(s.mean(), rel=1e-9)
    assert g.seed == 4 and g.scene_hash == "in-memory"
    assert g.json_attr("config_json")["photons_per_threshold"] == small_cfg.photons_per_threshold
    # metadata: phi per step, output frames at 342.9 fps with GT and maps
    phi = g.phi_true_rad
    assert phi.shape == (600,) and np.all(np.diff(phi) > 0)
    c = g.array("output/step_index")
    assert c.size == 10  # 30 ms at 342.9 fps, windows fitting inside
    assert g.f["gt/T"].shape == (10, 16, 24)
    t = g.array("output/times_s")[3]
    k = np.searchsorted(keyframes.times_s, t) - 1
    w = (t - keyframes.times_s[k]) / (keyframes.times_s[k + 1] - keyframes.times_s[k])
    T_ref = (1 - w) * keyframes.layers(k)[0] + w * keyframes.layers(k + 1)[0]
    np.testing.assert_allclose(g.gt_frame("T", 3), T_ref, atol=1e-3)  # float16 storage
    assert set(g.maps()) >= {"phi_perp", "R_perp", "R_par"}
    meta = json.loads((tmp_path / "g" / "group.json").read_text())
    assert meta["complete"] and meta["seed"] == 4
    g.close()


def test_render_dir_source(tmp_path, keyframes):
    """A polspike-render/1 folder is read lazily and gives the same stream as the same arrays."""
    from polinfra.exr import write_exr

    rd = tmp_path / "render"
    (rd / "frames").mkdir(parents=True)
    K = keyframes.times_s.size
    names = []
    for k in range(K):
        st = keyframes.stokes(k)
        T_, R_ = keyframes.layers(k)
        name = f"frames/{k:06d}.exr"
        write_exr(rd / name, {"S0": st[0], "S1": st[1], "S2": st[2], "T": T_, "R": R_})
        names.append(name)
    write_exr(rd / "maps.exr", {k: v for k, v in keyframes.maps().items()} | {"T_perp": keyframes.maps()["T_perp"]})
    pol = {"rate_hz": 30.0, "phase_deg": 5.0, "jitter_deg": 0.1}
    meta = {"format": "polspike-render/1", "complete": True, "scene_hash": "abc", "tier": "analytic", "width": 24, "height": 16, "fps": 200.0,
            "frame_times_s": keyframes.times_s.tolist(), "frames": names, "scene": {"polarizer": pol}, "modelled": {}, "timings": {}, "conventions": ""}
    (rd / "render.json").write_text(json.dumps(meta))
    src = keyframes_from_render(rd)
    assert src.scene_hash == "abc" and src.polarizer == PolarizerConfig(**pol)
    cfg = dataclasses.replace(IDEAL, width=24, height=16, random_init=True)
    a = _collect(src, cfg, 3, 100)
    b = _collect(keyframes, cfg, 3, 100)
    assert np.array_equal(a, b)
    summ = simulate(rd, 0.01, 3, cfg, out=tmp_path / "g")
    assert open_group(tmp_path / "g").scene_hash == "abc" and summ.n_steps == 200


def test_static_scene_single_keyframe(small_cfg):
    st = np.zeros((1, 3, 16, 24), np.float32)
    st[0, 0] = 0.5
    src = keyframes_from_arrays([0.0], st, polarizer=PolarizerConfig())
    s = _collect(src, small_cfg, 1, 1000, duration=0.05)
    assert np.unpackbits(s).mean() == pytest.approx(0.25, rel=0.1)  # unpolarized 0.5 -> 0.25 behind the polarizer


def test_much_noisier_than_real_cameras_warns(keyframes, small_cfg):
    from polinfra.errors import PolspikeWarning

    with pytest.warns(PolspikeWarning, match="ISI CV"):
        simulate(keyframes, 0.001, 0, dataclasses.replace(small_cfg, photons_per_threshold=20.0), out=None)


def test_aggregate_group_matches_stored_output_frames(tmp_path, keyframes, small_cfg):
    """aggregate_group reproduces the stored Eq. (3) centres and phi(i); I(i) = window mean of the spikes."""
    from spike_sim.aggregate import aggregate_group

    simulate(keyframes, 0.03, 2, small_cfg, out=tmp_path / "g")
    with open_group(tmp_path / "g") as g:
        agg = aggregate_group(g)
        np.testing.assert_array_equal(agg["centre_step"], g.array("output/step_index"))
        np.testing.assert_allclose(agg["phi_rad"], g.array("output/phi_nominal_rad"), atol=1e-12)
        c = agg["centre_step"][4]
        np.testing.assert_allclose(agg["I"][4], g.read(c - 6, c + 7).mean(0), rtol=1e-6)
        true_i = g.array("output/phi_true_rad")
        # jitter 0.1 deg per step averages over 13 steps; no offset in this polarizer
        assert np.max(np.abs(np.rad2deg(true_i - agg["phi_rad"]))) < 0.2


def test_simulate_currents_time_varying_ideal():
    from spike_sim.integrate_fire import simulate_currents

    cfg = dataclasses.replace(IDEAL, width=8, height=4)
    g = np.concatenate([np.full((50, 4, 8), 0.5, np.float32), np.full((50, 4, 8), 0.25, np.float32)])
    s = simulate_currents(g, cfg, seed=0)
    assert s.shape == (100, 4, 8)
    assert np.all(s[:50].sum(0) == 25) and np.all(s[50:].sum(0) == 12)


def test_memory_is_bounded_by_the_chunk_not_the_duration(tmp_path, keyframe_factory):
    """4x longer stream, same chunk: the Python-side peak grows by far less than the 4x larger spike data."""
    import tracemalloc

    src = keyframe_factory(H=40, W=100, K=3, duration=0.2)
    cfg = dataclasses.replace(IDEAL, width=100, height=40)
    peaks = []
    for i, d in enumerate((0.05, 0.2)):
        tracemalloc.start()
        simulate(src, d, 0, cfg, out=tmp_path / f"g{i}", chunk_steps=200, compression="none")
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    spike_bytes_extra = (0.2 - 0.05) * 20000 * 500
    assert peaks[1] - peaks[0] < 0.25 * spike_bytes_extra
