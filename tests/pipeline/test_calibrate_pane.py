"""calibrate-pane: the pane and field of view fitted to spikes behind a pane of known truth.

The truth is built independently of the fit: polphysics' camera, plane and Fresnel formulas and paper
Eq. (1)-(2) (window-averaged), Poisson spike counts; the fit differentiates generator.pane_fit's Dr.Jit
model.  Sizes are tiny (96 x 64, 0.1 s) so each case takes seconds.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from _mitsuba_common import require_mitsuba

from polphysics.fresnel import pane_coefficients
from polphysics.geometry import Plane, incidence_geometry


@pytest.fixture(autouse=True)
def _mitsuba_works():
    """The one skip policy (_mitsuba_common.require_mitsuba): skip only when mitsuba is not installed; under CI
    an installed Mitsuba whose import or backend fails is a failure, not a skip.
    """
    require_mitsuba()


def _field(rng, H, W, shift):
    """Smooth random field in [-1, 1] (a few low-frequency waves), shifted by (dx, dy) pixels."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    f = np.zeros((H, W))
    for _ in range(6):
        k = rng.uniform(0.02, 0.08) * 2 * math.pi
        a = rng.uniform(0, 2 * math.pi)
        f += np.cos(k * ((x - shift[0]) * math.cos(a) + (y - shift[1]) * math.sin(a)) + rng.uniform(0, 2 * math.pi))
    return f / 6 * 2.2


def _pane_geometry(tilt_deg, azimuth_deg, fov_deg, W, H, n, model):
    """The known pane's per-pixel geometry and Fresnel coefficients, and the 13-step window's polarizer sweep and sinc."""
    from reconstruct.pane.camera import camera_for, normal_from_angles

    cam = camera_for(W, H, fov_deg)
    N = normal_from_angles(math.radians(tilt_deg), math.radians(azimuth_deg), cam)
    geo = incidence_geometry(cam, Plane(cam.position + cam.forward, N))
    co = pane_coefficients(geo["theta"], n, model=model)
    span = 2 * math.pi * 30.0 * 13 / 20000.0
    return geo, co, span, math.sin(span) / span


def pane_stream(tilt_deg, azimuth_deg, *, fov_deg=55.0, n=1.5, model="single", H=64, W=96, M=34, exposure=40.0, black=True, seed=0, stride_deg=31.5, motion=1.0):
    """Eq. (3) frames behind a known pane (13-step windows at 20 kHz, 30 rev/s, ``stride_deg`` apart:
    31.5 = the output cadence, 7.02 = back to back).  black=True: T is black over part of the view and R
    over another part (the cone's edges are reached); else both layers are >= 0.3 everywhere.
    """
    rng = np.random.default_rng(seed)
    geo, co, span, sinc = _pane_geometry(tilt_deg, azimuth_deg, fov_deg, W, H, n, model)
    phi = rng.uniform(0, math.pi) + math.radians(stride_deg) * np.arange(M)
    sT, sR = rng.integers(0, 2**31), rng.integers(0, 2**31)
    I = []
    for i in range(M):
        fT = _field(np.random.default_rng(sT), H, W, (0.7 * motion * i, 0.0))
        fR = _field(np.random.default_rng(sR), H, W, (0.0, 0.4 * motion * i))
        if black:
            T = np.where(fT < -0.3, 0.0, 0.6 + 0.3 * fT)
            R = np.where((fR < -0.3) & (fT >= -0.3), 0.0, 1.0 + 0.5 * fR)
        else:
            T = 0.6 + 0.25 * fT
            R = 1.0 + 0.5 * fR
        z = 0.5 * (co["R_perp"] + co["R_par"]) + 0.5 * (co["R_perp"] - co["R_par"]) * sinc * np.cos(2 * (phi[i] - geo["phi_perp"]))  # Eq. (2)
        L = 0.5 * (z * np.maximum(R, 0) + (1 - z) * np.maximum(T, 0))  # Eq. (1)
        steps = 13 * exposure
        I.append(rng.poisson(L * steps) / steps)  # Eq. (3)
    return np.asarray(I, np.float32), phi, span, geo


def _errors(res, geo):
    th = np.degrees(np.abs(res["maps"]["theta"] - geo["theta"]))
    dp = np.degrees(np.abs(np.mod(res["maps"]["phi_perp"] - geo["phi_perp"] + math.pi / 2, math.pi) - math.pi / 2))
    return float(np.median(th)), float(np.median(dp))


CASES = [(55.0, 30.0, "single", 1.5), (40.0, 200.0, "thin_slab", 1.6), (30.0, 120.0, "single", 1.52)]


@pytest.mark.parametrize("tilt,az,model,n", [CASES[0], pytest.param(*CASES[1], marks=pytest.mark.slow)])
def test_geometry_recovered_with_fitted_fov(tilt, az, model, n):
    """Known pane, field of view fitted (96 x 64, 55 deg): phi_perp within the goal (0.5 deg median); the
    reported 1-sigma uncertainties cover the truth (tilt, azimuth, fov within 4 sigma; theta's median error
    within 3 of its median 1-sigma, and within 1 deg), and the fov is claimed exactly when theta's 1-sigma
    passes the 0.5 deg gate.
    """
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    I, phi, span, geo = pane_stream(tilt, az, n=n, model=model)
    res = calibrate_frames(I, phi, CalibratePaneConfig(), span_rad=span)
    assert res["ok"]
    th, ph = _errors(res, geo)
    p, u = res["report"]["params"], res["report"]["uncertainty_1sigma"]
    assert ph <= 0.5 and th <= 1.0 and th <= 3 * u["theta_deg_median"], (th, ph, u["theta_deg_median"])
    assert abs(p["tilt_deg"] - tilt) <= 4 * u["tilt_deg"] + 0.05
    assert abs(p["fov_deg"] - 55.0) <= 4 * u["fov_deg"] + 0.05
    assert abs((p["azimuth_deg"] - az + 180) % 360 - 180) <= 4 * u["azimuth_deg"] + 0.05
    fv = res["report"]["identifiability"]["fov"]
    assert fv["identified"] is (fv["theta_sigma_deg_median"] <= 0.5)


