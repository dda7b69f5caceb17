"""The motion bench: every method on glass-pane streams under camera and layer motion, scored against the true layers.

Streams: :mod:`reconstruct.stream.motion_scenes` (closed form per 20 kHz step, integrate-and-fire pixels).  Cells:
camera pans at :data:`PAN_SPEEDS` view widths per second, a hand-held shake (a random walk of the velocity, 1 view/s
rms), a rotation about the optical axis (60 deg/s), a zoom (scale rate 2 /s: the corners move ~1 view/s) and
independent layer motion (T pans at 1.1 views/s, R holds still); each at weak, strong and dominant reflection
(reflected share 0.1, 0.35, 0.6) and dim (0.02) and bright (0.3 spikes per pixel per step) light.

Methods (:data:`METHODS`), all on the same Eq. (3) windows (13 steps, N = 7, 31.5 deg apart):

* ``tfp``: T = 2 x the mean of the N windows (the plain spike image the stream reports beside T);
* ``mean17``: T = 2 x the plain spike mean over the 17.5 ms span (351 steps) the network reads;
* ``mean``: T = 2 x the spike mean over a motion-adapted span: L = 1 / v steps (1 px of smear), v the fastest
  RIR shift of the N windows per step, clipped to [13, 351] steps;
* ``anchor``: the best physics per pixel (:func:`reconstruct.physics.anchor.physics_anchor`: least squares, the span
  mean or a blend, chosen from the windows' noise statistics), the floor's fallback;
* ``ls``, ``ridge``, ``irls``, ``rwps``: the physics solvers (:data:`reconstruct.physics.solvers.PHYSICS_SOLVER_CONFIG`)
  on the self-calibrated zeta (:func:`reconstruct.pane.source.calibrate_source`; ``calibrate = "still"``, the default:
  on the still stream of the same rig, scene and light, once for every motion, as ``polspike calibrate-pane`` then
  ``--pane`` does; ``"cell"``: on the cell's own moving stream; where it refuses, the true pane maps, and the cell says
  so), RIR on; the networks run on the same zeta;
* ``net``: the shipped checkpoint as trained (RIR off, no floor); ``net+rir``: RIR on; ``net+floor``: RIR on and the
  data-consistency floor as the checkpoint sets it (the data check against the RWPS's residual, falling back per
  pixel to the RWPS and the best closed-form physics weighed by their error powers, ``floor_anchor = "blend"``,
  :mod:`reconstruct.physics.anchor`); ``net+rwpsfloor``: the floor falling back to the RWPS alone
  (``floor_anchor = "rwps"``, :mod:`reconstruct.physics.consistency`), ``net+rwpsfloor+aspan`` with ``--span auto``;
  ``net+anchorfloor``: the floor falling back to the best closed-form physics alone (``floor_anchor = "best"``),
  ``net+anchorfloor+aspan`` with ``--span auto``; ``net+bestfloor``: that floor with its layer checks (``floor_layers``); ``net+floor+mspan``: ``net+floor``
  with the long span motion-compensated (:mod:`reconstruct.stream.motion_span`); ``net+floor+rspan``:
  ``net+floor`` with the span's parts moved by the windows' RIR velocity (``polspike reconstruct --span rir``,
  :func:`reconstruct.stream.motion_span.part_shifts_from_windows`); ``net+floor+aspan``: ``--span auto``
  (:func:`reconstruct.stream.motion_span.auto_span_shifts`: the rir span where the windows follow one velocity that
  smears the span by a pixel or more, the parts' own registration where the windows are noise-limited, else plain).

The windows' RIR shifts are estimated once per frame (``rir``: ``window``, :func:`reconstruct.physics.rir.estimate_shifts`,
or ``chained``, :class:`reconstruct.physics.rir.ChainedRir` over the cell's consecutive frames) and shared by the physics,
the motion-adapted mean, the networks and the spans, as ``polspike reconstruct --rir`` shares them.

Scores: PSNR and SSIM of T and R at each output frame's centre step against the true layers there, with a gain
fitted (least squares) and the data range of the true layer, over the frame less a ``crop``-pixel border.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from typing import Any

import numpy as np
import torch

from polinfra.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["PAN_SPEEDS", "METHODS", "LIGHTS", "default_cells", "run_motion_bench", "motion_table", "motion_plot"]

PAN_SPEEDS = (0.0, 0.1, 0.3, 0.6, 1.1, 2.0, 3.0)
"""Camera pans of the bench, view widths per second."""

OTHER_MOTIONS = (("shake", 1.0), ("rotate", 60.0), ("zoom", 2.0), ("layers", 1.1))
"""The other motions and their speeds (units: :class:`reconstruct.stream.motion_scenes.MotionSceneConfig`)."""

LIGHTS = {"dim": 0.02, "bright": 0.3}
"""Light levels, mean spikes per pixel per step."""

PHYSICS = ("ls", "ridge", "irls", "rwps")
NETS = ("net", "net+rir", "net+floor", "net+anchorfloor", "net+floor+mspan", "net+bestfloor", "net+floor+rspan", "net+floor+aspan", "net+anchorfloor+aspan", "net+rwpsfloor", "net+rwpsfloor+aspan")
METHODS = ("tfp", "mean17", "mean", *PHYSICS, "anchor", *NETS)
"""Methods of the bench (module docstring)."""

K, N_OBS, WINDOW, WIDE, SPAN = 3, 7, 13, 57, 350


def default_cells(motions=None, speeds=PAN_SPEEDS, reflections=("weak", "strong", "dominant"), lights=tuple(LIGHTS)) -> list[dict]:
    """The bench's cells: pans at ``speeds`` and the :data:`OTHER_MOTIONS` named in ``motions`` (None: all kinds)."""
    kinds = ("pan", *(m for m, _ in OTHER_MOTIONS)) if motions is None else tuple(motions)
    out = []
    for refl in reflections:
        for light in lights:
            if light not in LIGHTS:
                raise ConfigError(f"light {light!r}: choose one of {', '.join(LIGHTS)}")
            if "pan" in kinds:
                out += [{"motion": "pan", "speed": float(v), "reflection": refl, "light": light} for v in speeds]
            out += [{"motion": m, "speed": float(v), "reflection": refl, "light": light} for m, v in OTHER_MOTIONS if m in kinds]
    return out


