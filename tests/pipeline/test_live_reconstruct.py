"""The real-time physics path: packed-bit window counts, equality with the general streaming path, --follow.

Oracles: window counts equal the sums of the unpacked spikes (spike_sim.vidar_dat.read_dat); the live path's
linear T and R (EXR frames) equal those of reconstruct_stream on the same .dat and model within a stated float
tolerance; --follow through the console script on a .dat a writer process appends to, stopped by SIGINT with
every output complete.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from reconstruct.stream.pane_stream import PaneStreamConfig, pane_stream_maps, write_pane_dat

H, W = 40, 72
CFG = PaneStreamConfig(height=H, width=W, exposure=2.0)
TOL_MAX, TOL_MEAN = 1e-3, 1e-5  # live vs stream, relative to the frame's peak: max and mean |diff| (the fused LS sums its
# 2 x 2 moments in float64, the torch path in float32: they part on ill-conditioned pixels near normal incidence)


@pytest.fixture(scope="module")
def dat(tmp_path_factory):
    return write_pane_dat(tmp_path_factory.mktemp("live") / "pane.dat", CFG, 0.08)


def test_packed_window_counts_equal_unpacked_sums(dat):
    from reconstruct.stream.packed import PackedDat
    from spike_sim.vidar_dat import read_dat

    rd = PackedDat(dat, H, W)
    assert rd.refresh() == 1600
    rng = np.random.default_rng(3)
    for a in rng.integers(0, 1600 - 255, 5):
        n = int(rng.integers(1, 256))
        got = rd.counts(int(a), int(a) + n)
        want = read_dat(dat, H, W, frames=slice(int(a), int(a) + n)).sum(0)
        assert got.dtype == np.uint8 and np.array_equal(got, want)
    with pytest.raises(Exception, match="255"):
        rd.counts(0, 256)
    rd.close()


def test_window_radiance_equals_the_counts_in_radiance_units_bit_for_bit(dat):
    """The one-pass kernel of the live path against ``counts(...).astype(float32) / scale`` (upright, header columns
    dropped); also on a stored width with header columns and a row length that is not a whole number of bytes.
    """
    from reconstruct.stream.packed import PackedArray, PackedDat, window_counts, window_radiance

    rd = PackedDat(dat, H, W)
    rd.refresh()
    scale = np.float32(13 * CFG.exposure)
    out = np.full((H, W), np.nan, np.float32)
    for a, n in ((0, 13), (777, 1), (1600 - 255, 255)):
        want = rd.counts(a, a + n).astype(np.float32) / scale
        assert np.array_equal(rd.radiance(a, a + n, scale, out).view(np.uint32), want.view(np.uint32))
    rd.close()
    rng = np.random.default_rng(5)
    pk = rng.integers(0, 256, (9, 6 * 36 // 8), dtype=np.uint8)  # 6 rows of 36 stored columns (4.5 bytes a row), 20 kept
    for flip in (False, True):
        want = window_counts(pk, 6, 36, 20, flip).astype(np.float32) / np.float32(3.7)
        got = window_radiance(pk, 6, 36, 20, flip, np.float32(3.7), np.empty((6, 20), np.float32))
        assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
    arr = PackedArray(pk[:, : 6 * 32 // 8], 6, 32)
    assert np.array_equal(arr.radiance(0, 9, np.float32(2.0), np.empty((6, 32), np.float32)), arr.counts(0, 9) / np.float32(2.0))


def _model(method, rir=False):
    from reconstruct.physics.zeta import PaneMaps
    from reconstruct.video.physics import PhysicsModel

    mp = pane_stream_maps(CFG)
    span = 2 * math.pi * CFG.rev_per_s * 13 / CFG.rate_hz
    return PhysicsModel(method, 7, maps=PaneMaps(R_perp=mp["R_perp"], R_par=mp["R_par"], phi_perp=mp["phi_perp"]), span_rad=span, rir=rir)


@pytest.mark.parametrize("method", ["ls", "rwps"])
def test_live_equals_stream_within_float_tolerance(dat, tmp_path, method):
    from reconstruct.stream.packed import PackedDat
    from reconstruct.stream.sources import dat_source
    from reconstruct.video.live import LiveConfig, reconstruct_live
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    model = _model(method)
    s_old = reconstruct_stream(dat_source(dat, H, W, CFG.phi0_rad, CFG.rev_per_s), model, tmp_path / "old", ReconstructConfig(frames="exr", exposure=CFG.exposure))
    s_new = reconstruct_live(PackedDat(dat, H, W), model, tmp_path / "new", LiveConfig(frames="exr", gain_frames=1000),
                             phi0_rad=CFG.phi0_rad, rev_per_s=CFG.rev_per_s, rate_hz=CFG.rate_hz, exposure=CFG.exposure)
    assert s_new["frames"] == s_old["frames"] >= 10
    _assert_frames_match(tmp_path / "old", tmp_path / "new", s_old["frames"])
    # the display gains come from the same histogram when the whole video fits the gain span
    for k in ("T", "R", "preview"):
        assert s_new["display_gain"][k] == pytest.approx(s_old["display_gain"][k], rel=1e-12)


def test_live_fused_rwps_with_rir_equals_the_torch_solver_on_a_moving_stream(tmp_path):
    """RWPS with RIR on a panning stream: the fused kernel (shifts applied while reading the ring of frames, numba
    Gauss-Newton) gives the frames of the torch path (warped windows in stream order, torch fit) within the tolerance.
    """
    import dataclasses

    from reconstruct.stream.packed import PackedDat
    from reconstruct.video.live import LiveConfig, reconstruct_live

    cfg = dataclasses.replace(CFG, motion_px_s=(0.0, 150.0))  # 0.44 px per output frame: shifts up to ~1.3 px in a window
    dat = write_pane_dat(tmp_path / "pan.dat", cfg, 0.06)
    model = _model("rwps", rir=True)
    out = {}
    for solver in ("torch", "fused"):
        out[solver] = reconstruct_live(PackedDat(dat, H, W), model, tmp_path / solver, LiveConfig(frames="exr", video=False, solver=solver),
                                       phi0_rad=cfg.phi0_rad, rev_per_s=cfg.rev_per_s, rate_hz=cfg.rate_hz, exposure=cfg.exposure)
    assert out["fused"]["frames"] == out["torch"]["frames"] >= 10
    _assert_frames_match(tmp_path / "torch", tmp_path / "fused", out["torch"]["frames"])


def _pan_dat(tmp_path):
    import dataclasses

    cfg = dataclasses.replace(CFG, motion_px_s=(0.0, 150.0))  # 0.44 px per output frame: RIR shifts every window
    return write_pane_dat(tmp_path / "pan.dat", cfg, 0.06), cfg


def _live(dat, cfg, out, stop=None, on_frame=None, **over):
    from reconstruct.stream.packed import PackedDat
    from reconstruct.video.live import LiveConfig, reconstruct_live

    return reconstruct_live(PackedDat(dat, H, W), _model("rwps", rir=True), out, LiveConfig(frames="exr", **over), phi0_rad=cfg.phi0_rad,
                            rev_per_s=cfg.rev_per_s, rate_hz=cfg.rate_hz, exposure=cfg.exposure, stop=stop, on_frame=on_frame)


def _exr_bits(out, i):
    from polinfra.exr import read_exr

    a = read_exr(out / "frames" / f"{i:06d}.exr", ["T", "R"])
    return {k: np.asarray(a[k], np.float32).view(np.uint32) for k in ("T", "R")}


def test_live_rwps_pipeline_writes_the_serial_frames_bit_for_bit(tmp_path):
    """RWPS + RIR on a panning stream: the solve on its own thread (the next frame made meanwhile) writes the same
    EXR frames, bit for bit, in the same order and number, as the path with every stage on one thread; the videos
    hold one frame per output frame.
    """
    import imageio.v3 as iio

    dat, cfg = _pan_dat(tmp_path)
    s = {p: _live(dat, cfg, tmp_path / str(p), pipeline=p, share_pixels=False) for p in (False, True)}
    s["share"] = _live(dat, cfg, tmp_path / "share")  # the stream's thread takes the pixel rows the solve thread has not
    assert s[True]["pipeline"] and not s[False]["pipeline"] and s[True]["pixel_chunks_on_stream_thread"] is None
    assert s["share"]["frames"] == s[False]["frames"] and s["share"]["pixel_chunks_on_stream_thread"] >= 0
    n = s[False]["frames"]
    assert s[True]["frames"] == n >= 10 and s[True]["nan_frames"] == s[False]["nan_frames"] == 0
    assert len(list((tmp_path / "True" / "frames").glob("*.exr"))) == n
    for i in range(n):
        a, b, c = _exr_bits(tmp_path / "False", i), _exr_bits(tmp_path / "True", i), _exr_bits(tmp_path / "share", i)
        for k in ("T", "R"):
            assert np.array_equal(a[k], b[k]) and np.array_equal(a[k], c[k]), (i, k)
    assert any(not np.array_equal(_exr_bits(tmp_path / "True", i)["T"], _exr_bits(tmp_path / "True", i + 1)["T"]) for i in range(n - 1))
    assert sum(1 for _ in iio.imiter(tmp_path / "True" / "T.mp4")) == n


def test_live_rwps_pipeline_stops_between_frames_with_complete_outputs(tmp_path):
    """``stop`` set from the frame callback (which runs on the solve thread): the run ends with every file complete,
    the frames it wrote equal to the serial run's first ones, bit for bit.
    """
    import threading

    import imageio.v3 as iio

    dat, cfg = _pan_dat(tmp_path)
    ref = _live(dat, cfg, tmp_path / "ref", video=False, pipeline=False)
    stop = threading.Event()
    s = _live(dat, cfg, tmp_path / "p", stop=stop, on_frame=lambda done, la: done >= 4 and stop.set())
    assert s["stopped"] == "interrupt" and 4 <= s["frames"] < ref["frames"]
    assert len(list((tmp_path / "p" / "frames").glob("*.exr"))) == s["frames"]
    for i in range(s["frames"]):
        a, b = _exr_bits(tmp_path / "ref", i), _exr_bits(tmp_path / "p", i)
        assert np.array_equal(a["T"], b["T"]) and np.array_equal(a["R"], b["R"]), i
    for name in ("T", "R"):
        assert sum(1 for _ in iio.imiter(tmp_path / "p" / f"{name}.mp4")) == s["frames"]
    assert not list((tmp_path / "p").glob("*.tmp*")) and not list((tmp_path / "p").glob(".*"))


@pytest.mark.parametrize("share", [False, True])
def test_live_rwps_pipeline_raises_the_solve_threads_error(tmp_path, monkeypatch, share):
    """An error in the solve thread reaches the caller (the stream's thread) as itself; no video is left behind."""
    import reconstruct.physics.fused_rwps as fr

    dat, cfg = _pan_dat(tmp_path)
    owner, name = (fr.RwpsWindow, "finish") if share else (fr, "rwps_fused")
    real, calls = getattr(owner, name), []

    def failing(*a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise FloatingPointError("solve failed on purpose")
        return real(*a, **k)

    monkeypatch.setattr(owner, name, failing)
    with pytest.raises(FloatingPointError, match="on purpose"):
        _live(dat, cfg, tmp_path / "p", share_pixels=share)
    assert len(calls) == 3  # nothing solved after the failure
    assert sorted(p.name for p in (tmp_path / "p" / "frames").glob("*.exr")) == ["000000.exr", "000001.exr"]
    assert not list((tmp_path / "p").glob("*.mp4"))


def test_live_path_writes_the_preview_only_with_the_flag(dat, tmp_path, polspike_main):
    """Through the console-script entry point on pane maps (``--pane``): T.mp4 and R.mp4 by default, preview.mp4 (input | T | R, three
    panels of W columns) with ``--preview``, every video one frame per output frame.
    """
    import imageio.v3 as iio

    from polinfra.exr import write_exr

    mp = pane_stream_maps(CFG)
    write_exr(tmp_path / "maps.exr", {k: np.asarray(mp[k], np.float32) for k in ("R_perp", "R_par", "phi_perp")}, {})
    args = ("reconstruct", dat, "--height", H, "--width", W, "--phi0-deg", math.degrees(CFG.phi0_rad), "--rev-per-s", CFG.rev_per_s,
            "--exposure", CFG.exposure, "--method", "ls", "--no-rir", "--pane", tmp_path / "maps.exr", "--quiet")
    for flag, want in (((), ["R.mp4", "T.mp4"]), (("--preview",), ["R.mp4", "T.mp4", "preview.mp4"])):
        out = tmp_path / f"o{len(flag)}"
        r = polspike_main(*args, *flag, "--out", out)
        assert r.returncode == 0, r.stderr[-2000:]
        s = json.loads((out / "reconstruct.json").read_text())
        assert s["path"] == "live" and s["outputs"] == want and s["frames"] >= 10
        for name in want:
            v = iio.imread(out / name, index=None)
            assert v.shape[:3] == (s["frames"], H, (3 if name == "preview.mp4" else 1) * W), (name, v.shape)


def _decode(path, h, w):
    import imageio_ffmpeg

    g = imageio_ffmpeg.read_frames(str(path), pix_fmt="gray", bits_per_pixel=8)
    next(g)
    return np.stack([np.frombuffer(b, np.uint8).reshape(h, w) for b in g])


def test_video_codecs_write_the_display_frames(tmp_path):
    """``h264``: the same file as imageio's writer converting gray to yuv420p inside ffmpeg (the path before, byte for
    byte), ``y4m``: the 8-bit frames exactly, ``h264-gray``: 4:0:0 H.264 decoding to the frames within CRF 23's loss.
    """
    import imageio.v2 as iio

    from reconstruct.video.live_video import open_video

    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[:50, :64]
    frames = [np.clip(128 + 90 * np.sin(xx / 7 + k / 3) * np.cos(yy / 9) + rng.normal(0, 4, (50, 64)), 0, 255).astype(np.uint8) for k in range(12)]
    params = ["-preset", "ultrafast", "-crf", "23", "-threads", "1"]
    w = iio.get_writer(str(tmp_path / "ref.mp4"), format="FFMPEG", mode="I", fps=342.86, codec="libx264", quality=None, macro_block_size=1,
                       pixelformat="yuv420p", ffmpeg_log_level="error", output_params=list(params))
    for f in frames:
        w.append_data(f)
    w.close()
    for codec, name in (("h264", "a.mp4"), ("y4m", "a.y4m"), ("h264-gray", "g.mp4")):
        v = open_video(tmp_path / name, codec, 50, 64, 342.86, list(params))
        for f in frames:
            v.append(f, False)
        v.close()
    assert (tmp_path / "a.mp4").read_bytes() == (tmp_path / "ref.mp4").read_bytes()
    assert np.array_equal(_decode(tmp_path / "a.y4m", 50, 64), np.stack(frames))
    g = _decode(tmp_path / "g.mp4", 50, 64).astype(int)
    assert g.shape == (12, 50, 64) and np.abs(g - np.stack(frames)).mean() < 4


def test_live_video_codec_y4m_through_the_entry_point(dat, tmp_path, polspike_main):
    """``--video-codec y4m`` writes T.y4m and R.y4m: one frame per output frame, the same 8-bit frames as the PNG
    frames of the run (bad values: tests/recon/test_live_kernels.py, through the console script).
    """
    import imageio.v3 as iio3

    from polinfra.exr import write_exr

    mp = pane_stream_maps(CFG)
    write_exr(tmp_path / "maps.exr", {k: np.asarray(mp[k], np.float32) for k in ("R_perp", "R_par", "phi_perp")}, {})
    r = polspike_main("reconstruct", dat, "--height", H, "--width", W, "--phi0-deg", math.degrees(CFG.phi0_rad), "--rev-per-s", CFG.rev_per_s,
                      "--exposure", CFG.exposure, "--method", "ls", "--no-rir", "--pane", tmp_path / "maps.exr", "--quiet", "--max-frames", 12,
                      "--video-codec", "y4m", "--frames", "png", "--out", tmp_path / "y")
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((tmp_path / "y" / "reconstruct.json").read_text())
    assert s["outputs"] == ["R.y4m", "T.y4m"] and s["frames"] == 12
    for k in ("T", "R"):
        png = np.stack([iio3.imread(tmp_path / "y" / "frames" / f"{k}_{i:06d}.png") for i in range(12)])
        assert png.std() > 1 and np.array_equal(_decode(tmp_path / "y" / f"{k}.y4m", H, W), png)


def test_display_table_is_within_one_level_of_the_exact_mapping():
    from reconstruct.stream.display import _to8
    from reconstruct.video.live import _to8_fast

    x = np.random.default_rng(0).uniform(-0.1, 1.3, 200000).astype(np.float32)
    d = np.abs(_to8_fast(x, 0.9).astype(int) - _to8(x, 0.9).astype(int))
    assert d.max() <= 1 and d.mean() < 0.05


def _writer(path, seconds, chunk_steps, pace):
    """A child process that appends the pane stream to ``path`` chunk by chunk, ``pace`` x real time."""
    code = (
        "import sys, time\n"
        "from reconstruct.stream.pane_stream import PaneStreamConfig, pane_stream_packed\n"
        f"cfg = PaneStreamConfig(height={H}, width={W}, exposure={CFG.exposure})\n"
        f"steps = int({seconds} * cfg.rate_hz)\n"
        "t0 = time.perf_counter(); done = 0\n"
        f"with open({str(path)!r}, 'ab', buffering=0) as fh:\n"
        f"    for pk in pane_stream_packed(cfg, steps, {chunk_steps}):\n"
        f"        rows = pk.reshape(pk.shape[0], {H}, {W // 8})[:, ::-1, :]\n"
        "        fh.write(rows.tobytes()); done += pk.shape[0]\n"
        f"        lag = done / cfg.rate_hz / {pace} - (time.perf_counter() - t0)\n"
        "        if lag > 0: time.sleep(lag)\n"
    )
    return subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})


