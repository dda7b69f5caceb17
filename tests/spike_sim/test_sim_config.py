"""SpikeSimConfig: presets, strict loading, documented units."""

from __future__ import annotations

import dataclasses

import pytest

from polinfra.config import from_dict, to_dict
from polinfra.errors import ConfigError
from spike_sim.config import DEFAULT, IDEAL, PRESETS, SpikeSimConfig, preset


def test_defaults_match_the_issue():
    assert (DEFAULT.width, DEFAULT.height, DEFAULT.rate_hz) == (400, 250, 20000.0)
    assert DEFAULT.dt_s == pytest.approx(5e-5)
    assert DEFAULT.n_pixels == 100000


def test_ideal_preset_switches_every_noise_term_off():
    flags = [f.name for f in dataclasses.fields(SpikeSimConfig) if isinstance(getattr(IDEAL, f.name), bool)]
    assert len(flags) == 7
    assert not any(getattr(IDEAL, f) for f in flags)
    assert all(getattr(DEFAULT, f) for f in flags)


def test_presets_and_unknown_name():
    assert set(PRESETS) >= {"ideal", "default"}
    assert preset("ideal") is IDEAL
    with pytest.raises(ConfigError, match="choose one of"):
        preset("bogus")


def test_round_trip_and_strictness():
    assert from_dict(SpikeSimConfig, to_dict(DEFAULT)) == DEFAULT
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(SpikeSimConfig, {"exposur": 1.0})
    with pytest.raises(ConfigError, match="out of range"):
        from_dict(SpikeSimConfig, {"gain_sigma": 2.0})
