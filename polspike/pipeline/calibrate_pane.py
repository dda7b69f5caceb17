"""``polspike calibrate-pane``: fit the pane and the camera's field of view to a recording, and write what was found.

Reads the recording (a group store or a ``.dat``), runs the fit of :mod:`reconstruct.pane.calibrate` with the
differentiable maps tier as its pane model (:class:`generator.pane_fit.PaneModelAD`), and writes maps, scene file,
report and figures (:mod:`polspike.pipeline.pane_outputs`); ``polspike bench calibrate-pane``'s stream and table.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from polinfra.errors import ConfigError
from polspike.pipeline.pane_outputs import _json_safe
from reconstruct.pane.calibrate import calibrate_frames as _calibrate_frames
from reconstruct.pane.calibrate_config import CalibratePaneConfig
from reconstruct.pane.geometry_fit import (
    _wrap90,
)

__all__ = ["calibrate_input"]

log = logging.getLogger(__name__)


def calibrate_frames(I: np.ndarray, phi: np.ndarray, cfg: CalibratePaneConfig = CalibratePaneConfig(), **kw) -> dict:
    """:func:`reconstruct.pane.calibrate.calibrate_frames` on the differentiable maps tier
    (:class:`generator.pane_fit.PaneModelAD`, Dr.Jit forward AD) as its pane model.
    """
    from generator.pane_fit import PaneModelAD

    return _calibrate_frames(I, phi, cfg, pane_model=PaneModelAD, **kw)


def calibrate_input(input: Path, cfg: CalibratePaneConfig, *, height: int | None = None, width: int | None = None, phi0_deg: float | None = None,
                    rev_per_s: float | None = None, rate_hz: float = 20000.0, progress=None) -> tuple[dict, dict | None, int, int]:
    """Load a group store or a raw .dat and run :func:`calibrate_frames`; returns (result, base scene dict, W, H)."""
    from reconstruct.pane.selfcal import leave_out_saturated
    from reconstruct.stream.groups import fov_from_group_dir
    from reconstruct.stream.sources import (
        StreamTooShortError,
        dat_source,
        frames_exposure,
        group_source,
        span_frames,
    )

    base = None
    input = Path(input)
    if input.suffix.lower() == ".dat":
        missing = [n for n, v in (("--height", height), ("--width", width), ("--phi0-deg", phi0_deg), ("--rev-per-s", rev_per_s)) if v is None]
        if missing:
            raise ConfigError(f"a .dat input needs {', '.join(missing)} (frame size and polarizer calibration)")
        src = dat_source(input, height, width, math.radians(phi0_deg), rev_per_s, rate_hz)
    elif input.is_dir() and (input / "spikes.h5").is_file():
        src = group_source(input)
        spec = input / "group_spec.json"
        if spec.is_file():
            try:
                base = json.loads(spec.read_text())["scene"]
            except (ValueError, KeyError):
                base = None
        if cfg.fov_deg <= 0 and fov_from_group_dir(input) is not None:
            log.info("%s records its field of view; calibrate-pane fits it anyway (give --fov-deg to fix it)", input)
    else:
        raise ConfigError(f"input {input} is neither a .dat file nor a spike group directory (GROUP/spikes.h5)")
    have = int(src.phi_step_rad.size)
    half_turn = int(math.ceil(src.rate_hz / (2.0 * src.polarizer_rev_s)))
    if have < half_turn:
        raise StreamTooShortError(
            f"{src.name} holds {have} steps ({1e3 * have / src.rate_hz:.1f} ms at {src.rate_hz / 1e3:g} kHz); calibrate-pane "
            f"needs at least half a polarizer turn, {half_turn} steps ({1e3 * half_turn / src.rate_hz:.1f} ms at "
            f"{src.polarizer_rev_s:g} rev/s): record longer, or check --rev-per-s")
    if have < round(cfg.span_s * src.rate_hz):
        log.warning("%s holds %.3f s, less than the %.3g s span asked for: fitting all of it", src.name, have / src.rate_hz, cfg.span_s)
    ex = frames_exposure(src)
    I, phi = span_frames(src, cfg.span_s, cfg.window_steps, ex)
    I, sat = leave_out_saturated(I, ex)  # clipped pixels would read as a weaker pane
    if sat > 0:
        log.info("%s: %.1f %% of the pixels saturate; left out of the fit", src.name, 100 * sat)
    res = calibrate_frames(I, phi, cfg, span_rad=src.window_span_rad(cfg.window_steps), name=src.name, progress=progress)
    return res, base, src.width, src.height


# --------------------------------------------------------------------------- benchmark
def bench_stream(width: int = 400, height: int = 250, span_s: float = 0.1, tilt_deg: float = 55.0, azimuth_deg: float = 30.0, fov_deg: float = 50.0,
                 n: float = 1.5, model: str = "thin_slab", exposure: float = 2.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float, dict]:
    """A closed-form stream for the benchmark: back-to-back 13-step Eq. (3) windows over ``span_s`` at 20 kHz and
    30 rev/s behind a known pane (polphysics geometry and Fresnel, paper Eq. (1)-(2)), moving smooth layers,
    Poisson counts at ``exposure`` thresholds per unit radiance.  Returns (I, phi, span_rad, truth).
    """
    from polphysics.fresnel import pane_coefficients
    from polphysics.geometry import Plane, incidence_geometry
    from reconstruct.pane.camera import camera_for, normal_from_angles

    rng = np.random.default_rng(seed)
    cam = camera_for(width, height, fov_deg)
    N = normal_from_angles(math.radians(tilt_deg), math.radians(azimuth_deg), cam)
    geo = incidence_geometry(cam, Plane(cam.position + cam.forward, N))
    co = pane_coefficients(geo["theta"], n, model=model)
    steps, rate, rev = 13, 20000.0, 30.0
    M = int(span_s * rate) // steps
    span = 2 * math.pi * rev * steps / rate
    phi = rng.uniform(0, math.pi) + span * (np.arange(M) + 0.5)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    waves = [(rng.uniform(0.01, 0.05) * 2 * math.pi, rng.uniform(0, 2 * math.pi), rng.uniform(0, 2 * math.pi)) for _ in range(12)]

    def layer(i, sh, k0):
        f = sum(np.cos(k * ((x - sh * i) * math.cos(a) + y * math.sin(a)) + p) for k, a, p in waves[k0:k0 + 6]) / 6
        return np.clip(0.5 + 0.8 * f, 0.0, None)

    sinc = math.sin(span) / span
    I = np.empty((M, height, width), np.float32)
    for i in range(M):
        z = 0.5 * (co["R_perp"] + co["R_par"]) + 0.5 * (co["R_perp"] - co["R_par"]) * sinc * np.cos(2 * (phi[i] - geo["phi_perp"]))
        L = 0.5 * (z * 2.0 * layer(i, 0.05, 0) + (1 - z) * layer(i, -0.08, 6))
        I[i] = rng.poisson(L * steps * exposure) / (steps * exposure)
    return I, phi, span, {"tilt_deg": tilt_deg, "azimuth_deg": azimuth_deg, "fov_deg": fov_deg, "n": n, "model": model, "theta": geo["theta"], "phi_perp": geo["phi_perp"]}


def _bench_accuracy(res: dict, truth: dict) -> dict:
    """The bench fit's errors against the closed-form truth, and what it claimed of the glass."""
    if not res["ok"]:
        return {"ok": False, "reason": res["report"].get("reason")}
    rep = res["report"]
    th = np.degrees(np.abs(res["maps"]["theta"] - truth["theta"]))
    dp = np.degrees(np.abs(_wrap90(2 * (res["maps"]["phi_perp"] - truth["phi_perp"])) / 2))
    idn = rep["identifiability"]
    return {"ok": True, "tilt_err_deg": abs(rep["params"]["tilt_deg"] - truth["tilt_deg"]), "fov_err_deg": abs(rep["params"]["fov_deg"] - truth["fov_deg"]),
            "theta_err_deg_median": float(np.median(th)), "phi_perp_err_deg_median": float(np.median(dp)),
            "theta_sigma_deg_median": rep["uncertainty_1sigma"]["theta_deg_median"], "fov_identified": idn["fov"]["identified"],
            "n": rep["params"]["n"], "n_err": abs(rep["params"]["n"] - truth["n"]), "n_identified": bool(idn["n"]["identified"]),
            "model": rep["params"]["model"], "model_right": rep["params"]["model"] == truth["model"], "model_identified": bool(idn["model"]["identified"])}


