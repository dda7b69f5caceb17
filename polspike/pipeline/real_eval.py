"""The real recordings of ../shared/data/real_spikes through `polspike reconstruct`'s path: ``polspike evaluate-real``.

None of these recordings has a rotating polarizer (README of that folder), so there is no
reflection to remove: the check is robustness.  Each recording is reconstructed with the given
checkpoint (default: the shipped one) on a bounded number of output frames, with the exposure
estimated from the stream (:mod:`reconstruct.stream.exposure`, the raw-.dat default) and a nominal
polarizer calibration (phi0 = 0; the rotation rate chosen so that the N observations of the
requested frames fit the recording at the trained 31.5 deg stride: 30 rev/s, faster for short recordings).  Per
recording: no crash, no NaN, and T against

* the TFP image of the same window: 2 x the mean of its N Eq. (3) frames (without a polarizer
  and a reflection, T = 2 I is the answer; paper Eq. (1) with zeta = 0);
* the spike mean: 2 x the whole recording's mean firing rate / exposure (less noisy than
  one window's TFP when the light is low).

PSNR uses the reference image's peak as the data range; the correlation is also given.
Outputs: ``real.md`` (table), ``real.json``, ``real.csv``, ``real.png`` (per recording: TFP, T, R,
spike mean) and each recording's ``reconstruct.json`` under ``runs/``.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["RECORDINGS", "Recording", "default_real_dir", "nominal_rev_per_s", "evaluate_real", "real_markdown"]


@dataclasses.dataclass(frozen=True)
class Recording:
    """One recording of the real_spikes folder and how to read it."""

    file: str
    kind: str  # "npz" or "dat"
    key: str = ""  # npz key
    order: str = "THW"  # axis order of the npz array
    height: int = 0  # .dat frame size
    width: int = 0
    note: str = ""


RECORDINGS = (
    Recording("spikingsim_real_spike.npz", "npz", key="arr_0", order="HWT", note="real capture (SpikingSIM), 0.22 spikes/step"),
    Recording("spikezoo_uhsr_real.npz", "npz", key="spk", order="THW", note="real low-light capture (UHSR), 0.01-0.065 spikes/step"),
    Recording("spikezoo_reds_200_part1_key_id151.dat", "dat", height=250, width=400, note="simulated from REDS (format check)"),
)
"""The recordings listed in the folder's README."""


def default_real_dir() -> Path:
    """../shared/data/real_spikes beside the project root."""
    return Path(__file__).resolve().parents[2].parent / "shared" / "data" / "real_spikes"


def nominal_rev_per_s(steps: int, frames: int, n_obs: int = 7, window_steps: int = 13, stride_deg: float = 31.5, rate_hz: float = 20000.0, min_rev_per_s: float = 30.0) -> float:
    """Rotation rate (rev/s): 30 (as trained), or faster when ``frames`` output frames (each N
    observations ``stride_deg`` apart) would not fit ``steps`` steps at 30.
    """
    span = steps - window_steps - 2
    per = span / (n_obs - 1 + max(1, frames))
    if per < 1:
        from polinfra.errors import ConfigError

        raise ConfigError(f"{steps} steps cannot hold {n_obs} observations of {window_steps} steps")
    return max(rate_hz * stride_deg / 360.0 / per, min_rev_per_s)