def _score(est, gt, crop: int) -> tuple[float, float]:
    from reconstruct.evaluate.metrics import psnr, ssim

    e = np.asarray(est, np.float64)[crop : -crop or None, crop : -crop or None]
    g = np.asarray(gt, np.float64)[crop : -crop or None, crop : -crop or None]
    a = float((e * g).sum() / max((e * e).sum(), 1e-20))
    rng = max(float(g.max()), 1e-6)
    return psnr(a * e, g, rng), ssim(a * e, g, rng)


def _frame_inputs(st, c: int, rate_hz: float, rev_per_s: float):
    """Windows, angles, wide windows, span mean and harmonic of the output frame centred on step c."""
    from reconstruct.stream.groups import harmonic_design, span_harmonic, spike_mean_span

    sp, ph, e = st.spikes, st.phi, st.exposure
    stride = rate_hz * (31.5 / 360.0) / rev_per_s
    cents = [int(round(c + k * stride)) for k in range(-K, K + 1)]

    def win(cc, w):
        lo, hi = cc - w // 2, cc + w // 2 + 1
        return sp[lo:hi].sum(0, dtype=np.int32) / np.float32(w * e), float(ph[lo:hi].mean())

    I = np.stack([win(cc, WINDOW)[0] for cc in cents]).astype(np.float32)
    phi = np.array([win(cc, WINDOW)[1] for cc in cents])
    I_wide = np.stack([win(cc, WIDE)[0] for cc in cents]).astype(np.float32)
    lo, hi = spike_mean_span(c, SPAN, sp.shape[0])
    sums = np.tensordot(harmonic_design(ph[lo:hi]), sp[lo:hi].astype(np.float32), axes=(1, 0))
    I_mean = (sums[0] / ((hi - lo) * e)).astype(np.float32)
    I_harm = span_harmonic(sums, ph[lo:hi], e)
    return I, phi, I_wide, I_mean, I_harm, cents, (int(lo), int(hi))


