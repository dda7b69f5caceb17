"""Paper Eq. (3) aggregation: centres at multiples of the angular stride, window sums, N = 2K + 1 stacks."""

from __future__ import annotations

import numpy as np
import pytest

from polinfra.errors import ConfigError, ShapeError
from spike_sim.aggregate import AggregateConfig, aggregate_stream, frame_centres, observation_stack, output_fps

DT = 5e-5


def test_default_cadence_is_342_9_fps():
    assert output_fps(30.0, 31.5) == pytest.approx(342.857, abs=1e-3)
    cfg = AggregateConfig()
    assert (cfg.window_steps, cfg.n_obs, cfg.K) == (13, 7, 3)
    assert cfg.window_steps * DT == pytest.approx(0.65e-3)


def test_centres_follow_the_angular_stride():
    t = (np.arange(20000) + 0.5) * DT
    phi = 0.3 + 2 * np.pi * 30.0 * t
    c, phi_i = frame_centres(phi, phi_start_rad=0.3)
    assert c.size == 342  # 1 s at 342.9 fps, first window (at t = 0) does not fit
    steps = np.diff(np.rad2deg(phi_i))
    assert np.all(np.abs(steps - 31.5) < 0.54 + 1e-9)  # rounded to whole steps (0.54 deg each)
    assert np.rad2deg(phi_i[-1] - phi_i[0]) == pytest.approx(31.5 * 341, abs=0.3)
    # wobbly speed: centres still land where the angle has turned by multiples of the stride
    phi_w = phi + 0.2 * np.sin(2 * np.pi * 3 * t)
    cw, pw = frame_centres(phi_w, phi_start_rad=0.3)
    k = np.rint((pw - 0.3) / np.deg2rad(31.5))
    assert np.all(np.abs(pw - 0.3 - k * np.deg2rad(31.5)) < np.deg2rad(0.6))


def test_window_sum_is_eq3():
    rng = np.random.default_rng(0)
    s = (rng.random((200, 4, 5)) < 0.3).astype(np.uint8)
    c = np.array([6, 50, 193])
    I = aggregate_stream(s, c)
    for m, cc in enumerate(c):
        np.testing.assert_allclose(I[m], s[cc - 6 : cc + 7].sum(0) / 13.0, rtol=1e-6)
    with pytest.raises(ShapeError):
        aggregate_stream(s, np.array([5]))


def test_observation_stack_and_validation():
    I = np.arange(10 * 2 * 2, dtype=np.float32).reshape(10, 2, 2)
    st, ph = observation_stack(I, np.arange(10.0), 5, K=3)
    assert st.shape == (7, 2, 2) and list(ph) == [2, 3, 4, 5, 6, 7, 8]
    with pytest.raises(ShapeError):
        observation_stack(I, np.arange(10.0), 2, K=3)
    with pytest.raises(ConfigError, match="odd"):
        AggregateConfig(window_steps=12)