@pytest.mark.slow
def test_follow_reads_a_growing_dat_and_stops_on_sigint_with_complete_outputs(tmp_path, polspike_cli):
    import imageio.v3 as iio

    dat = tmp_path / "live.dat"
    out = tmp_path / "o"
    w = _writer(dat, 20.0, 200, 0.25)  # a camera writing at a quarter of real time, longer than the test waits
    cmd = [str(polspike_cli.exe), "reconstruct", str(dat), "--height", str(H), "--width", str(W), "--phi0-deg", str(math.degrees(CFG.phi0_rad)),
           "--rev-per-s", "30", "--exposure", str(CFG.exposure), "--method", "ls", "--no-rir", "--zeta", "self", "--fov-deg", "60",
           "--follow", "--follow-idle", "0", "--frames", "png", "--out", str(out), "--quiet"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 120 and len(list((out / "frames").glob("T_*.png")) if (out / "frames").is_dir() else []) < 70:
            assert p.poll() is None, p.communicate()[1][-2000:]
            time.sleep(0.2)
        grown = dat.stat().st_size
        p.send_signal(signal.SIGINT)
        so, se = p.communicate(timeout=120)
    finally:
        w.kill()
        w.wait()
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, se[-2000:]
    s = json.loads((out / "reconstruct.json").read_text())
    assert s["stopped"] == "interrupt" and s["follow"]
    steps = grown // (H * W // 8)
    assert s["frames"] >= 70 and s["frames"] * 58.3 < steps + 2000  # made while the file grew, never past what was written then
    la = s["latency_s"]
    assert la["frames"] == s["frames"] and 0 <= la["median"] <= la["max"] < 30
    assert "latency" in se and "median" in se
    n_png = len(list((out / "frames").glob("T_*.png")))
    assert n_png == s["frames"]
    for name in ("T", "R"):
        frames = sum(1 for _ in iio.imiter(out / f"{name}.mp4"))
        assert frames == s["frames"], (name, frames)
    assert not (out / "preview.mp4").exists()  # the live path writes the side-by-side preview only with --preview
    assert not list(out.glob("*.tmp*")) and not list(out.glob(".*"))  # no partial file left


@pytest.mark.slow
def test_chained_rir_recovers_a_known_translation_as_well_as_the_window_estimate():
    """Oracle: the synthetic group's T layer moves by a known translation per frame; the shift registering frame k
    onto the centre c is pos_T(c) - pos_T(k).  The chained estimate (one registration per frame) is as close to it
    as the per-window masked phase correlation + refinement (within 1.5 x its RMS error, and under 0.1 px).
    """
    import torch

    import reconstruct.stream.synthetic as S
    from reconstruct.physics.rir import ChainedRir, estimate_shifts

    cfg = S.SyntheticConfig(width=160, height=100, n_frames=12, motion_px_per_frame=0.4, noise="integrate_fire", exposure=3.0, seed=1)
    rec, orig = [], S._shifted
    S._shifted = lambda img, dy, dx: (rec.append((dy, dx)), orig(img, dy, dx))[1]
    try:
        g = S.make_group(cfg, 0)
    finally:
        S._shifted = orig
    pos_T = np.array(rec[0::2])  # T is shifted first in every frame
    I = torch.from_numpy(np.asarray(g.I, np.float32))
    phi = torch.from_numpy(np.asarray(g.phi_nominal))
    ch = ChainedRir()
    err_new, err_old = [], []
    for i in range(3, cfg.n_frames - 3):
        true = pos_T[i] - pos_T[i - 3 : i + 4]
        err_new.append(ch.window_shifts(I[i - 3 : i + 4], phi[i - 3 : i + 4], np.arange(i - 3, i + 4)).numpy() - true)
        err_old.append(estimate_shifts(I[i - 3 : i + 4], phi[i - 3 : i + 4]).numpy() - true)
    rms_new = float(np.sqrt(np.mean(np.square(err_new))))
    rms_old = float(np.sqrt(np.mean(np.square(err_old))))
    assert rms_new < 0.1 and rms_new <= 1.5 * rms_old + 0.01, (rms_new, rms_old)


def _assert_frames_match(ref, got, n: int) -> None:
    """The first ``n`` EXR frames of two outputs agree in T and R within TOL_MAX (max) and TOL_MEAN (mean) of the
    reference frame's peak.
    """
    from polinfra.exr import read_exr

    for i in range(n):
        a = read_exr(ref / "frames" / f"{i:06d}.exr", ["T", "R"])
        b = read_exr(got / "frames" / f"{i:06d}.exr", ["T", "R"])
        for k in ("T", "R"):
            peak = float(np.abs(a[k]).max())
            d = np.abs(a[k] - b[k])
            assert peak > 0 and float(d.max()) <= TOL_MAX * peak and float(d.mean()) <= TOL_MEAN * peak, (i, k, float(d.max()), float(d.mean()), peak)