_MODELS: dict = {}
_PANES: dict = {}


FLOORS = {"net+anchorfloor": {"floor_anchor": "best"}, "net+anchorfloor+aspan": {"floor_anchor": "best"}, "net+bestfloor": {"floor_anchor": "best", "floor_layers": True},
          "net+rwpsfloor": {"floor_anchor": "rwps"}, "net+rwpsfloor+aspan": {"floor_anchor": "rwps"}}
"""The floor settings of the methods that do not run the checkpoint's own (``net+floor`` and the span methods do)."""


def _net(weights, use_rir: bool, floor: bool, overrides: dict | None = None):
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model

    key = (str(weights or DEFAULT_WEIGHTS), use_rir, floor, tuple(sorted((overrides or {}).items())))
    if key not in _MODELS:
        _MODELS[key] = load_model(weights or DEFAULT_WEIGHTS, "cpu", use_rir=use_rir, floor=floor, **(overrides or {}))[0]
    return _MODELS[key]


def _pane(st, cfg, calibrate: str, steps: int, rate_hz: float, rev: float):
    """(maps, source) of the cell's zeta: self-calibrated on the still stream of the same scene (``still``) or on the
    cell's own (``cell``); the true maps where the calibration refuses.
    """
    from reconstruct.pane.selfcal import SelfCalConfig
    from reconstruct.pane.source import calibrate_source
    from reconstruct.stream.motion_scenes import make_motion_stream
    from reconstruct.stream.sources import array_source

    key = (cfg.width, cfg.height, cfg.steps, cfg.reflection, cfg.rate, cfg.seed, cfg.tilt_deg)
    if calibrate == "still" and key in _PANES:
        return _PANES[key]
    src = st if calibrate == "cell" else make_motion_stream(dataclasses.replace(cfg, motion="pan", speed=0.0))
    res = calibrate_source(array_source(src.spikes, src.phi0, rev, rate_hz), WINDOW, src.exposure, SelfCalConfig(fov_deg=src.fov_deg, span_s=0.95 * steps / rate_hz))
    out = (res.maps, "self") if res.ok else (st.maps, f"true (self-calibration refused: {res.reason.split(':')[0]})")
    if calibrate == "still":
        _PANES[key] = out
    return out


