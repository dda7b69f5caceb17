"""Inspect the polarization ground truth of a stored group at one time: figures, data, video.

``polspike dataset inspect DIR [--group G] [--time T] --out OUT [--video]``
calls :func:`inspect_group`.  DIR is a dataset directory (``dataset.json``,
layout of :func:`reconstruct.stream.groups.list_groups`, or a folder of group
directories) or one group directory (``GROUP/spikes.h5``, ``spike_sim.store``).
The time T (seconds, default the middle of the stream) is snapped to the
nearest stored output frame m whose 2K + 1 observation window fits in the
stream, so every figure uses stored GT without interpolation.

What is computed (all in :func:`inspection_data`, saved to ``inspect_data.npz``):

* pane maps ``theta``, ``phi_perp`` (plane of incidence / s-direction in the
  image), ``R_perp``, ``R_par``, ``T_perp``, ``T_par`` (``T = 1 - R`` when the
  group has no T maps);
* ``zeta`` at the frame's true window-mean polarizer angle phi (paper Eq. (2),
  point value, like the optional stored ``gt/zeta``);
* Stokes of the mixed light in front of the polarizer, the T part plus the R
  part (:func:`polphysics.zeta.stokes_from_layers`)::

      S0 = L_R (R_perp + R_par)/2 + L_T (T_perp + T_par)/2
      (S1, S2) = [L_R (R_perp - R_par)/2 + L_T (T_perp - T_par)/2] (cos 2 phi_perp, sin 2 phi_perp)

  so that ``1/2 (S0 + S1 cos 2phi + S2 sin 2phi)`` is paper Eq. (1)
  ``L_M = 1/2 (zeta L_R + (1 - zeta) L_T)`` for a lossless pane; ``dop`` =
  sqrt(S1^2 + S2^2)/S0 in [0, 1] and ``aolp`` = 1/2 atan2(S2, S1) in [0, pi).
  This is the mixing model on the stored GT (stores keep layers and maps, not
  the rendered Stokes): a thick slab's displaced ghost appears only in the
  measured frame;
* ``mixed_gt``: the light behind the polarizer at phi from those Stokes;
  ``mixed_I``: the measured Eq. (3) frame (spikes per step / exposure);
* ``obs_I`` (N, H, W), ``obs_phi`` (N,): the observations I(i+k) of output
  frames m-K..m+K at their nominal angles (the reconstructor's input);
* a spike raster of a few pixels over the window span with phi(t).

Figures (PNG, each panel titled with units and a colour bar): ``pane_maps.png``,
``stokes.png``, ``layers.png``, ``raster.png``, ``window.png``; with
``video=True`` ``video.mp4`` (measured mixed input 2 I(i) | GT T | GT R, side
by side, at the output cadence).  ``inspect.json`` lists the files and the
numbers.  Every file is written atomically.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from polinfra.atomic import atomic_path, ensure_dir, write_json
from polinfra.errors import ConfigError, DataFormatError
from polphysics.stokes import aolp, dop, polarizer_intensity
from polphysics.zeta import stokes_from_layers, zeta

__all__ = ["group_names", "resolve_group", "inspection_data", "inspect_group", "FIGURES"]

log = logging.getLogger(__name__)

DEPARTURE_MAPS = ("dop_T", "dop_R", "eq12_err", "polT_model_err")
"""Maps a group of a 3-D object scene stores (keyframe 0): DoP of T alone and R alone, per-pixel worst-case
|I_rendered - I_Eq(1)-(2)| under the unpolarized-T assumption, and the same for the polarized-T model."""

FIGURES = ("pane_maps.png", "stokes.png", "layers.png", "raster.png", "window.png")
"""Figure files written by :func:`inspect_group`."""

_RAD = "linear radiance (1 = brightest layer)"


def group_names(root: str | os.PathLike) -> list[tuple[str, Path, str]]:
    """(name, directory, split) of every group under a dataset directory (or the one group ``root`` is)."""
    root = Path(root)
    if not root.exists():
        raise DataFormatError(f"{root} does not exist; give a dataset directory or a group directory (GROUP/spikes.h5)")
    if (root / "spikes.h5").is_file():
        return [(root.name, root, "")]
    meta = root / "dataset.json"
    out: list[tuple[str, Path, str]] = []
    if meta.is_file():
        try:
            data = json.loads(meta.read_text())
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{meta} is not valid JSON ({exc})") from None
        if isinstance(data.get("groups"), list):
            for g in data["groups"]:
                if isinstance(g, dict) and "path" in g:
                    p = root / g["path"]
                    out.append((str(g.get("name", p.name)), p, str(g.get("split", ""))))
        for split, rels in (data.get("splits") or {}).items():
            for rel in rels or []:
                rel = rel["path"] if isinstance(rel, dict) else rel
                out.append((Path(rel).name, root / rel, str(split)))
    else:
        out = [(p.name, p, "") for p in sorted(root.iterdir()) if (p / "spikes.h5").is_file()]
    if not out:
        raise DataFormatError(f"{root} holds no groups (no dataset.json listing groups and no GROUP/spikes.h5 folders); build a dataset first")
    return out


def resolve_group(root: str | os.PathLike, group: str | None = None) -> tuple[str, Path]:
    """(name, directory) of ``group`` in ``root`` (default: the first group listed)."""
    groups = group_names(root)
    if group is None:
        name, path, _ = groups[0]
    else:
        hits = [(n, p) for n, p, _ in groups if n == group or p.name == group]
        if not hits:
            names = [n for n, _, _ in groups]
            shown = ", ".join(names[:12]) + (f", ... ({len(names)} in all)" if len(names) > 12 else "")
            raise DataFormatError(f"no group {group!r} in {root}; choose --group from: {shown}")
        name, path = hits[0]
    if not (path / "spikes.h5").is_file():
        raise DataFormatError(f"group {name!r} is listed in {root} but {path}/spikes.h5 is missing; rebuild the dataset")
    return name, path


def _open_cached(group_dir):
    """Open a group with a 64 MiB HDF5 chunk cache: consecutive Eq. (3) windows share inflated spike chunks."""
    import h5py

    from spike_sim.store import open_group

    g = open_group(group_dir)
    name = g.f.filename
    g.f.close()
    g.f = h5py.File(name, "r", rdcc_nbytes=64 << 20, rdcc_nslots=10007)
    return g


def _frame_for_time(g, time_s: float | None, K: int) -> int:
    times = g.array("output/times_s") if g.has("output/times_s") else (g.array("output/step_index") + 0.5) * g.dt_s
    M = times.size
    if M == 0:
        raise DataFormatError(f"{g.path}: the group has no output frames (stream too short for one Eq. (3) window)")
    t_end = g.n_steps * g.dt_s
    if time_s is None:
        time_s = 0.5 * t_end
    if not 0.0 <= time_s <= t_end:
        raise ConfigError(f"--time {time_s:g} s lies outside the group's stream [0, {t_end:g}] s; choose a time inside it")
    m = int(np.argmin(np.abs(times - time_s)))
    if M >= 2 * K + 1:
        m = min(max(m, K), M - 1 - K)
    return m


def inspection_data(group_dir: str | os.PathLike, time_s: float | None = None, n_obs: int = 7, n_pixels: int = 6) -> dict[str, Any]:
    """Everything the figures show, for the output frame nearest ``time_s`` (module docstring).

    Args:
        group_dir: a group directory.
        time_s: time in the stream, seconds (default: its middle).
        n_obs: observations N = 2K + 1 of the window figure.
        n_pixels: pixels in the spike raster.

    Returns:
        dict of numpy arrays and scalars: maps (H, W) ``theta``, ``phi_perp``,
        ``R_perp``, ``R_par``, ``T_perp``, ``T_par``, ``zeta``, ``zeta_stored``
        (or absent), ``T``, ``R``, ``S`` (3, H, W), ``dop``, ``aolp``,
        ``mixed_gt``, ``mixed_I``, ``obs_I`` (N, H, W), ``obs_phi`` (N,),
        ``obs_steps`` (N,), ``raster`` (n, P) uint8, ``raster_t_s`` (n,),
        ``raster_phi_true`` (n,), ``raster_phi_nominal`` (n,), ``raster_pixels``
        (P, 2) (row, col), and scalars ``frame``, ``time_s``, ``phi_true``,
        ``phi_nominal``, ``centre_step``, ``window_steps``, ``exposure``.
    """
    K = n_obs // 2
    with _open_cached(group_dir) as g:
        mp = g.maps()
        missing = {"R_perp", "R_par", "phi_perp"} - set(mp)
        if missing:
            raise DataFormatError(f"{group_dir}: no coefficient maps {sorted(missing)} under /maps; inspect needs a group simulated from a source with maps")
        if not (g.has("gt/T") and g.has("gt/R")):
            raise DataFormatError(f"{group_dir}: no ground-truth layers gt/T, gt/R; inspect needs a group simulated from a source with layers")
        agg = g.json_attr("aggregate_json") or {}
        win = int(agg.get("window_steps", 13))
        h = win // 2
        exposure = float((g.json_attr("config_json") or {}).get("exposure", 1.0))
        m = _frame_for_time(g, time_s, K)
        steps = g.array("output/step_index")
        c = int(steps[m])
        phi_nom_all = g.phi_nominal_rad
        phi_true_all = g.phi_true_rad
        ph_t = float(g.array("output/phi_true_rad")[m]) if g.has("output/phi_true_rad") else float(phi_true_all[c - h : c + h + 1].mean())
        ph_n = float(g.array("output/phi_nominal_rad")[m]) if g.has("output/phi_nominal_rad") else float(phi_nom_all[c - h : c + h + 1].mean())
        f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
        Rp, Rs, pp = (f32(mp[k]) for k in ("R_perp", "R_par", "phi_perp"))
        Tp = f32(mp["T_perp"]) if "T_perp" in mp else 1.0 - Rp
        Ts = f32(mp["T_par"]) if "T_par" in mp else 1.0 - Rs
        T, R = g.gt_frame("T", m), g.gt_frame("R", m)
        S = stokes_from_layers(T, R, Rp, Rs, Tp, Ts, pp)  # T part + R part, paper Eq. (1)-(2) in Stokes form
        out: dict[str, Any] = {
            "theta": f32(mp.get("theta", np.full_like(Rp, np.nan))),
            "phi_perp": pp,
            "R_perp": Rp,
            "R_par": Rs,
            "T_perp": f32(Tp),
            "T_par": f32(Ts),
            "zeta": f32(zeta(ph_t, Rp, Rs, pp)),  # paper Eq. (2)
            "T": T,
            "R": R,
            "S": f32(S),
            "dop": f32(dop(S[0], S[1], S[2])),
            "aolp": f32(aolp(S[1], S[2])),
            "mixed_gt": f32(polarizer_intensity(S[0], S[1], S[2], ph_t)),
            "mixed_I": g.read(c - h, c + h + 1).sum(0, dtype=np.int32).astype(np.float32) / np.float32(win * exposure),  # paper Eq. (3)
        }
        if g.has("gt/zeta"):
            out["zeta_stored"] = g.gt_frame("zeta", m)
        for k in DEPARTURE_MAPS:  # 3-D object scenes: how far the rendered mixture departs from Eq. (1)-(2)
            if k in mp:
                out[k] = f32(mp[k])
        lo, hi = max(0, m - K), min(steps.size, m + K + 1)
        obs = steps[lo:hi]
        out["obs_steps"] = obs.astype(np.int64)
        out["obs_I"] = np.stack([g.read(s - h, s + h + 1).sum(0, dtype=np.int32) / np.float32(win * exposure) for s in obs]).astype(np.float32)  # Eq. (3)
        out["obs_phi"] = np.array([phi_nom_all[s - h : s + h + 1].mean() for s in obs])
        # raster: the window span of the observations
        r0, r1 = int(max(0, obs[0] - h - 2)), int(min(g.n_steps, obs[-1] + h + 3))
        pix = _raster_pixels(out["dop"], S[0], n_pixels)
        sp = g.read(r0, r1)
        out["raster"] = sp[:, pix[:, 0], pix[:, 1]].astype(np.uint8)
        out["raster_t_s"] = (np.arange(r0, r1) + 0.5) * g.dt_s
        out["raster_phi_true"] = phi_true_all[r0:r1]
        out["raster_phi_nominal"] = phi_nom_all[r0:r1]
        out["raster_pixels"] = pix
        out.update(frame=m, time_s=(c + 0.5) * g.dt_s, phi_true=ph_t, phi_nominal=ph_n, centre_step=c, window_steps=win, exposure=exposure, rate_hz=g.rate_hz, n_output_frames=int(steps.size))
    return out


def _raster_pixels(dop_map: np.ndarray, s0: np.ndarray, n: int) -> np.ndarray:
    """Deterministic pixels: most / least polarized, brightest / darkest, then spread over the image."""
    H, W = dop_map.shape
    picks = [np.argmax(dop_map), np.argmin(dop_map), np.argmax(s0), np.argmin(s0)]
    for q in np.linspace(0, H * W - 1, n + 2)[1:-1]:
        picks.append(int(q) + W // 2 if int(q) + W // 2 < H * W else int(q))
    seen: list[int] = []
    for p in picks:
        if int(p) not in seen:
            seen.append(int(p))
        if len(seen) == n:
            break
    return np.array([divmod(p, W) for p in seen], dtype=np.int64)


# ---------------------------------------------------------------------------------------------- figures


def _deg(a):
    return np.degrees(a)


def _figures(d: dict[str, Any], name: str, out: Path, dpi: int = 110) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from polinfra.plotting import image_grid, save_figure

    when = f"group {name}, t = {d['time_s'] * 1e3:.2f} ms (output frame {d['frame']}), phi = {_deg(d['phi_true']) % 180:.1f} deg"
    files = []
    frac = {"cmap": "viridis", "label": "fraction"}
    fig = image_grid(
        [
            ("incidence angle theta", _deg(d["theta"]), {"cmap": "magma", "label": "deg"}),
            ("s-direction phi_perp (plane of incidence)", _deg(d["phi_perp"]) % 180.0, {"cmap": "twilight", "vmin": 0, "vmax": 180, "label": "deg (mod 180)"}),
            ("R_perp (s reflectance)", d["R_perp"], frac),
            ("R_par (p reflectance)", d["R_par"], frac),
            ("zeta at phi, paper Eq. (2)", d["zeta"], frac),
            ("T_perp, T_par mean (transmittance)", 0.5 * (d["T_perp"] + d["T_par"]), frac),
        ],
        ncols=3,
        title=f"Pane coefficient maps - {when}",
    )
    files.append(save_figure(fig, out / "pane_maps.png", dpi=dpi))
    s0max = float(np.nanmax(d["S"][0])) or 1.0
    lmax = float(np.nanmax(np.abs(d["S"][1:]))) or 1e-6
    fig = image_grid(
        [
            ("S0 (total radiance)", d["S"][0], {"cmap": "gray", "vmin": 0, "vmax": s0max, "label": _RAD}),
            ("S1 (+: along image x)", d["S"][1], {"cmap": "RdBu_r", "vmin": -lmax, "vmax": lmax, "label": _RAD}),
            ("S2 (+: along +45 deg)", d["S"][2], {"cmap": "RdBu_r", "vmin": -lmax, "vmax": lmax, "label": _RAD}),
            ("DoP of the mixed light", d["dop"], {"cmap": "viridis", "vmin": 0, "vmax": max(1e-3, float(d["dop"].max())), "label": "degree of linear polarization (0-1)"}),
            ("AoLP of the mixed light", _deg(d["aolp"]), {"cmap": "twilight", "vmin": 0, "vmax": 180, "label": "deg from image x toward up"}),
            ("behind the polarizer at phi", d["mixed_gt"], {"cmap": "gray", "vmin": 0, "label": _RAD}),
        ],
        ncols=3,
        title=f"Stokes of the mixed light in front of the polarizer (T part + R part) - {when}",
    )
    files.append(save_figure(fig, out / "stokes.png", dpi=dpi))
    vmax = max(1e-6, float(max(d["T"].max(), d["R"].max())))
    mix = {"cmap": "gray", "vmin": 0, "vmax": max(1e-6, float(max(d["mixed_gt"].max(), d["mixed_I"].max()))), "label": _RAD}
    fig = image_grid(
        [
            ("transmission layer T (GT)", d["T"], {"cmap": "gray", "vmin": 0, "vmax": vmax, "label": _RAD}),
            ("reflection layer R (GT)", d["R"], {"cmap": "gray", "vmin": 0, "vmax": vmax, "label": _RAD}),
            ("mixed frame, paper Eq. (1) (GT)", d["mixed_gt"], mix),
            ("mixed frame I(i) from spikes, Eq. (3)", d["mixed_I"], mix),
        ],
        ncols=2,
        title=f"Layers and mixed frame - {when}",
    )
    files.append(save_figure(fig, out / "layers.png", dpi=dpi))
    files.append(_raster_figure(d, when, out / "raster.png", plt, save_figure, dpi))
    obs = d["obs_I"]
    vm = max(1e-6, float(obs.max()))
    fig = image_grid(
        [(f"I(i{k - len(obs) // 2:+d}), phi = {_deg(p) % 180:.1f} deg", im, {"cmap": "gray", "vmin": 0, "vmax": vm, "label": _RAD}) for k, (im, p) in enumerate(zip(obs, d["obs_phi"]))],
        ncols=min(4, len(obs)),
        title=f"The {len(obs)} observations of the window, paper Eq. (3) (nominal angles) - {when}",
    )
    files.append(save_figure(fig, out / "window.png", dpi=dpi))
    return files


def _raster_figure(d, when, path, plt, save_figure, dpi: int = 110) -> Path:
    t_ms = (d["raster_t_s"] - d["time_s"]) * 1e3
    r = d["raster"]
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 5.2), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    pos = [t_ms[np.nonzero(r[:, j])[0]] for j in range(r.shape[1])]
    a0.eventplot(pos, lineoffsets=np.arange(r.shape[1]), linelengths=0.8, colors="k", linewidths=0.6)
    a0.set_yticks(np.arange(r.shape[1]))
    a0.set_yticklabels([f"({y}, {x})" for y, x in d["raster_pixels"]], fontsize=7)
    a0.set_ylabel("pixel (row, col)")
    dt_ms = 1e3 / d["rate_hz"]
    for k, s in enumerate(d["obs_steps"]):
        c_ms = ((s + 0.5) / d["rate_hz"] - d["time_s"]) * 1e3
        half = d["window_steps"] * dt_ms / 2
        for ax in (a0, a1):
            ax.axvspan(c_ms - half, c_ms + half, color="tab:orange", alpha=0.25 if s != d["centre_step"] else 0.5, lw=0)
    a0.set_title(f"Spike raster (20 kHz steps) with the Eq. (3) windows shaded - {when}", fontsize=9)
    a1.plot(t_ms, _deg(d["raster_phi_true"]) % 180.0, ".", ms=1.5, label="true phi(t)")
    nom = _deg(d["raster_phi_nominal"]) % 180.0
    nom = np.where(np.concatenate([[False], np.diff(nom) < 0]), np.nan, nom)  # break the line at the wrap
    a1.plot(t_ms, nom, "-", color="tab:blue", lw=0.6, alpha=0.7, label="nominal (calibrated) phi(t)")
    a1.set_ylabel("polarizer angle (deg mod 180)")
    a1.set_xlabel("time relative to the frame centre (ms)")
    a1.set_ylim(0, 180)
    a1.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return save_figure(fig, path, dpi=dpi)


def _write_video(group_dir: Path, path: Path, max_frames: int, progress: Callable[[int, int], None] | None) -> int:
    """MP4 at the output cadence: measured mixed input 2 I(i) | GT T | GT R (gain 1, clipped to [0, 1])."""
    import imageio.v2 as iio

    with _open_cached(group_dir) as g:
        steps = g.array("output/step_index")
        agg = g.json_attr("aggregate_json") or {}
        win = int(agg.get("window_steps", 13))
        h = win // 2
        exposure = float((g.json_attr("config_json") or {}).get("exposure", 1.0))
        M = steps.size if not max_frames else min(steps.size, max_frames)
        dur = g.n_steps * g.dt_s
        fps = max(1.0, steps.size / dur) if dur > 0 else 30.0
        H2, W2 = g.height // 2 * 2, g.width // 2 * 2
        to8 = lambda a: (np.clip(a[:H2, :W2], 0, 1) * 255 + 0.5).astype(np.uint8)  # noqa: E731
        with atomic_path(path) as tmp:
            w = iio.get_writer(str(tmp), format="FFMPEG", mode="I", fps=fps, codec="libx264", quality=8, macro_block_size=1, pixelformat="yuv420p", ffmpeg_log_level="error")
            try:
                for m in range(M):
                    c = int(steps[m])
                    I = g.read(c - h, c + h + 1).sum(0, dtype=np.int32) / np.float32(win * exposure)  # Eq. (3)
                    frame = np.concatenate([to8(2.0 * I), to8(g.gt_frame("T", m)), to8(g.gt_frame("R", m))], 1)
                    w.append_data(frame)
                    if progress is not None:
                        progress(m + 1, M)
            finally:
                w.close()
    return M


def _departure_summary(d: dict[str, Any]) -> dict | None:
    """Stats of the Eq. (1)-(2) departure maps of a 3-D object scene (None for layer scenes)."""
    if "eq12_err" not in d:
        return None

    def st(a):
        v = np.asarray(a, np.float64).ravel()
        v = v[np.isfinite(v)]
        return None if v.size == 0 else {"mean": float(v.mean()), "p99": float(np.percentile(v, 99)), "max": float(v.max())}

    return {
        "what": "keyframe 0 of the full-tier render: DoP of T alone / R alone, worst case over phi of |I_rendered - I_Eq(1)-(2)| "
        "with unpolarized layers (eq12_err) and with T's polarization carried through the pane (polT_model_err)",
        **{k: st(d[k]) for k in DEPARTURE_MAPS if k in d},
        "dop_T_fraction_above_0.1": float(np.mean(np.asarray(d["dop_T"]) > 0.1)) if "dop_T" in d else None,
    }


def inspect_group(
    root: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    group: str | None = None,
    time_s: float | None = None,
    video: bool = False,
    video_frames: int = 0,
    n_pixels: int = 6,
    dpi: int = 110,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Write the inspection figures (and optionally the video) of one group at one time.

    Args:
        root: dataset directory or group directory.
        out_dir: output folder (created).
        group: group name (default: the first group of the dataset).
        time_s: time in the stream, seconds (default: the middle).
        video: also write ``video.mp4`` (mixed input | T | R at the output cadence).
        video_frames: at most this many video frames (0 = the whole group).
        n_pixels: pixels in the spike raster.
        dpi: figure resolution.
        progress: optional (done, total) callback for the video.

    Returns:
        Summary dict (also written to ``inspect.json``): group, path, frame, time_s,
        phi_deg, files, and checks (DoP range, zeta vs stored gt/zeta, Eq. (1) vs Stokes).
    """
    if n_pixels < 1:
        raise ConfigError(f"n_pixels = {n_pixels} must be >= 1")
    if not 20 <= dpi <= 600:
        raise ConfigError(f"dpi = {dpi} must be in [20, 600]")
    name, gdir = resolve_group(root, group)
    out = ensure_dir(out_dir)
    d = inspection_data(gdir, time_s, n_pixels=n_pixels)
    files = _figures(d, name, out, dpi)
    with atomic_path(out / "inspect_data.npz", suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **{k: np.asarray(v) for k, v in d.items()})
    files.append(out / "inspect_data.npz")
    n_video = 0
    if video:
        n_video = _write_video(gdir, out / "video.mp4", video_frames, progress)
        files.append(out / "video.mp4")
    eq1 = 0.5 * (d["zeta"] * d["R"] + (1 - d["zeta"]) * d["T"])  # paper Eq. (1)
    summary = {
        "group": name,
        "path": str(gdir),
        "frame": int(d["frame"]),
        "time_s": float(d["time_s"]),
        "phi_true_deg": float(math.degrees(d["phi_true"]) % 180.0),
        "phi_nominal_deg": float(math.degrees(d["phi_nominal"]) % 180.0),
        "window_steps": int(d["window_steps"]),
        "video_frames": n_video,
        "checks": {
            "dop_min": float(d["dop"].min()),
            "dop_max": float(d["dop"].max()),
            "zeta_vs_stored_max_abs": float(np.abs(d["zeta"] - d["zeta_stored"]).max()) if "zeta_stored" in d else None,
            "eq1_vs_stokes_max_abs": float(np.abs(eq1 - d["mixed_gt"]).max()),
            "mixed_I_vs_gt_mean_abs": float(np.abs(d["mixed_I"] - d["mixed_gt"]).mean()),
        },
        "eq12_departure": _departure_summary(d),
        "files": [p.name for p in files],
    }
    write_json(out / "inspect.json", summary)
    return summary
