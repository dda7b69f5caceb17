"""--zeta self: the pane geometry recovered from the stream (normal / vanishing point, theta, zeta) against
the truth of closed-form groups built independently (tests/recon/_pane_groups.py: polphysics geometry,
Fresnel, paper Eq. (1)-(2), Poisson spike counts), at several tilts and axes; the 90 deg flip where R < T;
'nothing modulates' flagged and logged at normal incidence; solver PSNR with self vs true zeta.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest

from reconstruct.pane.selfcal import SelfCalConfig, group_self_zeta, self_calibrate, self_zeta

from ._pane_groups import make_pane_group

SMALL = {"H": 64, "W": 96, "M": 34}


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(np.dot(a, b)) / (np.linalg.norm(a) * np.linalg.norm(b))))))


def _wrap180_deg(a):
    return np.degrees(np.abs(np.mod(a + np.pi / 2, np.pi) - np.pi / 2))


def test_exact_geometry_without_noise_or_motion():
    # the estimator's fixed point is the truth: normal and (fitted) field of view exact on clean data
    g, N = make_pane_group(60.0, 200.0, fov_deg=40.0, r_gain=4.0, noise=False, motion_px=0.0, record_fov=False, **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig())
    assert r.ok and r.fov_fitted
    assert _angle_deg(r.normal, N) < 0.1
    assert abs(r.fov_deg - 40.0) < 0.5
    assert float(np.abs(r.theta - g.theta).max()) < math.radians(0.2)


@pytest.mark.parametrize("tilt, azimuth", [(40.0, 20.0), (55.0, 140.0), (72.0, 250.0)])
def test_recovers_pane_normal_theta_and_zeta_with_noise(tilt, azimuth):
    # Poisson spike counts (about 13 spikes per frame where T is mean-bright) and sliding layers
    g, N = make_pane_group(tilt, azimuth, r_gain=4.0, exposure=3.0, seed=int(tilt), **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, model="single"))  # geometry; the model choice is tested below
    assert r.ok, r.reason
    assert _angle_deg(r.normal, N) < 4.0
    assert abs(r.tilt_deg - tilt) < 4.0
    # vanishing point of the normal: where the truth's lies, within 3 deg of viewing angle
    from polphysics.geometry import PinholeCamera

    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], g.fov_deg, SMALL["W"], SMALL["H"])
    vx, vy = cam.project(N)
    f = cam.focal_px
    ray = lambda x, y: np.array([x - SMALL["W"] / 2, y - SMALL["H"] / 2, f])  # noqa: E731
    assert _angle_deg(ray(*r.vp_px), ray(vx, vy)) < 4.0
    assert float(np.degrees(np.abs(r.theta - g.theta)).mean()) < 3.0
    assert float(np.median(_wrap180_deg(r.maps.phi_perp - g.maps.phi_perp))) < 2.0
    z = self_zeta(r, g.phi_true, g.span_rad)
    assert z.shape == g.gt_zeta.shape
    # zeta within 12 % (mean abs). On the (40, 20) pane of this 96 x 64 group (34 frames, 2 px blocks) the tilt is weakly
    # pinned: theta 2.5 deg / zeta 10.2 % off with the scatter-weighted polish (the default, which takes
    # theta from 0.33-6.7 to 0.05-0.31 deg on eval_paper), 2.0 deg / 9 % with |sum z4| weights alone
    assert float(np.abs(z - g.gt_zeta).mean()) < 0.12 * float(g.gt_zeta.mean())


def test_flip_where_reflection_is_darker_than_transmission():
    # R << T everywhere: the stream's AoLP is phi_perp + 90 deg (RECONSTRUCTION_NOTES section 2); mod-90 fit still finds N
    g, N = make_pane_group(55.0, 60.0, r_gain=0.05, t_level=1.5, seed=3, **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg))
    assert r.ok, r.reason
    # the raw orientation field: 4 AoLP = 4 (phi_perp + 90 deg) = 4 phi_perp, so equal mod 90 at the coherent blocks
    assert _angle_deg(r.normal, N) < 6.0


def test_field_of_view_fitted_when_not_given():
    g, N = make_pane_group(60.0, 200.0, fov_deg=80.0, r_gain=4.0, exposure=3.0, seed=5, record_fov=False, **SMALL)
    assert g.fov_deg is None
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig())
    assert r.ok and r.fov_fitted
    assert abs(r.fov_deg - 80.0) < 5.0
    assert _angle_deg(r.normal, N) < 3.0


def test_normal_incidence_says_nothing_modulates_and_falls_back(caplog):
    g, _ = make_pane_group(0.0, 0.0, r_gain=4.0, seed=1, **SMALL)
    with caplog.at_level(logging.WARNING, logger="reconstruct.pane.selfcal"):
        z = group_self_zeta(g)
    assert z is None
    r = group_self_zeta.last
    assert not r.ok and r.maps is None and "nothing modulates" in r.reason
    assert any("no self-calibrated zeta" in m for m in caplog.messages)
    from polinfra.errors import PolspikeError

    with pytest.raises(PolspikeError):
        self_zeta(r, g.phi_nominal)


def test_solvers_with_self_zeta_within_1db_of_true_zeta():
    import torch

    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups

    torch.manual_seed(0)
    g, _ = make_pane_group(55.0, 300.0, r_gain=5.0, seed=7, **SMALL)
    psnr = {}
    for src in ("gt", "self"):
        rep = evaluate_groups([g], EvalConfig(zeta=src, methods="ls,ridge,rwps", max_frames=3, figure_frames=0, rir=False))
        psnr[src] = {r["method"]: r["psnr_T"] for r in rep.rows if r["group"] == "overall"}
    for m in ("ls", "ridge", "rwps"):
        assert psnr["self"][m] > psnr["gt"][m] - 1.0, (m, psnr)


def _family_and_theta_err(r, g):
    return float(np.median(_wrap180_deg(r.maps.phi_perp - g.maps.phi_perp))), float(np.degrees(np.abs(r.theta - g.theta)).mean())


def test_narrow_view_glancing_pane_resolved_by_the_dop_cone():
    # 18 deg field of view, pane at 74 deg: the orientation field is nearly uniform and, modulo 90 deg, the pane turned by
    # 90 deg fits as well (twin ratio > 0.98).  Where the reflection dominates, the DoP exceeds what the transmission can
    # carry (DoP_T(theta)) along phi_perp, which the twin family's cone cannot hold: the cone picks the right family.
    g, N = make_pane_group(74.0, 30.0, fov_deg=18.0, r_gain=4.0, t_level=0.3, seed=74, **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, valley_step_deg=4.0))  # coarser candidate tilts: cheaper
    assert r.twin_ratio > 0.98  # the orientation field alone is ambiguous
    assert r.ok, r.reason
    cone = r.diagnostics["cone"]
    assert cone["v_family"][1 - cone["chosen_family"]] - cone["v_family"][cone["chosen_family"]] > SelfCalConfig().cone_margin
    pp_err, th_err = _family_and_theta_err(r, g)
    assert pp_err < 5.0  # the right family (the wrong one is 90 deg off)
    assert th_err < 6.0
    # the same pane in a 60 deg view is resolved by the orientation field itself (no cone needed)
    g, N = make_pane_group(74.0, 30.0, fov_deg=60.0, r_gain=4.0, exposure=3.0, seed=74, **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg))
    assert r.ok and r.twin_ratio < 0.98 and "cone" not in r.diagnostics and _angle_deg(r.normal, N) < 4.0


def _narrow_choice_group():
    # fov withheld, 35.6 deg view of a 62 deg pane: the orientation field prefers the right family only narrowly (twin
    # ratio 0.969, inside [twin_check_ratio, max_twin_ratio])
    return make_pane_group(62.2, 348.3, fov_deg=35.6, r_gain=0.81, t_level=1.0, exposure=3.0, motion_px=0.0, seed=303, record_fov=False, **SMALL)


def test_a_narrow_choice_with_the_fov_fitted_is_checked_and_kept_when_the_votes_do_not_both_favour_the_twin():
    g, _ = _narrow_choice_group()
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig())
    cfg = SelfCalConfig()
    assert r.ok and cfg.twin_check_ratio <= r.twin_ratio <= cfg.max_twin_ratio
    tc = r.diagnostics["twin_check"]
    assert not tc["overturned"] and "cone" not in r.diagnostics
    assert _family_and_theta_err(r, g)[0] < 3.0  # the right family (measured 1.0 deg)
    off = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(twin_check_ratio=1.0))  # the check off: the same pane, bit for bit
    np.testing.assert_array_equal(off.maps.phi_perp, r.maps.phi_perp)
    assert "twin_check" not in off.diagnostics
    given = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=35.6))  # a given fov pins the twin family: no check
    assert "twin_check" not in given.diagnostics


def test_the_twin_is_taken_only_where_the_cone_and_the_content_both_prefer_it(monkeypatch):
    # the decision rule, on the real check's output with the two families' labels swapped (so the "twin" is the right pane):
    # both votes swapped -> overturned, to the check's pick; one vote swapped -> kept
    import copy

    import reconstruct.pane.selfcal as sc

    g, _ = _narrow_choice_group()
    real, cache = sc._resolve_by_cone, []
    for swap_cone, swap_content, want in ((True, True, True), (True, False, False), (False, True, False)):
        def fake(*a, **k):
            if not cache:
                cache.append(real(*a, **k))  # the same stream each time: the check runs once
            out = copy.deepcopy(cache[0])
            out["v_family"] = [9.0 + 2 * sc.SelfCalConfig().cone_margin, 0.0] if swap_cone else [0.0, 9.0 + 2 * sc.SelfCalConfig().cone_margin]
            ct = dict(out.get("content") or {})
            ct["corr_family"] = [0.6, 0.1] if swap_content else [0.1, 0.6]
            out["content"] = ct
            return out

        monkeypatch.setattr(sc, "_resolve_by_cone", fake)
        r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(geometry_weighting="s4"))  # s4: no polish after the decision
        assert r.ok and r.diagnostics["twin_check"]["overturned"] is want
        if want:
            assert r.diagnostics["cone"]["by"] == "twin_check" and abs(r.tilt_deg - math.degrees(r.diagnostics["cone"]["tilt"])) < 1e-9
        else:
            assert "cone" not in r.diagnostics


def _t_dominated_narrow_glancing(azimuth=120.0, contrast=1.0):
    # the transmission dominates everywhere (R/T 0.3, no dark T): the DoP stays inside both families' cones (the cone cannot
    # refute the 90 deg twin; the previous version refused these)
    return make_pane_group(74.0, azimuth, fov_deg=18.0, r_gain=0.3, t_level=1.0, exposure=10.0, motion_px=0.0, seed=7, contrast=contrast, **SMALL)


def test_valley_candidates_whose_fov_ran_into_its_bounds_are_left_out():
    # fov free, narrow glancing view: along the tilt valley the fitted fov runs into the 5 deg bound for some tilts
    # (degenerate views, not fitted values); drop_fov_bounds leaves exactly those out, and a given fov is never dropped
    from reconstruct.pane.camera import FOV_BOUNDS_DEG
    from reconstruct.pane.normal import fit_normal, valley_candidates
    from reconstruct.pane.orientation import orientation_field

    g, _ = _t_dominated_narrow_glancing()
    f = orientation_field(g.I, g.phi_nominal, 2)
    h, w = f.psi.shape
    fit = fit_normal(f.s4, f.q, w, h, None)
    seeds = [(fit["tilt"], fit["azimuth"], fit["fov_deg"])] + ([(fit["twin_tilt"], fit["twin_azimuth"], fit["twin_fov_deg"])] if "twin_tilt" in fit else [])
    key = lambda c: (c["family"], round(c["tilt"], 6))  # noqa: E731
    every = valley_candidates(f.s4, w, h, seeds, None, tilt_step_deg=4.0)
    kept = valley_candidates(f.s4, w, h, seeds, None, tilt_step_deg=4.0, drop_fov_bounds=True)
    at_bound = [c for c in every if not FOV_BOUNDS_DEG[0] + 0.05 < c["fov_deg"] < FOV_BOUNDS_DEG[1] - 0.05]
    assert at_bound and len(kept) == len(every) - len(at_bound)
    assert {key(c) for c in kept} == {key(c) for c in every} - {key(c) for c in at_bound}
    given = valley_candidates(f.s4, w, h, seeds[:1], 5.0, tilt_step_deg=8.0, drop_fov_bounds=True)  # a given fov is the lens: kept
    assert given and all(c["fov_deg"] == 5.0 for c in given)
    # a uniform field (an orthographic view's): every candidate of both families sits on the 5 deg bound; dropping them
    # would leave a family empty, to lose by default, so nothing is dropped and the ambiguity stands
    uni = np.full((8, 12), 50.0 * np.exp(4j * 0.4))
    fu = fit_normal(uni, np.full(uni.shape, 50.0), 12, 8, None)
    su = [(fu["tilt"], fu["azimuth"], fu["fov_deg"]), (fu["twin_tilt"], fu["twin_azimuth"], fu["twin_fov_deg"])]
    every = valley_candidates(uni, 12, 8, su, None, tilt_step_deg=4.0)
    assert {c["family"] for c in every} == {0, 1} and all(c["fov_deg"] < FOV_BOUNDS_DEG[0] + 0.05 for c in every)
    assert len(valley_candidates(uni, 12, 8, su, None, tilt_step_deg=4.0, drop_fov_bounds=True)) == len(every)


def test_twin_the_cone_cannot_refute_is_told_apart_by_the_layers_content():
    # under the twin the solved R' carries the transmission's texture (R' ~ T + (T - R)): R^ and T^ gradients correlate;
    # under the true pane they are the two independent layers.  Checked against the known truth, not the estimator's own fit.
    g, _ = _t_dominated_narrow_glancing()
    cfg = SelfCalConfig(fov_deg=g.fov_deg, valley_step_deg=4.0)
    r = self_calibrate(g.I, g.phi_nominal, cfg)
    assert r.diagnostics["modulating_blocks"] > 0.5  # it does modulate (4 x 4 blocks above noise)
    assert r.twin_ratio > 0.98  # the orientation field alone is ambiguous
    assert r.ok, r.reason
    cone = r.diagnostics["cone"]
    assert cone["by"] == "content"  # the cone alone did not decide
    ct = cone["content"]
    chosen, other = ct["corr_family"][cone["chosen_family"]], ct["corr_family"][1 - cone["chosen_family"]]
    assert other - chosen > cfg.content_margin and other >= cfg.content_ratio * chosen
    pp_err, th_err = _family_and_theta_err(r, g)
    assert pp_err < 3.0  # the true family (the twin's phi_perp is 90 deg off)
    assert th_err < 3.0
    assert r.model == "single"  # the group's pane: the content also tells the model's scale (T leaks into R^ otherwise)


def test_flat_layers_keep_the_twin_refused():
    # the same pane with featureless layers: no texture tells R from T under either family, so it still refuses
    g, _ = _t_dominated_narrow_glancing(contrast=0.0)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, valley_step_deg=4.0))
    assert not r.ok and "ambiguous" in r.reason and "cone" in r.reason and "content" in r.reason
    ct = r.diagnostics["cone"]["content"]
    assert abs(ct["corr_family"][0] - ct["corr_family"][1]) < SelfCalConfig().content_margin


@pytest.mark.slow
def test_cone_and_content_disagreeing_is_refused():
    # R nearly black (R/T 0.08): the right family sits on the cone's -DoP_T edge, and noise there can push it out by a
    # little more than the twin (violations 9.8 / 0.5: the cone alone picks the twin, checked against the truth below);
    # the layers' content picks the right family clearly (0.17 / 0.77).  Neither is trusted over the other: refused.
    # (Group 10 of `docs/selfcal_report.py twin-heldout`, held still.)
    g, _ = make_pane_group(75.45894911989473, 207.78390161863172, fov_deg=19.16270642992466, r_gain=0.15081105912306855, t_level=1.0,
                           exposure=3.0, motion_px=0.0, model="thin_slab", seed=110, **SMALL)
    cfg = SelfCalConfig(fov_deg=g.fov_deg, valley_step_deg=4.0)
    cone_only = self_calibrate(g.I, g.phi_nominal, dataclasses.replace(cfg, content_margin=0.0))
    assert cone_only.ok and _family_and_theta_err(cone_only, g)[0] > 80.0  # the cone alone: the twin (90 deg off)
    r = self_calibrate(g.I, g.phi_nominal, cfg)
    assert not r.ok and "pick different families" in r.reason
    assert r.diagnostics["cone"]["conflict"]


def test_layer_gradient_correlation_is_small_for_the_true_pane_and_large_for_its_twin():
    # oracle: the group's true maps (and the same pane with phi_perp turned 90 deg), clean data, T dominant
    from reconstruct.pane.content import _content_parts, layer_gradient_correlation

    g, _ = make_pane_group(60.0, 30.0, r_gain=0.4, t_level=1.0, noise=False, motion_px=0.0, seed=11)  # 160 x 100: textures' chance correlation ~0.1
    halves = _content_parts(g.I, g.phi_nominal)
    sf = math.sin(g.span_rad) / g.span_rad
    true = layer_gradient_correlation(halves, g.maps.phi_perp, g.theta, 1.5, "single", sf)
    twin = layer_gradient_correlation(halves, g.maps.phi_perp + np.pi / 2, g.theta, 1.5, "single", sf)
    slab = layer_gradient_correlation(halves, g.maps.phi_perp, g.theta, 1.5, "thin_slab", sf)  # the right geometry, the wrong scale
    assert true["rms"] < 0.2 and abs(true["corr"]) < 0.1  # independent textures: chance correlation only
    assert twin["corr"] > 0.7 and twin["rms"] > 0.7
    assert slab["rms"] > true["rms"] + 0.3  # T leaks into R^ by (1 - B / B') T


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_cone_bounds_are_the_dop_of_either_layer_alone(model):
    # oracle: paper Eq. (1)-(2) with one layer black, fitted by the harmonic fit, gives m / a0 = DoP_R (T = 0) and
    # -DoP_T (R = 0) along phi_perp: exactly the cone's edges at that theta
    from polphysics.fresnel import pane_coefficients
    from reconstruct.pane.cone import chunk_harmonics, cone_bounds

    theta = np.deg2rad(np.array([[20.0, 45.0, 56.3, 70.0, 80.0]]))
    co = pane_coefficients(theta, 1.5, model=model)
    phi_perp = np.deg2rad(np.array([[10.0, 40.0, 80.0, 120.0, 170.0]]))
    phi = np.deg2rad(np.arange(0.0, 180.0, 7.0))
    zeta = co["R_perp"] * np.cos(phi[:, None, None] - phi_perp) ** 2 + co["R_par"] * np.sin(phi[:, None, None] - phi_perp) ** 2  # paper Eq. (2)
    lo, hi = cone_bounds(theta, 1.5, model)
    for R, T, edge in ((1.0, 0.0, hi), (0.0, 1.0, lo)):
        I = 0.5 * (zeta * R + (1.0 - zeta) * T)  # paper Eq. (1)
        a0, c = chunk_harmonics(I, phi)
        rho = np.real(c[0] * np.exp(-2j * phi_perp)) / a0[0]
        np.testing.assert_allclose(rho, edge, atol=2e-3)



@pytest.mark.slow
def test_the_near_black_reflection_is_never_given_the_wrong_family_over_five_noise_draws():
    """The group of the test above under five noise draws (seeds 110-114): the calibration refuses or picks the true
    family (phi_perp within 3 deg), never the twin.  The cone alone picking the twin is one draw's event, not a
    property: measured, the cone alone took the twin at seed 110 only (89.2 deg off) and refused at 111-114, while
    the calibration refused at 110, 112, 113 and was right at 111 and 114 (0.2 deg).  Run with content_margin = 0
    (the cone alone) this test fails at seed 110.
    """
    wrong = []
    for seed in range(110, 115):
        g, _ = make_pane_group(75.45894911989473, 207.78390161863172, fov_deg=19.16270642992466, r_gain=0.15081105912306855, t_level=1.0,
                               exposure=3.0, motion_px=0.0, model="thin_slab", seed=seed, **SMALL)
        r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, valley_step_deg=4.0))
        if r.ok and abs(_family_and_theta_err(r, g)[0]) > 3.0:
            wrong.append((seed, round(_family_and_theta_err(r, g)[0], 1)))
    assert not wrong, f"calibrations that took the wrong family (seed, phi_perp error deg): {wrong}"

def test_cone_violation_tells_the_pane_from_its_90_deg_flip():
    # a steep pane, the reflection dominating (static layers, bright): the true phi_perp keeps every aggregate in the
    # cone; the same field turned by 90 deg puts the strong modulation on the T side, beyond DoP_T
    from reconstruct.pane.cone import chunk_harmonics, cone_aggregates, cone_violation

    g, _ = make_pane_group(60.0, 200.0, r_gain=4.0, t_level=0.3, exposure=3.0, motion_px=0.0, seed=5, **SMALL)
    a0, c = chunk_harmonics(g.I, g.phi_nominal)
    v_true = cone_violation(cone_aggregates(a0, c, g.maps.phi_perp, g.theta), 1.5, "single")
    v_flip = cone_violation(cone_aggregates(a0, c, g.maps.phi_perp + np.pi / 2, g.theta), 1.5, "single")
    cfg = SelfCalConfig()
    assert v_flip > 100.0 and v_flip - v_true > cfg.cone_margin and v_flip > cfg.cone_ratio * v_true


def test_fit_glass_claims_a_model_or_an_index_only_with_a_margin():
    from reconstruct.pane.glass import fit_glass

    ns = (1.4, 1.5, 1.6, 1.7)
    # slab violated everywhere, single fits 1.5-1.6 only: model and index claimed
    sc = {("single", n): {1.4: 50.0, 1.5: 0.0, 1.6: 2.0, 1.7: 40.0}[n] for n in ns} | {("thin_slab", n): 80.0 for n in ns}
    f = fit_glass(sc, 1.5, "thin_slab", 9.0)
    assert f["model"] == "single" and f["model_identified"] and f["n_identified"] and f["n"] == 1.5 and f["n_range"] == [1.5, 1.6]
    # both models hold the data within the margin, every index too: the priors, flagged as not identified
    sc = {(m, n): 0.5 for m in ("single", "thin_slab") for n in ns}
    f = fit_glass(sc, 1.5, "thin_slab", 9.0)
    assert f["model"] == "thin_slab" and not f["model_identified"] and not f["n_identified"] and f["n"] == 1.5
    # an index range that reaches the grid's end is a bound, not a fit: the prior moved into it
    sc = {(m, n): (0.0 if n >= 1.6 else 30.0) for m in ("single", "thin_slab") for n in ns}
    f = fit_glass(sc, 1.5, "thin_slab", 9.0)
    assert not f["n_identified"] and f["n"] == 1.6


def test_pane_model_not_identified_keeps_the_prior_and_says_so():
    # both layers bright everywhere: the DoP never reaches either cone edge, so single and slab both hold the data
    g, _ = make_pane_group(55.0, 140.0, r_gain=2.0, t_level=0.5, exposure=3.0, model="single", seed=12, **SMALL)
    r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, prior_model="thin_slab"))
    assert r.ok, r.reason
    gl = r.diagnostics["glass"]
    assert not gl["model_identified"] and r.model == "thin_slab" and "not identified" in gl["why"]
    # a given model is used as given, without a fit
    r2 = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=g.fov_deg, model="single"))
    assert r2.model == "single" and "glass" not in r2.diagnostics


def test_modulating_fraction_separates_noise_from_a_modulating_pane():
    # the reported share of pixels modulating above noise: near 0 at normal incidence, most pixels behind a steep pane
    g0, _ = make_pane_group(0.0, 0.0, r_gain=4.0, seed=1, **SMALL)
    r0 = self_calibrate(g0.I, g0.phi_nominal, SelfCalConfig(fov_deg=g0.fov_deg))
    g1, _ = make_pane_group(55.0, 300.0, r_gain=4.0, exposure=30.0, motion_px=0.0, seed=7, **SMALL)
    r1 = self_calibrate(g1.I, g1.phi_nominal, SelfCalConfig(fov_deg=g1.fov_deg))
    assert r0.diagnostics["modulating_px"] < 0.03 and r0.diagnostics["modulating_blocks"] < 0.05
    assert r1.diagnostics["modulating_px"] > 0.5
    assert r1.summary()["modulating_px"] == r1.diagnostics["modulating_px"]


def test_evaluate_self_fov_scene_gives_the_groups_fov_and_fitted_withholds_it():
    # EvalConfig.self_fov: scene = the group's recorded fov, as given; fitted = what polspike reconstruct meets on a .dat
    from reconstruct.evaluate.harness import EvalConfig, group_zeta

    g, N = make_pane_group(60.0, 200.0, fov_deg=80.0, r_gain=4.0, exposure=3.0, seed=5, **SMALL)
    assert g.fov_deg == 80.0
    group_zeta(g, EvalConfig(zeta="self"))
    r_scene = group_self_zeta.last
    group_zeta(g, EvalConfig(zeta="self", self_fov="fitted"))
    r_fit = group_self_zeta.last
    assert r_scene.ok and not r_scene.fov_fitted and r_scene.fov_deg == 80.0
    assert r_fit.ok and r_fit.fov_fitted and r_fit.fov_deg != 80.0 and abs(r_fit.fov_deg - 80.0) < 5.0
    assert g.fov_deg == 80.0  # the group itself is left as it was
    assert _angle_deg(r_fit.normal, N) < 3.0


def test_evaluate_self_source_fits_or_takes_the_given_pane_model():
    # polspike evaluate's self source: the cone's glass fit by default (not identified here -> thin slab, said why),
    # a given model with EvalConfig.self_pane_model; the two zetas differ by the slab's larger reflectance
    from reconstruct.evaluate.harness import EvalConfig, group_zeta

    g, _ = make_pane_group(55.0, 140.0, r_gain=2.0, exposure=3.0, seed=12, **SMALL)
    z_auto = group_zeta(g, EvalConfig(zeta="self"))
    r_auto = group_self_zeta.last
    z_single = group_zeta(g, EvalConfig(zeta="self", self_pane_model="single", pane_n=1.5))
    r_single = group_self_zeta.last
    assert r_auto.ok and r_single.ok
    assert r_auto.model == "thin_slab" and "glass" in r_auto.diagnostics
    assert r_single.model == "single" and "glass" not in r_single.diagnostics
    assert float(np.abs(z_single - g.gt_zeta).mean()) < 0.1 * float(g.gt_zeta.mean())  # the group is a single pane
    assert float(z_auto.mean()) > 1.3 * float(z_single.mean())


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_content_tells_the_pane_model_at_a_known_geometry(model):
    # the true geometry given, the pane model unknown: the wrong model's scale leaks T into R^ by (1 - B / B') T, so the
    # layers come out correlated under it; the right one is claimed (single vs thin slab, Poisson spike counts; static
    # layers: motion within a chunk of half a turn blurs the closed-form solve, and at 0.5 px per frame neither is claimed)
    from reconstruct.pane.content import content_model

    g, _ = make_pane_group(50.0, 200.0, r_gain=0.6, t_level=1.0, exposure=3.0, motion_px=0.0, model=model, seed=21)
    cm = content_model(g.I, g.phi_nominal, g.maps.phi_perp, g.theta, 1.5)
    assert cm["identified"] and cm["model"] == model, cm["scores"]


def test_content_claims_no_model_for_flat_layers():
    from reconstruct.pane.content import content_model

    g, _ = make_pane_group(50.0, 200.0, r_gain=0.6, t_level=1.0, exposure=3.0, motion_px=0.0, seed=21, contrast=0.0)
    cm = content_model(g.I, g.phi_nominal, g.maps.phi_perp, g.theta, 1.5)
    assert not cm["identified"] and cm["model"] is None, cm["scores"]


def test_scatter_polish_discounts_blocks_whose_pixels_scatter():
    """polish_geometry on a synthetic block orientation field: the left half of the blocks carries the true pane's
    phi_perp with little pixel scatter, the right half a phi_perp biased by 5 deg with pixels scattering 7x more
    (content moving through the harmonic fit). Their |sum z4| is alike, so a fit weighted by it lands between the
    two (its phi_perp field 2.3 deg off, median over blocks); the scatter weights (each block's orientation
    variance measured from its pixels) bring it within 0.8 deg, and at least 3x closer, from a start 3 deg off.
    """
    from scipy.optimize import least_squares

    from reconstruct.pane.camera import _phi_perp_grid, camera_for, normal_from_angles
    from reconstruct.pane.normal import polish_geometry
    from reconstruct.pane.orientation import OrientationField, block_orientation_variance

    w, h, b, fov = 24, 16, 4, 50.0
    tilt, az = math.radians(50.0), math.radians(30.0)
    cam = camera_for(w, h, fov)
    ppf = lambda t, a: _phi_perp_grid(cam, normal_from_angles(t, a, cam))  # noqa: E731
    pp = ppf(tilt, az)
    rng = np.random.default_rng(0)
    weak = np.zeros((h, w), bool)
    weak[:, w // 2 :] = True
    px_ang = np.kron(np.where(weak, pp + math.radians(5.0), pp), np.ones((b, b)))
    sig = np.kron(np.where(weak, 2.0, 0.3), np.ones((b, b)))
    sp = np.exp(4j * px_ang) + sig * (rng.standard_normal(px_ang.shape) + 1j * rng.standard_normal(px_ang.shape)) / math.sqrt(2)
    s4 = sp.reshape(h, b, w, b).sum(axis=(1, 3))
    of = OrientationField(s4=s4, q=(np.abs(sp) ** 2).reshape(h, b, w, b).sum(axis=(1, 3)), psi=np.angle(s4) / 4, s4_px=sp, q_px=np.abs(sp) ** 2)
    v, _ = block_orientation_variance(s4, sp, b)
    assert np.median(v[weak]) > 20 * np.median(v[~weak])
    pol = polish_geometry(of, b, tilt + math.radians(3.0), az, fov, fit_fov=False)
    e_pol = float(np.median(np.degrees(np.abs(ppf(pol["tilt"], pol["azimuth"]) - pp))))
    sw = np.sqrt(np.abs(s4)).ravel()  # the |sum z4| weighting of the grid search, same residuals
    r = least_squares(lambda x: sw * 0.5 * np.sin(2.0 * (of.psi - ppf(x[0], x[1]))).ravel(), [tilt + math.radians(3.0), az])
    e_s4 = float(np.median(np.degrees(np.abs(ppf(*r.x) - pp))))
    assert e_pol < 0.8 and e_s4 > 3 * e_pol, (e_pol, e_s4)


def test_saturated_pixels_are_left_out_of_the_calibration():
    """A pixel whose window reaches the spike ceiling (one spike per step) in any frame is set to 0 in every frame and
    counted; without an exposure nothing changes.  On a stream clipped at the ceiling over a bright part of the view,
    the calibration given the exposure keeps the unclipped stream's geometry and zeta scale.
    """
    from reconstruct.pane.selfcal import leave_out_saturated
    from reconstruct.physics.span import SPAN_SATURATION

    g, N = make_pane_group(65.0, 200.0, r_gain=4.0, exposure=3.0, seed=7, **SMALL)
    e = 0.9 / float(g.I.max())  # the closed-form counts have no ceiling: a sensor whose brightest pixel fires 0.9 per step
    ceiling = np.float32(1.0 / e)  # one spike per step, in radiance units
    bright = np.zeros(g.I.shape[1:], bool)
    bright[:, : SMALL["W"] // 3] = True
    I = g.I.copy()
    I[:, bright] = np.minimum(I[:, bright] * 8.0, ceiling)  # a bright third of the view, clipped by the sensor
    out, frac = leave_out_saturated(I, e)
    sat = (I * e >= SPAN_SATURATION).any(0)
    assert sat.any() and frac == pytest.approx(float(sat.mean()))
    assert np.all(out[:, sat] == 0) and np.array_equal(out[:, ~sat], I[:, ~sat])
    same, zero = leave_out_saturated(I, None)
    assert same is I and zero == 0.0
    cfg = SelfCalConfig(fov_deg=g.fov_deg, model="single")
    ref = self_calibrate(g.I, g.phi_nominal, cfg, exposure=e)
    r = self_calibrate(I, g.phi_nominal, cfg, exposure=e)
    assert ref.ok and r.ok and r.diagnostics["saturated_px"] == pytest.approx(frac) and ref.diagnostics["saturated_px"] == 0.0
    assert _angle_deg(r.normal, N) < 4.0
    z, z_ref = self_zeta(r, g.phi_true, g.span_rad), self_zeta(ref, g.phi_true, g.span_rad)
    assert abs(float(z.mean()) / float(z_ref.mean()) - 1.0) < 0.05