@pytest.mark.slow
def test_a_narrow_view_reports_the_fov_tilt_trade_off_instead_of_claiming_theta():
    """Narrow view (fov 15 deg), fov fitted: phi_perp's curvature barely changes along the fov-tilt valley,
    so the fit must not claim theta: the fov is reported NOT identified, theta's 1-sigma exceeds the 0.5 deg
    gate, and the truth lies within 4 reported sigmas (honest error bars).
    """
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    tilt, az = 50.0, 60.0
    I, phi, span, geo = pane_stream(tilt, az, fov_deg=15.0, n=1.5, model="single", H=48, W=72)
    res = calibrate_frames(I, phi, CalibratePaneConfig(), span_rad=span)
    assert res["ok"]
    rep = res["report"]
    fv = rep["identifiability"]["fov"]
    assert fv["identified"] is False and fv["theta_sigma_deg_median"] > 0.5 and "fov-deg" in fv["why"]
    u = rep["uncertainty_1sigma"]
    assert abs(rep["params"]["tilt_deg"] - tilt) <= 4 * u["tilt_deg"] and abs(rep["params"]["fov_deg"] - 15.0) <= 4 * u["fov_deg"]
    th, ph = _errors(res, geo)
    assert ph <= 0.5  # the orientation itself is pinned


def test_a_fov_fit_that_ends_in_a_degenerate_view_keeps_the_self_calibrated_fov(monkeypatch):
    """Where the fov-free orientation fit slides to its bound (an orthographic view: seen on a weakly reflecting
    62 deg view of eval_fresh_val, every start ended at fov 5 deg while the self-calibration's vanishing point gave
    34 deg), calibrate-pane keeps the self-calibration's fov and fits the orientation at it instead of refusing:
    the result is usable (phi_perp within the goal) and the fov is reported NOT identified with the reason.
    """
    import polspike.pipeline.calibrate_pane as cp
    import reconstruct.pane.calibrate as core

    real = core.fit_geometry
    calls = []

    def sliding(of, width, height, block, x0, fit_fov, **kw):
        geo = real(of, width, height, block, x0, fit_fov, **kw)
        calls.append(fit_fov)
        if fit_fov:  # the valley's end: the bound
            geo = dataclasses.replace(geo, x=np.r_[geo.x[:2], math.radians(5.0), geo.x[3:]])
        return geo

    monkeypatch.setattr(core, "fit_geometry", sliding)
    tilt, az = CASES[0][:2]
    I, phi, span, geo = pane_stream(tilt, az, n=1.5, model="single")
    res = cp.calibrate_frames(I, phi, cp.CalibratePaneConfig(), span_rad=span)
    assert calls == [True, False]
    assert res["ok"], res["report"].get("reason")
    rep = res["report"]
    kept = rep["geometry"]["fov_kept"]
    assert kept["by"] == "self_calibration" and kept["ended_at"][2] == pytest.approx(5.0) and rep["params"]["fov_deg"] == pytest.approx(rep["init"]["fov_deg"])
    fv = rep["identifiability"]["fov"]
    assert fv["identified"] is False and "ran into its bounds" in fv["why"] and "--fov-deg" in fv["why"]
    th, ph = _errors(res, geo)
    assert ph <= 0.5 and th <= 1.0  # this stream's self-calibrated fov is close to the truth (55 deg)
    # without the degenerate end nothing is kept
    monkeypatch.setattr(core, "fit_geometry", real)
    assert cp.calibrate_frames(I, phi, cp.CalibratePaneConfig(), span_rad=span)["report"]["geometry"]["fov_kept"] is None


