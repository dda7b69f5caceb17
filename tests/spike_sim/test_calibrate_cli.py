"""`polspike calibrate GROUP`: phase and speed from a stored group, error against its true phi(t)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

from polphysics.polarizer import PolarizerConfig
from polspike.cli import get_app
from spike_sim.config import DEFAULT
from spike_sim.simulate import keyframes_from_arrays, simulate

H, W = 30, 40


def _group(tmp_path, stokes, pol, maps=None, duration=0.12):
    cfg = dataclasses.replace(DEFAULT, width=W, height=H)
    src = keyframes_from_arrays([0.0], stokes[None].astype(np.float32), maps=maps, polarizer=pol)
    simulate(src, duration, 3, cfg, out=tmp_path / "g")
    return tmp_path / "g"


def _calibrate(args):
    r = CliRunner().invoke(get_app(), ["calibrate", *map(str, args), "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.output)


def test_flat_target_group(tmp_path):
    """Flat target at 20 deg, true phase = nominal 37 + offset 3 deg, rate 29.7: recovered to < 0.1 deg / 1e-3."""
    psi = np.deg2rad(20.0)
    st = np.stack([np.full((H, W), 0.6), np.full((H, W), 0.6 * np.cos(2 * psi)), np.full((H, W), 0.6 * np.sin(2 * psi))])
    g = _group(tmp_path, st, PolarizerConfig(rate_hz=29.7, phase_deg=37.0, calibration_offset_deg=3.0))
    res = _calibrate([g, "--target-aolp-deg", "20"])
    assert res["phi0_deg"] == pytest.approx(40.0, abs=0.1) and res["nominal_phase_deg"] == 37.0
    assert res["rate_hz"] == pytest.approx(29.7, rel=1e-3)
    assert abs(res["phi0_err_deg"]) < 0.1 and res["max_abs_deg"] < 0.1
    fixed = _calibrate([g, "--target-aolp-deg", "20", "--rate-hz", "29.7"])
    assert fixed["rate_hz"] == 29.7 and fixed["max_abs_deg"] < 0.1


def test_glass_scene_group_uses_the_stored_phi_perp_map(tmp_path):
    """No target: the group's phi_perp map is the polarization axis (up to 90 deg); nominal phase breaks the tie."""
    phi_perp = np.deg2rad(10.0) + np.deg2rad(15.0) * np.linspace(0, 1, W)[None].repeat(H, 0)
    sign = np.where(np.arange(W)[None].repeat(H, 0) < W // 2, 1.0, -1.0)
    st = np.stack([np.full((H, W), 0.6), 0.3 * sign * np.cos(2 * phi_perp), 0.3 * sign * np.sin(2 * phi_perp)])
    maps = {"phi_perp": phi_perp.astype(np.float32), "R_perp": np.full((H, W), 0.2, np.float32), "R_par": np.full((H, W), 0.05, np.float32)}
    g = _group(tmp_path, st, PolarizerConfig(phase_deg=-50.0, calibration_offset_deg=4.0), maps=maps)
    res = _calibrate([g])
    assert res["method"] == "modulation fit"
    assert res["phi0_deg"] == pytest.approx(180.0 - 46.0, abs=0.1)
    assert res["rms_deg"] < 0.1


def test_group_without_maps_needs_a_target(tmp_path):
    from polinfra.errors import ConfigError

    st = np.stack([np.full((H, W), 0.6), np.full((H, W), 0.3), np.zeros((H, W))])
    g = _group(tmp_path, st, PolarizerConfig(), duration=0.01)
    r = CliRunner().invoke(get_app(), ["calibrate", str(g)])
    assert isinstance(r.exception, ConfigError) and "--target-aolp-deg" in str(r.exception)


def test_calibration_verdict_is_the_exit_code_of_the_console_script(tmp_path, polspike_cli):
    """Through the installed `polspike` script: a good calibration exits 0; one whose phi(t) misses the
    true angle by more than --tolerance-deg rms exits 1 with verdict "fail"; a bad tolerance exits 2.
    """
    psi = np.deg2rad(20.0)
    st = np.stack([np.full((H, W), 0.6), np.full((H, W), 0.6 * np.cos(2 * psi)), np.full((H, W), 0.6 * np.sin(2 * psi))])
    g = _group(tmp_path, st, PolarizerConfig(rate_hz=29.7, phase_deg=37.0, calibration_offset_deg=3.0))
    ok = polspike_cli("calibrate", g, "--target-aolp-deg", "20", "--json")
    assert ok.returncode == 0, ok.stderr[-1500:]
    res = json.loads(ok.stdout)
    assert res["verdict"] == "pass" and res["rms_deg"] < 0.1 and res["tolerance_deg"] == 1.0
    # the operator gives the wrong target angle (50 instead of 20 deg): phi0 is off by 30 deg
    bad = polspike_cli("calibrate", g, "--target-aolp-deg", "50", "--json")
    assert bad.returncode == 1, (bad.returncode, bad.stdout[-400:], bad.stderr[-1500:])
    res = json.loads(bad.stdout)
    assert res["verdict"] == "fail" and res["rms_deg"] == pytest.approx(30.0, abs=0.2)
    # the same run in sentence form: exit 1 and the verdict printed
    text = polspike_cli("calibrate", g, "--target-aolp-deg", "50")
    assert text.returncode == 1 and "verdict fail" in " ".join(text.stdout.split())
    # a tighter tolerance than the achieved error fails a good calibration too
    tight = polspike_cli("calibrate", g, "--target-aolp-deg", "20", "--tolerance-deg", "1e-6", "--json")
    assert tight.returncode == 1 and json.loads(tight.stdout)["verdict"] == "fail"
    polspike_cli.one_line_exit_2(polspike_cli("calibrate", g, "--tolerance-deg", "0"), "--tolerance-deg")
