"""The glass of a stream's self-calibration: `polspike reconstruct` fits the index and pane model where the spikes
constrain them (as the evaluation's group_self_zeta does), unless the user knows them (--pane-n, --pane-model).
"""

from __future__ import annotations

import pytest

import reconstruct.pane.source as pv
from reconstruct.pane.selfcal import SelfCalConfig


@pytest.fixture
def captured(monkeypatch):
    seen = []
    monkeypatch.setattr(pv, "calibrate_source", lambda source, window_steps=13, exposure=None, cfg=SelfCalConfig(): seen.append(cfg) or "result")
    return seen


def test_stream_calibration_fits_the_glass_by_default(captured):
    """Defaults are the self-calibration's own (model auto, prior index 1.5), the ones the evaluation measures; before,
    a stream was calibrated as a single interface of n 1.5 whatever its spikes said.
    """
    assert pv.calibrate_stream(object()) == "result"
    assert captured[-1].model == SelfCalConfig().model == "auto" and captured[-1].n == 1.5
    pv.calibrate_stream(object(), pane_n=1.62, pane_model="auto")
    assert captured[-1].model == "auto" and captured[-1].n == 1.62  # a known index with the model still fitted
    pv.calibrate_stream(object(), pane_n=1.52, pane_model="thin_slab")
    assert captured[-1].model == "thin_slab" and captured[-1].n == 1.52


def test_net_zeta_passes_the_known_glass_on(monkeypatch):
    from reconstruct.net import net_zeta

    seen = {}

    def fake(source, group_dir, window_steps, exposure, selfcal, pane_n, pane_model):
        seen.update(n=pane_n, model=pane_model)
        raise RuntimeError("stop")

    monkeypatch.setattr(pv, "calibrate_stream", fake)
    for kw, want in (({}, (None, None)), ({"pane_n": 1.7, "pane_model": "single"}, (1.7, "single"))):
        with pytest.raises(RuntimeError):
            net_zeta.build_net_zeta_model(object(), "self", object(), **kw)
        assert (seen["n"], seen["model"]) == want


def test_cli_pane_glass_usage_errors(tmp_path, polspike_cli, polspike_main):
    f = tmp_path / "x.dat"
    f.write_bytes(bytes(8 * 16 * 20))
    geo = ("--height", 16, "--width", 20, "--phi0-deg", 0, "--rev-per-s", 30)
    r = polspike_cli("reconstruct", f, *geo, "--pane-model", "slab", "--out", tmp_path / "o")
    polspike_cli.one_line_exit_2(r, "--pane-model 'slab'", "thin_slab")
    r = polspike_main("reconstruct", f, *geo, "--pane-n", 0.8, "--out", tmp_path / "o")
    polspike_main.one_line_exit_2(r, "--pane-n 0.8")
    assert not (tmp_path / "o").exists()