def run_bench(out: Path, width: int = 400, height: int = 250, span_s: float = 0.1, spans: tuple[float, ...] = ()) -> dict:
    """``polspike bench calibrate-pane``: one full fit (fov, n and model free) of a ``span_s`` stream at
    width x height, stage by stage, beside the self-calibration alone (the reference, same run).  ``spans``: the
    span knob measured as well (speed against accuracy): a fit of the same pane and layers over each span, its
    seconds as a ratio to the reference and its errors against the truth.
    """
    import os

    from polinfra.atomic import write_json
    from reconstruct.pane.selfcal import SelfCalConfig, self_calibrate

    I, phi, span, truth = bench_stream(width, height, span_s)
    t0 = time.perf_counter()
    c0 = time.process_time()
    self_calibrate(I, phi, SelfCalConfig())
    ref = time.perf_counter() - t0
    ref_cpu = time.process_time() - c0
    t0 = time.perf_counter()
    c0 = time.process_time()
    res = calibrate_frames(I, phi, CalibratePaneConfig(span_s=span_s), span_rad=span)
    total = time.perf_counter() - t0
    cpu = time.process_time() - c0
    rep = res["report"]
    tm = rep.get("timings_s", {})
    rows = [{"stage": "self-calibration alone (reference)", "s": ref, "ratio": 1.0}]
    for k in ("selfcal_s", "geometry_s", "twin_s", "glass_s", "content_s", "dop_fov_s", "maps_s"):
        if k in tm:
            rows.append({"stage": k[:-2], "s": tm[k], "ratio": tm[k] / ref})
    rows.append({"stage": "calibrate-pane total", "s": total, "ratio": total / ref})
    acc = _bench_accuracy(res, truth)
    sweep = []
    for s in spans:
        I_s, phi_s, span_s_rad, truth_s = bench_stream(width, height, s)
        t0 = time.perf_counter()
        r_s = calibrate_frames(I_s, phi_s, CalibratePaneConfig(span_s=s), span_rad=span_s_rad)
        sweep.append({"span_s": s, "frames": int(I_s.shape[0]), "s": time.perf_counter() - t0, **_bench_accuracy(r_s, truth_s)})
        sweep[-1]["ratio"] = sweep[-1]["s"] / ref
    doc = {
        "width": width, "height": height, "span_s": span_s, "frames": int(I.shape[0]), "rows": rows, "total_s": total, "cpu_s": cpu, "reference_cpu_s": ref_cpu,
        "goal_s": 120.0, "goal_met": bool(total <= 120.0), "variant": rep.get("variant"),
        "accuracy": acc, "span_sweep": sweep,
        "machine": {"cpus": os.cpu_count(), "load_avg_1min": os.getloadavg()[0]},
        "note": "closed-form stream (polphysics + paper Eq. (1)-(2), Poisson counts); frames are built before timing; speed also as a ratio to the self-calibration in the same run",
    }
    write_json(Path(out) / "bench_calibrate_pane.json", _json_safe(doc))
    return doc