def test_max_incidence_is_the_maps_theta_where_every_ray_meets_the_pane_and_exceeds_90_where_some_do_not():
    """max_incidence_deg against the differentiable tracer's own theta (block centres): equal where every ray meets
    the pane in front; a steep pane seen wide (tilt 80, fov 60) has rays beyond 90 deg, which the maps fold back.
    """
    from generator.pane_fit import PaneModelAD
    from reconstruct.pane.geometry_fit import max_incidence_deg

    W, H, block = 96, 64, 4
    pm = PaneModelAD(W, H, "single", block=block)
    every = np.ones((H // block, W // block), bool)
    for tilt, az, fov in ((50.0, 30.0, 55.0), (20.0, 250.0, 80.0)):
        x = np.radians([tilt, az, fov, 0.0])
        x[3] = 1.5
        assert max_incidence_deg(x, W, H, block, every) == pytest.approx(float(np.degrees(pm.maps(x)["theta"].max())), abs=1e-3)
    x = np.r_[np.radians([80.0, 100.0, 60.0]), 1.5]
    assert max_incidence_deg(x, W, H, block, every) > 90.0 > float(np.degrees(pm.maps(x)["theta"].max()))
    half = every.copy()
    half[H // block // 2:] = False  # the normal leans up (azimuth 100): the steepest rays are in the lower half
    assert max_incidence_deg(x, W, H, block, half) < max_incidence_deg(x, W, H, block, every)


def test_a_fov_fit_that_ends_where_modulating_blocks_could_not_see_the_pane_is_narrowed(monkeypatch):
    """The fov-free orientation fit made to end at a 140 deg view of a 30 deg pane, where blocks that modulate would
    meet the pane beyond 90 deg: the fov is bisected to the widest view that keeps every modulating block within
    max_incidence_deg (89), on that boundary to the bisection's resolution, and reported NOT identified, why said.
    Unpatched, nothing is narrowed.
    """
    import polspike.pipeline.calibrate_pane as cp
    import reconstruct.pane.calibrate as core

    real = core.fit_geometry

    def too_wide(of, width, height, block, x0, fit_fov, **kw):
        geo = real(of, width, height, block, x0, fit_fov, **kw)
        if fit_fov:
            geo = dataclasses.replace(geo, x=np.r_[geo.x[:2], math.radians(140.0), geo.x[3:]])
        return geo

    tilt, az = CASES[2][:2]
    I, phi, span, geo = pane_stream(tilt, az, n=1.52, model="single")
    assert cp.calibrate_frames(I, phi, cp.CalibratePaneConfig(), span_rad=span)["report"]["geometry"]["fov_kept"] is None
    monkeypatch.setattr(core, "fit_geometry", too_wide)
    res = cp.calibrate_frames(I, phi, cp.CalibratePaneConfig(), span_rad=span)
    assert res["ok"], res["report"].get("reason")
    rep = res["report"]
    kept = rep["geometry"]["fov_kept"]
    assert kept["by"] == "feasibility" and kept["ended_at"][2] == pytest.approx(140.0) and kept["max_incidence_deg_there"] > 89.0
    assert rep["params"]["fov_deg"] == pytest.approx(kept["fov_deg"]) and rep["params"]["fov_deg"] < 140.0
    x = np.radians([rep["params"]["tilt_deg"], rep["params"]["azimuth_deg"], rep["params"]["fov_deg"]])
    block = rep["geometry"]["block_px"]
    gh, gw = rep["geometry"]["blocks"][1], rep["geometry"]["blocks"][0]
    mi = core.max_incidence_deg(x, 96, 64, block, np.ones((gh, gw), bool))  # every block of this stream modulates
    assert 87.0 <= mi <= 89.0 + 1e-6, mi  # on the boundary, to the bisection's resolution
    fv = rep["identifiability"]["fov"]
    assert fv["identified"] is False and "edge-on or behind" in fv["why"] and "--fov-deg" in fv["why"]


def test_geometry_with_known_fov():
    """Fov given (a low tilt, 30 deg): theta and phi_perp within the goal (0.5 deg median), tilt within
    1 deg and 4 reported sigmas.
    """
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    tilt, az = CASES[2][:2]
    I, phi, span, geo = pane_stream(tilt, az, n=1.52, model="single")
    res = calibrate_frames(I, phi, CalibratePaneConfig(fov_deg=55.0), span_rad=span)
    rep = res["report"]
    err = abs(rep["params"]["tilt_deg"] - tilt)
    assert err <= 1.0 and err <= 4 * rep["uncertainty_1sigma"]["tilt_deg"]
    assert rep["params"]["fov_deg"] == pytest.approx(55.0)
    assert rep["identifiability"]["fov"]["identified"] is None  # given
    th, ph = _errors(res, geo)
    assert th <= 0.5 and ph <= 0.5


def test_refuses_to_claim_the_glass_when_no_layer_is_ever_black():
    """Layers never black (the cone's edges are not reached): n and the model are reported as NOT
    identified and the priors are kept (not the truth, 1.6 / single, by luck); the geometry's truth lies
    within 4 reported sigmas even on this weakly modulating stream.
    """
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    tilt, az = CASES[2][:2]
    I, phi, span, geo = pane_stream(tilt, az, n=1.6, model="single", black=False)
    res = calibrate_frames(I, phi, CalibratePaneConfig(fov_deg=55.0, content=False), span_rad=span)
    rep = res["report"]
    assert abs(rep["params"]["tilt_deg"] - tilt) <= 4 * rep["uncertainty_1sigma"]["tilt_deg"]
    ident = rep["identifiability"]
    assert ident["n"]["identified"] is False and rep["params"]["n"] == 1.5
    assert ident["model"]["identified"] is False and rep["params"]["model"] == "thin_slab"
    assert ident["reflectance_scale"]["identified"] is False and ident["thickness"]["identified"] is False
    # with the content test (default): these layers are a few smooth waves (their gradients correlate by chance):
    # whatever it claims must be right
    rep = calibrate_frames(I, phi, CalibratePaneConfig(fov_deg=55.0), span_rad=span)["report"]
    ident = rep["identifiability"]
    assert ident["model"]["identified"] is False or rep["params"]["model"] == "single"
    assert ident["n"]["identified"] is False or abs(rep["params"]["n"] - 1.6) <= 0.03


@pytest.mark.parametrize("z,model", [(2.0, "single"), (0.5, "thin_slab")])
def test_an_unclaimed_model_guess_stands_when_its_best_index_is_at_the_end_of_the_range(monkeypatch, z, model):
    """The content test prefers single by z standard errors, at n = 1.40 (the range's end: no minimum).  The model
    comparison holds over the same range of indices, so above content_best_z (1) the maps use single; the index is
    no estimate, so the prior 1.5 stays and the report says why.  Below it, the prior model stays.
    """
    import polspike.pipeline.calibrate_pane as cp
    import reconstruct.pane.calibrate as core

    tilt, az = CASES[2][:2]
    I, phi, span, _ = pane_stream(tilt, az, n=1.6, model="single", black=False)
    grid = core.CONTENT_N_GRID

    def fake(*a, **kw):
        sc = {"single": [0.1] * grid.size, "thin_slab": [0.2] * grid.size}
        return {"ok": True, "tiles": 36, "n_grid": grid.tolist(), "score": sc, "best_model": "single", "best_n": float(grid[0]), "best_score": 0.1,
                "model": {"identified": False, "value": "single", "z": z, "other": "thin_slab", "other_n": 1.5, "other_score": 0.2, "why": "fake"},
                "n": {"identified": False, "value": float(grid[0]), "accepted_range": [1.4, 1.46], "why": "fake"}}

    monkeypatch.setattr(core, "content_glass", fake)
    rep = cp.calibrate_frames(I, phi, cp.CalibratePaneConfig(fov_deg=55.0), span_rad=span)["report"]
    ident = rep["identifiability"]
    assert ident["model"]["identified"] is False and ident["n"]["identified"] is False
    assert rep["params"]["model"] == model and rep["params"]["n"] == 1.5
    assert "end of the range" in ident["n"]["why"]


def textured_stream(tilt_deg, azimuth_deg, model, n, *, H=80, W=128, M=104, fov_deg=70.0, exposure=200.0, R_level=1.0, T_level=0.5, contrast=True, seed=0):
    """Back-to-back 13-step windows behind a known pane (polphysics geometry and Fresnel, paper Eq. (1)-(2),
    Poisson counts) of static layers with fine independent textures (Gaussian-smoothed white noise, 1.5 px), or
    flat layers (contrast=False).
    """
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    geo, co, span, sinc = _pane_geometry(tilt_deg, azimuth_deg, fov_deg, W, H, n, model)
    phi = rng.uniform(0, math.pi) + span * np.arange(M)

    def tex(s):
        f = gaussian_filter(np.random.default_rng(s).standard_normal((H, W)), 1.5)
        return f / f.std()

    T = np.clip(T_level * (1 + 0.4 * tex([seed, 1])), 0.05, None) if contrast else np.full((H, W), T_level)
    R = np.clip(R_level * (1 + 0.4 * tex([seed, 2])), 0.05, None) if contrast else np.full((H, W), R_level)
    I = []
    for p in phi:
        z = 0.5 * (co["R_perp"] + co["R_par"]) + 0.5 * (co["R_perp"] - co["R_par"]) * sinc * np.cos(2 * (p - geo["phi_perp"]))  # Eq. (2)
        L = 0.5 * (z * R + (1 - z) * T)  # Eq. (1)
        I.append(rng.poisson(L * 13 * exposure) / (13 * exposure))  # Eq. (3)
    return np.asarray(I, np.float32), phi, sinc, geo


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_content_test_picks_the_pane_model_from_textured_layers(model):
    """Textured independent layers, wide view of a tilted pane (theta 31-90 deg), n 1.5, no layer black (the cone
    says nothing): the layers solved under the true model are the least mixed; the other model's best index scores
    clearly worse (>= 2 standard errors over the tiles), and the true index is inside the accepted range.
    """
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.content_glass import content_glass

    I, phi, g, geo = textured_stream(70.0, 30.0, model, 1.5)
    r = content_glass(I, phi, geo["theta"], geo["phi_perp"], g, ("single", "thin_slab"), CalibratePaneConfig())
    assert r["ok"] and r["best_model"] == model, r.get("model")
    assert r["model"]["z"] >= 2.0, r["model"]
    lo, hi = r["n"]["accepted_range"]
    assert lo <= 1.5 <= hi and abs(r["best_n"] - 1.5) <= 0.1


def test_content_pixels_auto_splits_where_the_span_holds_enough_parts():
    """content_pixels = auto: 0.07 s (2 time parts) scores exactly as same; 0.2 s (4 parts of 3 half turns) exactly as
    split (the checkerboard sets, which drop the fixed pattern's pull on the index).  Explicit choices are kept.
    """
    import dataclasses

    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.content_glass import CONTENT_SPLIT_PARTS, content_glass, content_pixels_for

    assert [content_pixels_for("auto", p) for p in (2, 3, 4, 6)] == ["same", "same", "split", "split"] and CONTENT_SPLIT_PARTS == 4
    assert content_pixels_for("same", 8) == "same" and content_pixels_for("split", 2) == "split"
    for M, parts, mode in ((104, 2, "same"), (307, 4, "split")):
        I, phi, g, geo = textured_stream(60.0, 30.0, "single", 1.5, H=40, W=64, M=M)
        run = lambda px: content_glass(I, phi, geo["theta"], geo["phi_perp"], g, ("single",), dataclasses.replace(CalibratePaneConfig(), content_pixels=px))  # noqa: E731
        auto, fixed = run("auto"), run(mode)
        assert auto["parts"] == parts and auto["pixels"] == mode
        np.testing.assert_array_equal(auto["score"]["single"], fixed["score"]["single"])
        other = run("split" if mode == "same" else "same")
        assert np.max(np.abs(np.subtract(other["score"]["single"], auto["score"]["single"]))) > 0


@pytest.mark.parametrize("tilt,n,sigma_deg", [(50.0, 1.55, 0.5), (35.0, 1.6, 1.0), (70.0, 1.5, 0.3)])
def test_content_index_uncertainty_from_the_geometry_matches_the_dop_slope(tilt, n, sigma_deg):
    """A narrow view (fov 10 deg) whose tilt is uncertain by sigma: every theta moves by about sigma, so the index
    that keeps the reflection's DoP moves by |dDoP/dtheta| / |dDoP/dn| sigma (finite differences of the Fresnel
    formulas at the centre, an independent oracle), to the 0.0025 grid of the search.
    """
    from generator.pane_fit import PaneModelAD
    from polphysics.fresnel import pane_coefficients
    from reconstruct.pane.content_glass import content_n_sigma_from_geometry

    pm = PaneModelAD(64, 40, "single", sub=1)
    x = np.array([math.radians(tilt), 0.3, math.radians(10.0), n])
    got = content_n_sigma_from_geometry(pm, x, np.diag([math.radians(sigma_deg) ** 2, 1e-14]), (0, 1), "single", n)

    def dop(t, m):
        c = pane_coefficients(np.array([t]), m, model="single")
        return float(((c["R_perp"] - c["R_par"]) / (c["R_perp"] + c["R_par"]))[0])

    t0, e = math.radians(tilt), 1e-5
    slope = abs((dop(t0 + e, n) - dop(t0 - e, n)) / (dop(t0, n + e) - dop(t0, n - e)))
    assert got == pytest.approx(slope * math.radians(sigma_deg), abs=0.003)
    assert content_n_sigma_from_geometry(pm, x, np.zeros((2, 2)), (0, 1), "single", n) < 1e-9


def test_content_test_claims_nothing_without_content():
    """R = T everywhere (flat, equal): the pane changes nothing in the solved layers, whose gradients are only spike
    noise, independent across time parts: neither the model nor n is claimed.
    """
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.content_glass import content_glass

    I, phi, g, geo = textured_stream(70.0, 30.0, "single", 1.5, R_level=0.6, T_level=0.6, contrast=False)
    r = content_glass(I, phi, geo["theta"], geo["phi_perp"], g, ("single", "thin_slab"), CalibratePaneConfig())
    assert r["ok"]
    assert r["model"]["identified"] is False and r["n"]["identified"] is False, (r["model"], r["n"])


def test_outputs_pane_toml_reproduces_the_fit_and_maps_exr_has_the_render_channels(tmp_path):
    """pane.toml is a valid scene whose own geometry (generator.scene) gives the fitted theta / phi_perp;
    maps.exr has the channels of a render's maps.exr; report.json and the figures exist; given n / model kept.
    """
    from generator.analytic import MAP_CHANNELS
    from generator.scene import load_scene
    from polinfra.exr import read_exr
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from polspike.pipeline.pane_outputs import write_outputs
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    I, phi, span, geo = pane_stream(50.0, 300.0, n=1.55, model="single", H=48, W=72)
    res = calibrate_frames(I, phi, CalibratePaneConfig(n=1.55, pane_model="single"), span_rad=span)
    rep = write_outputs(tmp_path, res, width=72, height=48)
    for f in ("pane.toml", "maps.exr", "report.json", "convergence.png", "aolp_residual.png", "modulation_depth.png"):
        assert (tmp_path / f).is_file(), f
    assert not list(tmp_path.glob(".*tmp*"))
    ch = read_exr(tmp_path / "maps.exr")
    render_channels = {"theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par"}
    assert render_channels <= set(MAP_CHANNELS) and set(ch) == render_channels
    sc = load_scene(tmp_path / "pane.toml")
    assert sc.pane.model == "single" and sc.pane.index() == pytest.approx(1.55)
    g2 = incidence_geometry(sc.camera_model(), sc.pane_plane())
    assert np.max(np.abs(g2["theta"] - ch["theta"])) < 2e-3  # maps.exr: 2x2 rays per pixel (footprint mean)
    dp = np.abs(np.mod(g2["phi_perp"] - ch["phi_perp"] + np.pi / 2, np.pi) - np.pi / 2)
    assert np.median(dp) < 1e-3
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["identifiability"]["n"]["identified"] is None and doc["identifiability"]["model"]["identified"] is None
    assert doc["params"]["tilt_deg"] == pytest.approx(rep["params"]["tilt_deg"])


def _dat_stream(path, tilt, az, fov=55.0, H=48, W=72, steps=2000, seed=1):
    """A raw .dat: Bernoulli spikes per 50 us step behind a known pane, polarizer at 30 rev/s from phi0 = 20 deg."""
    from reconstruct.pane.camera import camera_for, normal_from_angles
    from spike_sim.vidar_dat import write_dat

    rng = np.random.default_rng(seed)
    cam = camera_for(W, H, fov)
    N = normal_from_angles(math.radians(tilt), math.radians(az), cam)
    geo = incidence_geometry(cam, Plane(cam.position + cam.forward, N))
    co = pane_coefficients(geo["theta"], 1.5, model="single")
    T = 0.25 + 0.15 * _field(np.random.default_rng(5), H, W, (0, 0))
    R = 0.9 + 0.4 * _field(np.random.default_rng(6), H, W, (0, 0))
    t = (np.arange(steps) + 0.5) / 20000.0
    ph = math.radians(20.0) + 2 * math.pi * 30.0 * t
    sp = np.zeros((steps, H, W), np.uint8)
    for k in range(steps):
        z = co["R_perp"] * np.cos(ph[k] - geo["phi_perp"]) ** 2 + co["R_par"] * np.sin(ph[k] - geo["phi_perp"]) ** 2
        L = 0.5 * (z * R + (1 - z) * T)
        sp[k] = rng.random((H, W)) < np.clip(1.5 * L, 0, 1)  # exposure 1.5 thresholds per unit radiance
    write_dat(path, sp)
    return geo


def test_cli_on_a_raw_dat_and_bad_input(tmp_path):
    from typer.testing import CliRunner

    from polinfra.errors import PolspikeError
    from polspike.cli import get_app

    dat = tmp_path / "rec.dat"
    _dat_stream(dat, 50.0, 80.0)
    app = get_app()
    r = CliRunner().invoke(app, ["calibrate-pane", str(dat), "--height", "48", "--width", "72", "--phi0-deg", "20", "--rev-per-s", "30", "--fov-deg", "55", "--out", str(tmp_path / "cal")])
    assert r.exit_code == 0, r.output
    doc = json.loads((tmp_path / "cal" / "report.json").read_text())
    assert abs(doc["params"]["tilt_deg"] - 50.0) < 1.0 and abs((doc["params"]["azimuth_deg"] - 80.0 + 180) % 360 - 180) < 1.0
    # bad input: one line, exit 2
    for args in (["calibrate-pane", str(dat), "--out", str(tmp_path / "x")],  # .dat without its size / calibration
                 ["calibrate-pane", str(tmp_path / "missing"), "--out", str(tmp_path / "x")],
                 ["calibrate-pane", str(dat), "--height", "48", "--width", "72", "--phi0-deg", "20", "--rev-per-s", "30", "--pane-model", "triple", "--out", str(tmp_path / "x")]):
        r = CliRunner().invoke(app, args)
        assert isinstance(r.exception, PolspikeError), (args, r.output)  # the console script prints it on one line, exit 2


def test_a_dat_shorter_than_half_a_polarizer_turn_says_how_long_it_must_be(tmp_path, polspike_cli):
    """300 steps at 20 kHz are 15 ms; half a turn at 30 rev/s is 16.7 ms (334 steps): exit 2, one line with both
    lengths.  At 60 rev/s half a turn is 167 steps, so the same file is long enough to be read (and refused for
    want of modulation, not length: it is a stream without a polarizer).
    """
    from spike_sim.vidar_dat import write_dat

    dat = tmp_path / "short.dat"
    write_dat(dat, (np.random.default_rng(0).random((300, 16, 24)) < 0.2).astype(np.uint8))
    base = ["calibrate-pane", dat, "--height", 16, "--width", 24, "--phi0-deg", 0, "--out", tmp_path / "x"]
    r = polspike_cli(*base, "--rev-per-s", 30)
    polspike_cli.one_line_exit_2(r, "300 steps", "15.0 ms", "334 steps", "half a polarizer turn")
    r = polspike_cli(*base, "--rev-per-s", 60)
    assert r.returncode != 2 and "half a polarizer turn" not in r.stderr, r.stderr[-800:]


def _fitted_scene(tmp_path, report: dict | None):
    from polspike.pipeline.pane_outputs import fitted_scene_dict, scene_toml_text

    params = {"tilt_deg": 47.0, "azimuth_deg": 110.0, "fov_deg": 52.0, "n": 1.58, "model": "single"}
    d = fitted_scene_dict(params, 80, 50)
    (tmp_path / "pane.toml").write_text(scene_toml_text(d, "test"))
    if report is not None:
        (tmp_path / "report.json").write_text(json.dumps(report))
    return tmp_path / "pane.toml"


def test_a_pane_edge_on_in_part_of_the_view_gets_no_scene_file_but_keeps_its_maps(tmp_path, monkeypatch):
    """Tilt 80 deg seen with a 60 deg fov: rays at the view's edge run parallel to the pane or away from it, which no
    scene file (generator.scene) can hold, whatever the pane's size: fitted_scene_dict says so (SceneError, one
    sentence); write_outputs writes maps.exr and report.json without pane.toml and the report says why.
    """
    from polinfra.errors import SceneError
    from polspike.pipeline.pane_outputs import fitted_scene_dict, write_outputs

    params = {"tilt_deg": 80.0, "azimuth_deg": 20.0, "fov_deg": 60.0, "n": 1.5, "model": "thin_slab"}
    with pytest.raises(SceneError, match="edge-on"):
        fitted_scene_dict(params, 72, 48)
    fitted_scene_dict({**params, "tilt_deg": 40.0}, 72, 48)  # the same view at 40 deg: a scene
    maps = {k: np.full((48, 72), 0.1, np.float64) for k in ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")}
    rep = {"input": "x", "identifiability": {}, "uncertainty_1sigma": {"tilt_deg": 0.1}}
    res = {"ok": True, "report": rep, "params": params, "maps": maps}
    import polspike.pipeline.pane_outputs as po

    monkeypatch.setattr(po, "_figures", lambda out, res: [])  # the figures need a full fit's report
    out = write_outputs(tmp_path / "cal", res, width=72, height=48)
    assert out["pane_toml"]["written"] is False and "edge-on" in out["pane_toml"]["why"]
    assert sorted(p.name for p in (tmp_path / "cal").iterdir()) == ["maps.exr", "report.json"]


def test_dataset_new_like_keeps_the_fitted_geometry_and_glass(tmp_path):
    """--like --jitter none: every group's pane sees the scene's theta / phi_perp maps exactly (the pane is
    relative to the sampled camera); content and pointing still vary.  --jitter fit: tilt spread within
    2 sigma of the report, n fixed where the report says it is not identified.
    """
    import tomllib

    from generator.scene import load_scene, scene_from_dict
    from polspike.pipeline.like import like_manifest_text
    from polspike.pipeline.manifest import parse_manifest

    scene = _fitted_scene(tmp_path, None)
    ref = load_scene(scene)
    g_ref = incidence_geometry(ref.camera_model(), ref.pane_plane())
    m = parse_manifest(tomllib.loads(like_manifest_text(scene, 5, 3, jitter="none")))
    looks, sources = set(), set()
    for g in m.groups:
        sc = scene_from_dict(g.scene)
        geo = incidence_geometry(sc.camera_model(), sc.pane_plane())
        assert np.max(np.abs(geo["theta"] - g_ref["theta"])) < 1e-9
        assert sc.pane.model == "single" and sc.pane.index() == pytest.approx(1.58) and sc.camera.fov_deg == pytest.approx(52.0)
        looks.add(tuple(sc.camera.look_at))
        sources.add(sc.layers.transmission.source + str(sc.layers.transmission.seed))
    assert len(looks) > 1 and len(sources) > 1
    _fitted_scene(tmp_path, {"uncertainty_1sigma": {"tilt_deg": 0.5, "azimuth_deg": 0.3, "fov_deg": 1.0, "n": 0.02},
                             "identifiability": {"n": {"identified": False}}})
    m = parse_manifest(tomllib.loads(like_manifest_text(scene, 12, 4, jitter="fit")))
    tilts = np.array([scene_from_dict(g.scene).pane.tilt_deg for g in m.groups])
    assert np.all(np.abs(tilts - 47.0) <= 1.0 + 1e-9) and tilts.std() > 0.05
    assert all(scene_from_dict(g.scene).pane.index() == pytest.approx(1.58) for g in m.groups)  # n not identified: fixed


@pytest.mark.slow
@pytest.mark.parametrize("tilt,az,model,n", [
    (65.0, 120.0, "single", 1.52),  # was a strict xfail until the geometry weighted blocks by their measured scatter (theta now close enough for the edges)
    (45.0, 200.0, "thin_slab", 1.5),
])
def test_pane_model_from_the_cone_edges_when_layers_go_black(tilt, az, model, n):
    """0.1 s of back-to-back windows (120 x 80) where T and R are each black somewhere: the model, when
    claimed, is the true one; n, when claimed, is within 0.03 (here its 1-sigma exceeds the 0.03 gate,
    so it is not claimed and the prior is kept).
    """
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    I, phi, span, geo = pane_stream(tilt, az, n=n, model=model, H=80, W=120, M=153, stride_deg=360 * 30 * 13 / 20000, exposure=4.0, motion=0.2)
    rep = calibrate_frames(I, phi, CalibratePaneConfig(), span_rad=span)["report"]
    ident = rep["identifiability"]
    assert ident["model"]["identified"] is True and rep["params"]["model"] == model
    if ident["n"]["identified"]:
        assert abs(rep["params"]["n"] - n) <= 0.03
    else:
        assert rep["params"]["n"] == 1.5 or "content test's best guess" in ident["n"]["why"]


def test_nothing_modulates_is_reported_not_fitted(tmp_path):
    """Near-normal incidence: no pane is claimed; report.json says why and nothing else is written."""
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from polspike.pipeline.pane_outputs import write_outputs
    from reconstruct.pane.calibrate_config import CalibratePaneConfig

    I, phi, span, _ = pane_stream(1.0, 0.0, H=48, W=72)
    res = calibrate_frames(I, phi, CalibratePaneConfig(fov_deg=55.0), span_rad=span)
    assert res["ok"] is False and res["report"]["reason"]
    write_outputs(tmp_path, res, width=72, height=48)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    assert json.loads((tmp_path / "report.json").read_text())["ok"] is False


@pytest.mark.slow
def test_the_90_deg_twin_is_told_apart_by_the_modulation_depth():
    """Glancing pane, narrow view (tilt 72, fov 20 deg): modulo 90 deg the orientation field is explained
    almost as well by a second pane whose s-directions run along the true one's p-directions.  find_twin
    finds that pane (its phi_perp field is turned: weighted mean cos 2 delta < 0, and it explains the
    orientation field nearly as well), and the modulation depths, which reach the true cone's edges
    (layers go black), violate the twin's cone [-DoP_T, DoP_R] by far more chi^2 than the true pane's.
    """
    from generator.pane_fit import PaneModelAD
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.edges import _cone_violation
    from reconstruct.pane.geometry_fit import find_twin, fit_geometry
    from reconstruct.pane.orientation import orientation_field

    tilt, az, fov, H, W = 72.0, 30.0, 20.0, 48, 72
    I, phi, span, geo = pane_stream(tilt, az, fov_deg=fov, H=H, W=W, M=120, stride_deg=360 * 30 * 13 / 20000, exposure=4.0, motion=0.2)
    block = 4
    of = orientation_field(I, phi, block)
    x_true = np.array([math.radians(tilt), math.radians(az), math.radians(fov), 1.5])
    g_true = fit_geometry(of, W, H, block, x_true, fit_fov=False, pane_model=PaneModelAD)
    tw = find_twin(of, W, H, block, g_true.x, fit_fov=False, pane_model=PaneModelAD)
    assert tw is not None
    pm = PaneModelAD(W, H, "single", block=block)
    w = np.abs(of.s4)
    assert np.sum(w * np.cos(2 * (pm.maps(tw.x)["phi_perp"] - pm.maps(g_true.x)["phi_perp"]))) < 0
    assert tw.score < 1.5 * g_true.score + 1.0  # nearly as good an explanation of the orientation field
    gain = math.sin(span) / span
    v_true = _cone_violation(I, phi, g_true.x, W, H, block, gain, ("single", "thin_slab"), None, CalibratePaneConfig(), pane_model=PaneModelAD)[0]
    v_twin = _cone_violation(I, phi, tw.x, W, H, block, gain, ("single", "thin_slab"), None, CalibratePaneConfig(), pane_model=PaneModelAD)[0]
    assert v_twin - v_true >= CalibratePaneConfig().twin_delta_chi2, (v_true, v_twin)


def test_unknown_geometry_weighting_is_refused():
    from generator.pane_fit import PaneModelAD
    from polinfra.errors import ConfigError
    from reconstruct.pane.geometry_fit import fit_geometry
    from reconstruct.pane.orientation import OrientationField

    of = OrientationField(s4=np.ones((4, 4), complex), q=np.ones((4, 4)), psi=np.zeros((4, 4)), s4_px=np.ones((16, 16), complex), q_px=np.ones((16, 16)))
    with pytest.raises(ConfigError, match="weighting"):
        fit_geometry(of, 16, 16, 4, np.array([0.5, 0.0, 1.0, 1.5]), fit_fov=False, weighting="bogus", pane_model=PaneModelAD)


def test_block_orientation_variance_matches_the_monte_carlo_spread_of_psi():
    """The scatter of a block's pixel sums perpendicular to its direction gives the noise variance of psi_b = arg(s4_b) / 4
    (oracle: the spread of psi_b over independent noise draws); q / (32 |s4|^2), the pure-noise scale, overstates it
    where the block modulates.  A block whose signal sits in one pixel has an effective pixel count of 1.
    """
    from reconstruct.pane.orientation import block_orientation_variance

    rng = np.random.default_rng(5)
    b, hb, wb, sig = 4, 3, 5, 0.4
    psi0 = rng.uniform(0, np.pi / 2, (hb, wb))
    amp = rng.uniform(1.0, 3.0, (hb * b, wb * b))  # the modulation's strength varies from pixel to pixel (content)
    clean = amp * np.exp(4j * np.kron(psi0, np.ones((b, b))))
    draws, v_est = [], []
    for _ in range(400):
        sp = clean + sig * (rng.standard_normal(clean.shape) + 1j * rng.standard_normal(clean.shape))
        s4 = sp.reshape(hb, b, wb, b).sum(axis=(1, 3))
        v, n_eff = block_orientation_variance(s4, sp, b)
        draws.append(np.mod(np.angle(s4) / 4 - psi0 + np.pi / 4, np.pi / 2) - np.pi / 4)
        v_est.append(v)
    v_mc = np.var(np.array(draws), axis=0)
    ratio = np.mean(np.array(v_est), axis=0) / v_mc
    assert np.all(np.abs(ratio - 1) < 0.25), ratio  # 400 draws: the MC variance itself is good to ~ 7 %
    assert np.all(n_eff > 0.8 * b * b)
    one = np.zeros((b, b), complex)
    one[1, 2] = 5.0
    v1, n1 = block_orientation_variance(one.sum()[None, None], one, b)
    assert n1[0, 0] == pytest.approx(1.0)


def test_bench_measures_the_span_knob_through_the_console_script(tmp_path):
    """``polspike bench calibrate-pane --spans``, run as a person runs it: per span a fit of the same closed-form pane
    (frames = span x 20 kHz / 13 steps), its seconds as a ratio to the self-calibration measured in the same run,
    and its errors against the closed-form truth (phi_perp within the goal; theta within 4 of its own 1-sigma).
    A malformed --spans is one line on stderr, exit 2, no traceback.
    """
    import subprocess
    import sys
    from pathlib import Path

    exe = str(Path(sys.executable).with_name("polspike"))
    if not Path(exe).exists():
        pytest.fail("the console script 'polspike' is not installed next to this interpreter (pip install -e .)")
    out = tmp_path / "bench"
    r = subprocess.run([exe, "bench", "calibrate-pane", "--width", "96", "--height", "64", "--span-s", "0.05", "--spans", "0.05,0.1", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    doc = json.loads((out / "bench_calibrate_pane.json").read_text())
    ref = doc["rows"][0]["s"]
    assert doc["rows"][0]["ratio"] == 1.0 and doc["rows"][-1]["ratio"] == pytest.approx(doc["total_s"] / ref)
    sw = doc["span_sweep"]
    assert [w["span_s"] for w in sw] == [0.05, 0.1] and [w["frames"] for w in sw] == [int(s * 20000) // 13 for s in (0.05, 0.1)]
    for w in sw:
        assert w["ok"] and w["ratio"] == pytest.approx(w["s"] / ref)
        assert w["phi_perp_err_deg_median"] <= 0.5
        assert w["theta_err_deg_median"] <= 4 * w["theta_sigma_deg_median"] + 0.05
    assert "span knob" in r.stdout
    bad = subprocess.run([exe, "bench", "calibrate-pane", "--spans", "0.1,x", "--out", str(tmp_path / "b2")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--spans" in bad.stderr and "Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1


def test_a_narrowly_chosen_twin_is_overturned_by_the_cone_along_the_other_familys_fov_valley(monkeypatch):
    """Glancing narrow view (tilt 72, fov 20 deg) with layers that go black (the cone's edges are reached).  The
    self-calibration is made to hand over the 90 deg twin, chosen narrowly (twin ratio 0.97), as eval_paper_val
    train_004's did: calibrate-pane profiles the other family along the fov, finds the point whose cone the
    modulation depths fit (the true pane: phi_perp within the goal, theta within 1 deg), takes it, and reports its
    fov as NOT identified (it comes from the profile).  Left alone (the self-calibration's own, right choice), the
    same check keeps the chosen pane.
    """
    import dataclasses

    import reconstruct.pane.selfcal as sc
    from generator.pane_fit import PaneModelAD
    from polspike.pipeline.calibrate_pane import calibrate_frames
    from reconstruct.pane.calibrate_config import CalibratePaneConfig
    from reconstruct.pane.geometry_fit import find_twin
    from reconstruct.pane.orientation import orientation_field

    tilt, az, fov, H, W = 72.0, 30.0, 20.0, 48, 72
    I, phi, span, geo = pane_stream(tilt, az, fov_deg=fov, H=H, W=W, M=120, stride_deg=360 * 30 * 13 / 20000, exposure=4.0, motion=0.2)
    right = calibrate_frames(I, phi, CalibratePaneConfig(), span_rad=span)
    assert right["ok"] and _errors(right, geo)[1] <= 0.5
    assert right["report"].get("twin", {}).get("chosen", "best") == "best"
    tw = find_twin(orientation_field(I, phi, 4), W, H, 4, np.array([math.radians(tilt), math.radians(az), math.radians(fov), 1.5]), fit_fov=True, pane_model=PaneModelAD)
    real = sc.self_calibrate

    def handing_over_the_twin(*a, **kw):
        r = real(*a, **kw)
        return dataclasses.replace(r, ok=True, reason="", tilt_deg=math.degrees(tw.x[0]), azimuth_deg=math.degrees(tw.x[1]), fov_deg=math.degrees(tw.x[2]), twin_ratio=0.97)

    monkeypatch.setattr(sc, "self_calibrate", handing_over_the_twin)
    res = calibrate_frames(I, phi, CalibratePaneConfig(), span_rad=span)
    assert res["ok"], res["report"].get("reason")
    rep = res["report"]
    assert rep["twin"]["chosen"] == "twin", rep["twin"]["why"]
    th, ph = _errors(res, geo)
    assert ph <= 0.5 and th <= 1.0, (th, ph)
    fv = rep["identifiability"]["fov"]
    assert fv["identified"] is False and "twin" in fv["why"] and rep["geometry"]["fov_kept"]["by"] == "twin_profile"


def test_content_parts_follow_the_span_in_half_turns():
    """The content test's time parts (content_parts = 0): one per 3 half turns of the polarizer (0.05 s at 30 rev/s),
    at least 2, so 0.1 s of back-to-back 13-step windows gives 2 parts and 0.2 s gives 4; a given count is kept.
    """
    from reconstruct.pane.content_glass import content_parts_for

    step = 2 * math.pi * 30.0 * 13 / 20000.0  # polarizer sweep per window
    for span_s, want in ((0.05, 2), (0.1, 2), (0.2, 4), (0.4, 8)):
        M = int(span_s * 20000) // 13
        assert content_parts_for(0.3 + step * np.arange(M), M) == want, span_s
    assert content_parts_for(0.3 + step * np.arange(300), 300, parts=3) == 3


def test_orientation_field_and_geometry_fit_are_frozen_records_that_carry_what_the_callers_read():
    """orientation_field and fit_geometry return frozen records (no caller can change a fit in place); the geometry
    fit of a known pane's stream lands on it and carries the uncertainty the report prints.
    """
    from generator.pane_fit import PaneModelAD
    from reconstruct.pane.geometry_fit import GeometryFit, fit_geometry
    from reconstruct.pane.orientation import OrientationField, orientation_field

    tilt, az, fov = 50.0, 30.0, 55.0
    I, phi, span, geo = pane_stream(tilt, az, fov_deg=fov)
    of = orientation_field(I, phi, 4)
    assert isinstance(of, OrientationField) and of.blocks == (16, 24) and of.s4_px.shape == (64, 96)
    assert np.allclose(np.mod(np.angle(of.s4) / 4, np.pi / 2), of.psi) and np.all((0 <= of.coherence) & (of.coherence <= 1))
    with pytest.raises(dataclasses.FrozenInstanceError):
        of.psi = of.psi + 1.0
    g = fit_geometry(of, 96, 64, 4, np.r_[np.radians([tilt + 5.0, az - 5.0, fov]), 1.5], fit_fov=False, pane_model=PaneModelAD)
    assert isinstance(g, GeometryFit) and g.wrt == (0, 1) and g.mask.shape == of.blocks
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.x = g.x * 0
    assert abs(math.degrees(g.x[0]) - tilt) < 0.5 and abs(math.degrees(g.x[1]) - az) < 0.5
    assert 0 < g.sigma_theta_deg_median <= g.sigma_theta_deg_max and g.sigma[2] == 0.0