def run_cell(cell: dict, *, width: int = 96, height: int = 64, frames: int = 1, seed: int = 0, crop: int = 6, methods=METHODS, weights=None,
             calibrate: str = "still", rir: str = "window") -> dict[str, Any]:
    """Every method of ``methods`` on one cell -> {cell..., "zeta": source, "scores": {method: {T_psnr, ...}}, ...}."""
    from reconstruct.net.net_zeta import MapsZetaNet
    from reconstruct.physics.rir import ChainedRir, estimate_shifts, warp
    from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, solve
    from reconstruct.physics.zeta import zeta_from_maps
    from reconstruct.stream.groups import span_part_edges
    from reconstruct.stream.motion_scenes import MotionSceneConfig, make_motion_stream
    from reconstruct.stream.motion_span import SPAN_PARTS, auto_span_shifts, compensate_part_sums, compensated_span, part_shifts_from_windows, span_part_sums
    from reconstruct.stream.window_inputs import WindowInputs, inputs_of
    from reconstruct.video.tiling import run_model_on_windows

    if calibrate not in ("still", "cell"):
        raise ConfigError(f"calibrate {calibrate!r}: choose still or cell")
    if rir not in ("window", "chained"):
        raise ConfigError(f"rir {rir!r}: choose window or chained")
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ConfigError(f"unknown method(s) {', '.join(bad)}; choose from {', '.join(METHODS)}")
    rate_hz, rev = 20000.0, 30.0
    stride = rate_hz * (31.5 / 360.0) / rev
    reach = int(math.ceil(K * stride)) + WIDE // 2 + 1
    reach = max(reach, SPAN // 2 + 1)
    steps = 2 * reach + int(math.ceil((frames - 1) * stride)) + 2
    cfg = MotionSceneConfig(width=width, height=height, steps=steps, motion=cell["motion"], speed=cell["speed"], reflection=cell["reflection"], rate=LIGHTS[cell["light"]], seed=seed)
    t0 = time.perf_counter()
    st = make_motion_stream(cfg)
    span_rad = 2 * math.pi * rev * WINDOW / rate_hz
    maps, zsrc = _pane(st, cfg, calibrate, steps, rate_hz, rev)
    chained = ChainedRir() if rir == "chained" else None
    nets = {m: MapsZetaNet(_net(weights, m != "net", m not in ("net", "net+rir"), FLOORS.get(m)), maps, span_rad) for m in methods if m in NETS}
    acc: dict[str, dict[str, list]] = {m: {"T_psnr": [], "T_ssim": [], "R_psnr": [], "R_ssim": []} for m in methods}
    moved: dict[str, list] = {}  # per span method, per frame: what moved the span's parts (rir, parts or plain)
    for f in range(frames):
        c = reach + int(round(f * stride))
        I, phi, I_wide, I_mean, I_harm, cents, (lo, hi) = _frame_inputs(st, c, rate_hz, rev)
        Tg, Rg = (x[0] for x in st.layers_at([c]))
        It, pt = torch.from_numpy(I).double(), torch.from_numpy(phi)
        sh = estimate_shifts(It, pt) if chained is None else chained.window_shifts(It, pt, np.arange(f, f + N_OBS))  # consecutive frames, one Eq. (3) frame apart
        Z = zeta_from_maps(maps, phi, span_rad, dtype=torch.float64)
        Iw, Zw = warp(It, sh), warp(Z, sh)
        out: dict[str, tuple] = {}
        if "tfp" in methods:
            out["tfp"] = (2.0 * I.mean(0), None)
        if "mean17" in methods:
            out["mean17"] = (2.0 * I_mean, None)
        if "mean" in methods:
            dsteps = np.abs(np.array(cents) - c)
            v = max([float(np.hypot(*sh[k].tolist())) / dsteps[k] for k in range(N_OBS) if dsteps[k] > 0] + [1e-9])
            L = int(np.clip(1.0 / v, WINDOW, SPAN + 1)) // 2 * 2 + 1
            out["mean"] = (2.0 * st.spikes[c - L // 2 : c + L // 2 + 1].mean(0) / st.exposure, None)
        for m in PHYSICS:
            if m in methods:
                r = solve(m, Zw, Iw, None, PHYSICS_SOLVER_CONFIG)
                out[m] = (r.T.clamp_min(0).numpy(), r.R.clamp_min(0).numpy())
        if "anchor" in methods:
            from reconstruct.physics.anchor import physics_anchor
            from reconstruct.physics.span import zbar_of

            a = physics_anchor(Zw, Iw, torch.from_numpy(I_mean).double(), zbar_of(Zw, pt.double()))
            out["anchor"] = (a.T.numpy(), a.R.numpy())
        mspan = sums = None
        parts = span_part_edges(hi - lo, SPAN_PARTS)
        tc = np.asarray(cents, np.float64) - lo  # the windows' centres in the span's steps
        for m, model in nets.items():
            kw = {"I_mean": I_mean[None], "I_harm": I_harm[None], "I_wide": I_wide[None], "exposure": st.exposure, "span_steps": hi - lo}
            if m == "net+floor+mspan":
                if mspan is None:
                    mspan = compensated_span(st.spikes[lo:hi], st.phi[lo:hi], st.exposure)
                kw["I_mean"], kw["I_harm"] = mspan[0][None], mspan[1][None]
            if m.endswith(("+rspan", "+aspan")):  # the span's parts moved by the windows' velocity (aspan: auto_span_shifts)
                if sums is None:  # the parts' sums, once per frame for both span methods
                    sums, _ = span_part_sums(st.spikes[lo:hi], st.phi[lo:hi])
                psh, how = (part_shifts_from_windows(sh.numpy(), tc, parts), "rir") if m == "net+floor+rspan" else auto_span_shifts(sh.numpy(), tc, sums, parts, st.phi[lo:hi], float(st.exposure * I.mean() * WINDOW))
                sp = compensate_part_sums(sums, parts, st.phi[lo:hi], st.exposure, shifts=psh)
                kw["I_mean"], kw["I_harm"] = sp[0][None], sp[1][None]
                moved.setdefault(m, []).append(how)
            x = WindowInputs(I[None], phi[None].astype(np.float32), **kw, shifts=sh.numpy()[None] if model.accepts_shifts else None).only(inputs_of(model))
            o = run_model_on_windows(model, x, "cpu", 0)
            out[m] = (o["T"][0], o["R"][0])
        for m, (T, R) in out.items():
            for key, est, gt in (("T", T, Tg), ("R", R, Rg)):
                if est is None:
                    continue
                p, s = _score(est, gt, crop)
                acc[m][f"{key}_psnr"].append(p)
                acc[m][f"{key}_ssim"].append(s)
    scores = {m: {k: (float(np.mean(v)) if v else None) for k, v in d.items()} for m, d in acc.items()}
    return {**cell, "zeta": zsrc, "scores": scores, "seconds": time.perf_counter() - t0, "exposure": st.exposure, "rir": rir,
            "span_moved": {m: ",".join(v) for m, v in moved.items()}}


DEFAULT_NET = ("net+floor+aspan", "net+floor")
"""The method that stands for ``polspike reconstruct``'s defaults (RIR, the checkpoint's floor, ``--span auto``), or the plain
span's where a run did not include it."""


def holds(row: dict) -> dict[str, Any]:
    """The project's rule on one cell for the default network (:data:`DEFAULT_NET`): T at least its own physics core's
    (RWPS) and the plain spike mean's (``holds_core``, ``margin_core_db``), at least every physics solver's and both
    spike means' (``holds_solvers``, ``margin_solvers_db``), and at least those and the anchor's (``holds``,
    ``margin_db``).
    """
    s = row["scores"]
    m = next((k for k in DEFAULT_NET if k in s), None)
    if m is None:
        return {}
    net = s[m]["T_psnr"]

    def margin(names):
        refs = [s[k]["T_psnr"] for k in names if k in s]
        return min(net - v for v in refs) if refs else None

    worst, core, solvers = margin((*PHYSICS, "anchor", "mean17", "mean")), margin(("rwps", "mean17")), margin((*PHYSICS, "mean17", "mean"))
    return {"judged": m, "margin_db": worst, "holds": bool(worst is not None and worst >= 0.0), "margin_core_db": core,
            "holds_core": bool(core is not None and core >= 0.0), "margin_solvers_db": solvers,
            "holds_solvers": bool(solvers is not None and solvers >= 0.0)}


def run_motion_bench(cells: list[dict], progress=None, **kw) -> dict[str, Any]:
    """:func:`run_cell` over ``cells`` -> {"config": kw, "rows": [...]} (each row with :func:`holds`)."""
    rows = []
    for i, cell in enumerate(cells):
        r = run_cell(cell, **kw)
        r.update(holds(r))
        rows.append(r)
        log.info("%s %.2f %s %s: %s", cell["motion"], cell["speed"], cell["reflection"], cell["light"], {m: round(v["T_psnr"], 2) for m, v in r["scores"].items()})
        if progress is not None:
            progress(i + 1, len(cells))
    return {"config": {k: (str(v) if k == "weights" else (list(v) if isinstance(v, tuple) else v)) for k, v in kw.items()}, "rows": rows}


def motion_table(result: dict) -> str:
    """Markdown: one row per cell, T PSNR per method (R PSNR of the layered methods in a second table)."""
    rows = result["rows"]
    if not rows:
        return "(no cells)\n"
    methods = list(rows[0]["scores"])
    judged = rows[0].get("judged", "net+floor")
    head = "| motion | speed | reflection | light | zeta | " + " | ".join(methods) + f" | {judged} >= rwps, mean17 | {judged} >= every solver, mean | {judged} >= every physics, anchor, mean |\n"
    head += "|---|---:|---|---|---|" + "---:|" * len(methods) + "---|---|---|\n"

    def fmt(v):
        return "" if v is None else f"{v:.2f}"

    lines = []
    def verdict(r, key):
        if r.get(f"holds_{key}" if key else "holds") is None:
            return ""
        return "yes" if r[f"holds_{key}" if key else "holds"] else f"no ({r[f'margin_{key}_db' if key else 'margin_db']:+.2f} dB)"

    for r in rows:
        ok = " | ".join(verdict(r, k) for k in ("core", "solvers", ""))
        z = "true" if str(r["zeta"]).startswith("true") else r["zeta"]
        lines.append(f"| {r['motion']} | {r['speed']:g} | {r['reflection']} | {r['light']} | {z} | " + " | ".join(fmt(r["scores"][m]["T_psnr"]) for m in methods) + f" | {ok} |")
    rm = [m for m in methods if rows[0]["scores"][m]["R_psnr"] is not None]
    rt = "| motion | speed | reflection | light | " + " | ".join(rm) + " |\n|---|---:|---|---|" + "---:|" * len(rm) + "\n"
    rt += "\n".join(f"| {r['motion']} | {r['speed']:g} | {r['reflection']} | {r['light']} | " + " | ".join(fmt(r["scores"][m]["R_psnr"]) for m in rm) + " |" for r in rows)
    n_hold, n_core, n_solv = (sum(1 for r in rows if r.get(k)) for k in ("holds", "holds_core", "holds_solvers"))
    return (f"T PSNR (dB)\n\n{head}" + "\n".join(lines) + f"\n\n{judged} >= its own core (rwps) and the plain spike mean on T: {n_core} of {len(rows)} cells; "
            f">= every physics solver and both spike means: {n_solv} of {len(rows)}; >= those and the anchor: {n_hold} of {len(rows)}\n\nR PSNR (dB)\n\n{rt}\n")


def motion_plot(result: dict, path) -> None:
    """T PSNR against pan speed, one line per method, one panel per reflection strength and light level."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from polinfra.atomic import atomic_path

    pans = [r for r in result["rows"] if r["motion"] == "pan"]
    combos = sorted({(r["reflection"], r["light"]) for r in pans}, key=lambda x: (x[1], x[0]))
    if not combos:
        return
    fig, axes = plt.subplots(1, len(combos), figsize=(4 * len(combos), 3.4), squeeze=False)
    methods = list(pans[0]["scores"])
    judged = next((m for m in DEFAULT_NET if m in methods), None)
    colours = plt.get_cmap("tab20").colors
    for ax, (refl, light) in zip(axes[0], combos):
        sel = sorted((r for r in pans if (r["reflection"], r["light"]) == (refl, light)), key=lambda r: r["speed"])
        for i, m in enumerate(methods):  # networks dashed, physics and means solid; the default drawn bold
            ax.plot([r["speed"] for r in sel], [r["scores"][m]["T_psnr"] for r in sel], marker="o", ms=3, label=m, color="black" if m == judged else colours[(2 * i) % 20 + (2 * i) // 20 % 2],
                    ls="--" if m.startswith("net") and m != judged else "-", lw=2.6 if m == judged else 1.0, zorder=3 if m == judged else 2)
        ax.set_title(f"{refl} reflection, {light}")
        ax.set_xlabel("pan, view widths / s")
        ax.set_ylabel("T PSNR (dB)")
        ax.grid(alpha=0.3)
    fig.legend(*axes[0][0].get_legend_handles_labels(), fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")
    plt.close(fig)