def _load(rec: Recording, folder: Path, crop: int) -> np.ndarray:
    p = folder / rec.file
    if rec.kind == "npz":
        a = np.load(p)[rec.key]
        sp = np.transpose(a, [rec.order.index(c) for c in "THW"])
    else:
        from spike_sim.vidar_dat import read_dat

        sp = read_dat(p, rec.height, rec.width)
    sp = np.ascontiguousarray(sp, dtype=np.uint8)
    if crop > 0:
        H, W = sp.shape[1:]
        y0, x0 = max(0, (H - crop) // 2), max(0, (W - crop) // 2)
        sp = np.ascontiguousarray(sp[:, y0 : y0 + crop, x0 : x0 + crop])
    return sp


def _psnr_peak(est: np.ndarray, ref: np.ndarray) -> float:
    from reconstruct.evaluate.metrics import psnr

    return psnr(est, ref, data_range=max(float(ref.max()), 1e-9))


def evaluate_real(out: str | Path, folder: str | Path | None = None, *, weights: str | Path | None = None, max_frames: int = 3, crop: int = 0,
                  zeta: str = "learned", device: str = "cpu", recordings=RECORDINGS, progress=None, ensemble: int = 1) -> dict[str, Any]:
    """Reconstruct every recording present in ``folder`` (module docstring) -> {"rows": [...], "config": {...}}.

    A recording that raises is reported (``status`` "error: ...") and the others still run.
    """
    from polinfra.atomic import ensure_dir
    from polinfra.exr import read_exr
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.net.net_zeta import build_net_zeta_model
    from reconstruct.stream.exposure import estimate_exposure
    from reconstruct.stream.sources import array_source
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream
    from spike_sim.aggregate import AggregateConfig, frame_centres

    folder = Path(folder) if folder is not None else default_real_dir()
    out = ensure_dir(out)
    net = load_model(weights or DEFAULT_WEIGHTS, device)[0]
    if ensemble > 1:  # test-time self-ensemble (reconstruct.net.network.SymmetryEnsemble)
        from reconstruct.net.network import SymmetryEnsemble

        net = SymmetryEnsemble(net, ensemble).eval()
    N = net.cfg.n_obs
    rows, images = [], []
    present = [r for r in recordings if (folder / r.file).is_file()]
    for j, rec in enumerate(present):
        row: dict[str, Any] = {"recording": rec.file, "note": rec.note}
        try:
            sp = _load(rec, folder, crop)
            T_steps, H, W = sp.shape
            row.update(steps=int(T_steps), size=f"{W}x{H}", mean_rate=float(sp.mean()))
            est = estimate_exposure(sp)
            rev = nominal_rev_per_s(T_steps, max_frames, N)
            src = array_source(sp, 0.0, rev, name=rec.file)
            model, info = build_net_zeta_model(net, zeta, src, window_steps=13, exposure=est.exposure)
            cfg = ReconstructConfig(frames="exr", video=False, max_frames=max_frames, exposure=est.exposure)
            run_dir = out / "runs" / Path(rec.file).stem
            s = reconstruct_stream(src, model, run_dir, cfg, device=device, meta={"exposure_source": "estimated", "exposure_estimate": est.summary(), "zeta": info["zeta"]})
            centres, _ = frame_centres(src.phi_step_rad, AggregateConfig(window_steps=13, stride_deg=31.5, n_obs=N))
            mean_img = 2.0 * sp.mean(0, dtype=np.float64) / est.exposure
            m = {"psnr_tfp": [], "psnr_mean": [], "corr_tfp": [], "corr_mean": [], "psnr_tfp_vs_mean": []}
            first = None
            for i in range(s["frames"]):
                fr = read_exr(run_dir / "frames" / f"{i:06d}.exr", ["T", "R"])
                I = np.stack([sp[c - 6 : c + 7].sum(0) / (13.0 * est.exposure) for c in centres[i : i + N]])  # paper Eq. (3)
                tfp = 2.0 * I.mean(0)
                T = fr["T"].astype(np.float64)
                m["psnr_tfp"].append(_psnr_peak(T, tfp))
                m["psnr_mean"].append(_psnr_peak(T, mean_img))
                m["psnr_tfp_vs_mean"].append(_psnr_peak(tfp, mean_img))
                m["corr_tfp"].append(float(np.corrcoef(T.ravel(), tfp.ravel())[0, 1]))
                m["corr_mean"].append(float(np.corrcoef(T.ravel(), mean_img.ravel())[0, 1]))
                if first is None:
                    first = (tfp, T, fr["R"].astype(np.float64), mean_img)
            row.update(status="ok", frames=s["frames"], nan_frames=s["nan_frames"], finite=bool(s["nan_frames"] == 0), exposure=est.exposure,
                       rev_per_s=rev, zeta=info["zeta"], **{k: float(np.mean(v)) for k, v in m.items()})
            if first is not None:
                images.append((rec.file, first))
        except Exception as exc:  # noqa: BLE001 - a crash is what this command reports
            row.update(status=f"error: {type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}", finite=False)
        rows.append(row)
        if progress:
            progress(j + 1, len(present))
    conf = {"folder": str(folder), "weights": str(weights or DEFAULT_WEIGHTS), "max_frames": max_frames, "crop": crop, "zeta": zeta, "ensemble": ensemble, "n_obs": N,
            "missing": [r.file for r in recordings if r not in present]}
    res = {"rows": rows, "config": conf}
    _figure(images, out / "real.png")
    return res


def _figure(images, path: Path) -> None:
    if not images:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from polinfra.atomic import atomic_path

    cols = ("TFP (2 x window mean)", "T", "R", "spike mean (whole recording)")
    fig, axes = plt.subplots(len(images), 4, figsize=(10, 2.2 * len(images) + 0.4), squeeze=False)
    for r, (name, imgs) in enumerate(images):
        gain = 1.0 / max(float(np.percentile(imgs[0], 99.9)), 1e-6)  # one gain per row, from the TFP image
        for c, im in enumerate(imgs):
            ax = axes[r, c]
            ax.imshow(np.clip(im * gain, 0, 1), cmap="gray", vmin=0, vmax=1)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(name.replace("_", "\n", 1), fontsize=6)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)


def real_markdown(res: dict) -> str:
    """The table of :func:`evaluate_real`."""
    head = ("| recording | status | size | steps | frames | NaN frames | exposure (est.) | PSNR T vs TFP (dB) | PSNR T vs spike mean (dB) | PSNR TFP vs spike mean (dB) | corr T-TFP | corr T-mean |\n"
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")

    def f(v, nd=2):
        return "n/a" if v is None or (isinstance(v, float) and not math.isfinite(v)) else (f"{v:.{nd}f}" if isinstance(v, float) else str(v))

    lines = [f"| {r['recording']} | {r['status']} | {r.get('size', '')} | {r.get('steps', '')} | {r.get('frames', '')} | {r.get('nan_frames', '')} | {f(r.get('exposure'), 3)} | "
             f"{f(r.get('psnr_tfp'))} | {f(r.get('psnr_mean'))} | {f(r.get('psnr_tfp_vs_mean'))} | {f(r.get('corr_tfp'), 3)} | {f(r.get('corr_mean'), 3)} |" for r in res["rows"]]
    c = res["config"]
    tail = f"\nCheckpoint {c['weights']}, network zeta {c['zeta']}, at most {c['max_frames']} frames" + (f", centre crop {c['crop']} px" if c["crop"] else "") + ". No recording has a polarizer: T should equal the TFP image (2 I).\n"
    if c["missing"]:
        tail += f"Missing from {c['folder']}: {', '.join(c['missing'])}.\n"
    return head + "\n".join(lines) + "\n" + tail
