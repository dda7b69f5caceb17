"""The MP4s of `polspike reconstruct` opened as files: frame count, frame rate (343 FPS) and content.

Read back with the project's own video reader (the generator's ``video:`` layer source,
imageio-ffmpeg underneath) and the container's frame rate from ffmpeg's stream header, never
from the summary dict that the writer returns.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
from reconstruct.stream.sources import array_source
from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

pytestmark = pytest.mark.skipif(not DEFAULT_WEIGHTS.is_file(), reason=f"shipped checkpoint {DEFAULT_WEIGHTS} not present")

OUT_FPS = 10800 / 31.5  # 30 rev/s, 31.5 deg stride: 342.857 output frames per second (supp. Eq. (18))


def _read(path, shape):
    from generator.layers import load_source

    return np.array(load_source(f"video:{path}", shape, gamma=1.0))


def _fps(path) -> float:
    import imageio.v3 as iio

    return float(iio.immeta(path, plugin="FFMPEG")["fps"])


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    import torch

    torch.set_num_threads(1)
    model = load_model(DEFAULT_WEIGHTS)[0]
    rng = np.random.default_rng(3)
    H, W = 16, 24
    # a left-to-right ramp of firing rates and a dark block sliding right (1 px per 20 steps, ~3 px per output
    # frame): frames that differ by content, not only by noise (a network taking the 17.5 ms spike mean returns
    # nearly the same frame for a static scene)
    ramp = np.broadcast_to(np.linspace(0.05, 0.45, W), (H, W))
    spikes = np.empty((1400, H, W), np.uint8)
    for t in range(spikes.shape[0]):
        rate = ramp.copy()
        x0 = (t // 20) % W
        rate[: H // 2, x0 : x0 + W // 4] = 0.02
        spikes[t] = rng.random((H, W)) < rate
    out = tmp_path_factory.mktemp("video")
    s = reconstruct_stream(array_source(spikes, 0.0, 30.0, chunk_steps=400), model, out, ReconstructConfig(max_frames=4, video=True, frames="png"))
    return out, s, (H, W)


def test_mp4_frame_count_and_rate(reconstructed):
    out, s, (H, W) = reconstructed
    assert s["frames"] == 4
    for name, width in (("T", W), ("R", W), ("preview", 3 * W)):
        frames = _read(out / f"{name}.mp4", (H, width))
        assert frames.shape[0] == s["frames"], (name, frames.shape)
        assert math.isclose(_fps(out / f"{name}.mp4"), OUT_FPS, rel_tol=1e-3), (name, _fps(out / f"{name}.mp4"))


def test_mp4_frames_are_the_reconstructed_frames_in_order(reconstructed):
    """Each decoded T frame matches its PNG (same tone mapping) to H.264 error, and not its neighbours' better."""
    import imageio.v3 as iio

    out, s, (H, W) = reconstructed
    video = _read(out / "T.mp4", (H, W))
    pngs = np.array([iio.imread(out / "frames" / f"T_{i:06d}.png") / 255.0 for i in range(s["frames"])])
    err = np.abs(video[:, None] - pngs[None]).mean(axis=(2, 3))  # err[i, j]: video frame i vs PNG j
    assert np.all(np.diag(err) < 0.03), np.diag(err)
    assert np.all(np.argmin(err, axis=1) == np.arange(s["frames"])), err
