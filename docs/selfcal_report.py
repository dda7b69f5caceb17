"""Measurements behind docs/selfcal.md (self-calibrated zeta and physics-only streaming).

Usage (from the repository root, venv active; one torch thread):

    python docs/selfcal_report.py closed-form                       # closed-form pane groups (tests/recon/_pane_groups.py)
    python docs/selfcal_report.py dataset out/datasets/selfcal_strong [--pane-model M --pane-n N --max-frames 8]   # built groups (docs/selfcal_strong.toml)
    python docs/selfcal_report.py speed GROUP_DIR [WEIGHTS]          # frames/s: physics-only streams vs the network, same run
    python docs/selfcal_report.py twin-heldout                      # 16 random T-dominated narrow glancing closed-form groups:
        # how the 90 deg twin is decided (cone / content / refused) against the truth (not used to choose any threshold)
    python docs/selfcal_report.py fov out/datasets/eval_fresh_val [SPLIT]   # per group: geometry error with the scene's fov
        # given and withheld (fitted, as reconstruct does for a .dat without --fov-deg)
    python docs/selfcal_report.py stress out/datasets/stress BY_REGIME_JSON [FIGURE.png]   # per-group table: calibration
        # (modulating share, cone, glass, geometry and zeta error) beside the PSNRs of
        # `polspike evaluate out/datasets/stress --by-regime --regime-zetas gt,self --no-net --max-frames 3` (its by_regime.json)

Each prints one JSON line per row (stress: then a markdown table) and writes nothing else (stress: the figure, when named).
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
torch.set_num_threads(1)
MAX_FRAMES = 8
"""output frames per group scored by ``dataset`` (``--max-frames N`` overrides)"""


def _psnr_rows(g, sources=("gt", "self"), max_frames=6, **kw) -> dict:
    from reconstruct.evaluate.harness import EvalConfig, evaluate_groups

    row = {}
    for src in sources:
        rep = evaluate_groups([g], EvalConfig(zeta=src, methods="ls,ridge,irls,rwps", max_frames=max_frames, figure_frames=0, **kw))
        for rr in rep.rows:
            if rr["group"] == "overall":
                row[f"{rr['method']}:{src}"] = rr["psnr_T"]
    return row


def _errors_deg(g, r) -> tuple[float, float]:
    """(mean |theta error|, median |phi_perp error| modulo 180) of calibration ``r`` against group ``g``'s true maps, degrees."""
    return float(np.degrees(np.abs(r.theta - g.theta)).mean()), float(np.median(np.degrees(np.abs(np.mod(r.maps.phi_perp - g.maps.phi_perp + np.pi / 2, np.pi) - np.pi / 2))))


def _geometry(g, r, Zs, Zg) -> dict:
    th, pp = _errors_deg(g, r)
    return {
        "tilt_fit_deg": r.tilt_deg,
        "theta_err_deg": th,
        "phi_perp_err_deg_median": pp,
        "zeta_mae": float(np.abs(Zs - Zg).mean()),
        "zeta_mae_rel": float(np.abs(Zs - Zg).mean() / Zg.mean()),
        "z": r.diagnostics["z"],
    }


def closed_form() -> None:
    from reconstruct.pane.selfcal import group_self_zeta
    from tests.recon._pane_groups import make_pane_group

    for tilt, az, rg in [(35, 20, 3.0), (55, 120, 3.0), (70, 250, 3.0), (55, 300, 5.0), (45, 200, 2.0)]:
        g, N = make_pane_group(tilt, az, r_gain=rg, seed=tilt)
        t0 = time.perf_counter()
        Zs = group_self_zeta(g, 1.5, "single")  # the groups' glass, given (as when docs/selfcal.md was measured)
        r = group_self_zeta.last
        row = {"tilt": tilt, "axis": az, "r_gain": rg, "ok": r.ok, "calib_s": time.perf_counter() - t0}
        if r.ok:
            row["normal_err_deg"] = math.degrees(math.acos(min(1.0, abs(float(r.normal @ N)))))
            row.update(_geometry(g, r, Zs, g.gt_zeta))
        row.update(_psnr_rows(g, self_pane_model="single"))
        print(json.dumps(row), flush=True)


def dataset(path: str, pane_model: str = "single", pane_n: float = 1.5) -> None:
    from reconstruct.evaluate.harness import EvalConfig, group_zeta, load_groups
    from reconstruct.pane.selfcal import group_self_zeta

    for g in load_groups(path, "test", EvalConfig()):
        t0 = time.perf_counter()
        Zs = group_self_zeta(g, pane_n, pane_model)
        r = group_self_zeta.last
        row = {"group": g.name, "fov_deg": g.fov_deg, "pane_model": pane_model, "pane_n": pane_n, "ok": r.ok, "calib_s": time.perf_counter() - t0}
        if r.ok:
            row.update(_geometry(g, r, Zs, group_zeta(g, EvalConfig(zeta="gt"))))
        row.update(_psnr_rows(g, ("gt", "self", "physics"), max_frames=MAX_FRAMES, pane_model=pane_model, pane_n=pane_n, self_pane_model=pane_model))
        print(json.dumps(row), flush=True)


def speed(group_dir: str, weights: str | None = None) -> None:
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.stream.sources import group_source
    from reconstruct.video.physics import build_physics_model
    from reconstruct.video.stream import ReconstructConfig, reconstruct_stream

    src = group_source(group_dir)
    res: dict = {}

    def run(label, model, n):
        s = reconstruct_stream(src, model, f"/tmp/selfcal_speed_{label}", ReconstructConfig(max_frames=n, video=False), device="cpu")
        res[label] = {"frames": s["frames"], "seconds": s["seconds"], "fps": s["frames_per_second_processed"]}
        print(json.dumps({label: res[label]}), flush=True)

    t0 = time.perf_counter()
    m, info = build_physics_model("rwps", "self", src, group_dir=group_dir, rir=True)
    res["selfcal_seconds"] = time.perf_counter() - t0
    run("rwps_self_rir", m, 8)
    m.rir = False
    run("rwps_self_norir", m, 16)
    m2, _ = build_physics_model("ls", "gt", src, group_dir=group_dir, rir=False)
    run("ls_gt_norir", m2, 16)
    net, _ = load_model(Path(weights) if weights else DEFAULT_WEIGHTS, "cpu")
    res["net_weights"] = str(weights or DEFAULT_WEIGHTS)
    run("net", net, 3)
    for k in ("rwps_self_rir", "rwps_self_norir", "ls_gt_norir"):
        res[k]["x_net"] = res[k]["fps"] / res["net"]["fps"]
    print(json.dumps(res), flush=True)


def _calibration_row(g) -> dict:
    from reconstruct.evaluate.harness import EvalConfig, group_zeta
    from reconstruct.pane.selfcal import group_self_zeta

    t0 = time.perf_counter()
    Zs = group_self_zeta(g)
    r = group_self_zeta.last
    sm = r.summary()
    row = {"group": g.name, "ok": r.ok, "calib_s": time.perf_counter() - t0, "z": sm["z"], "twin_ratio": sm["twin_ratio"],
           "modulating_px": sm["modulating_px"], "modulating_blocks": sm["modulating_blocks"], "reason": r.reason}
    if sm["cone"]:
        row["cone"] = {k: sm["cone"].get(k) for k in ("resolved", "by", "v_family", "chosen_family", "tilt_range_deg", "content")}
    if r.ok:
        Zg = group_zeta(g, EvalConfig(zeta="gt"))
        th, pp = _errors_deg(g, r)
        row.update({"tilt_fit_deg": r.tilt_deg, "model": r.model, "n": r.n, "glass_why": (sm["glass"] or {}).get("why"),
                    "glass_content": ((sm["glass"] or {}).get("content") or {}).get("scores"),
                    "theta_err_deg": th, "phi_perp_err_deg_median": pp,
                    "zeta_mae_rel": float(np.abs(Zs - Zg).mean() / Zg.mean())})
    return row


MODULATES_PX = 0.05
"""A group "modulates" when at least this share of its pixels modulates above 3 noise sigmas (SelfCalResult.diagnostics['modulating_px'])."""


def _short_reason(row) -> str:
    if row["ok"]:
        return "calibrated" + ((" (content)" if row["cone"].get("by") == "content" else " (cone)") if "cone" in row else "")
    r = row["reason"]
    return "refused: nothing modulates" if r.startswith("nothing") else "refused: 90 deg ambiguous" if r.startswith("ambiguous") else "refused: " + r[:40]


def stress(path: str, by_regime_json: str, figure: str | None = None) -> None:
    from reconstruct.evaluate.harness import EvalConfig, load_groups

    psnr = {g["group"]: g for g in json.loads(Path(by_regime_json).read_text())["groups"]}
    rows = []
    for g in load_groups(path, "test", EvalConfig()):
        row = _calibration_row(g)
        row["psnr"] = {k: v for k, v in psnr.get(g.name, {}).items() if "@" in k}
        print(json.dumps(row), flush=True)
        rows.append(row)
    sol = ("ls", "ridge", "irls", "rwps")
    print("\n| group | modulating px (%) | self zeta | theta err (deg) | zeta err (rel) | model, n | " + " | ".join(f"{m} gt / self" for m in sol) + " |")
    print("|---|---:|---|---:|---:|---|" + "---|" * len(sol))
    for r in rows:
        p = r["psnr"]
        print(f"| {r['group']} | {100 * r['modulating_px']:.1f} | {_short_reason(r)} | "
              + (f"{r['theta_err_deg']:.2f} | {r['zeta_mae_rel']:.3f} | {r['model']} {r['n']:g} | " if r["ok"] else "- | - | - | ")
              + " | ".join(f"{p.get(m + '@gt', float('nan')):.2f} / {p.get(m + '@self', float('nan')):.2f}" for m in sol) + " |")
    mod = [r for r in rows if r["modulating_px"] >= MODULATES_PX]
    cal = [r for r in mod if r["ok"]]
    d = {m: [r["psnr"][m + "@self"] - r["psnr"][m + "@gt"] for r in cal] for m in sol}
    print(f"\nmodulating groups (>= {100 * MODULATES_PX:g} % of pixels): {len(mod)} of {len(rows)}; calibrated: {len(cal)} of them "
          f"(and {sum(r['ok'] for r in rows) - len(cal)} of the others); self - gt (dB) over the calibrated modulating groups: "
          + ", ".join(f"{m} min {min(v):+.2f} mean {np.mean(v):+.2f}" for m, v in d.items() if v))
    if figure:
        _stress_figure(rows, figure)


def _stress_figure(rows, figure: str) -> None:
    import matplotlib.pyplot as plt

    from polinfra.plotting import save_figure

    sol = ("ls", "ridge", "irls", "rwps")
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    names = [r["group"].replace("refl-", "").replace("_motion-", " ").replace("_light-", " ").replace("_inc-", " ").replace("_pane-", " ") for r in rows]
    y = np.arange(len(rows))
    for k, m in enumerate(sol):
        d = [r["psnr"].get(m + "@self", np.nan) - r["psnr"].get(m + "@gt", np.nan) for r in rows]
        ax[0].scatter(d, y + 0.18 * (k - 1.5), s=14, label=m)
    ax[0].axvline(-1.0, color="k", lw=0.8, ls="--")
    ax[0].axvline(0.0, color="k", lw=0.5)
    ax[0].set_yticks(y, [f"{n} [{_short_reason(r).replace('refused: ', 'x ')}]" for n, r in zip(names, rows)], fontsize=6)
    ax[0].set_xlabel("PSNR T, self - true zeta (dB); dashed: the 1 dB goal")
    ax[0].set_xlim(-12, 4.5)
    ax[0].legend(fontsize=7)
    ax[1].barh(y, [100 * r["modulating_px"] for r in rows], color=["tab:green" if r["ok"] else "tab:red" for r in rows])
    ax[1].axvline(100 * MODULATES_PX, color="k", lw=0.8, ls="--")
    ax[1].set_yticks(y, [""] * len(rows))
    ax[1].set_xlabel("pixels modulating above 3 sigma (%); green: calibrated, red: refused")
    fig.tight_layout()
    save_figure(fig, figure, dpi=130)


def twin_heldout(n_groups: int = 16, seed: int = 2026) -> None:
    """Closed-form groups where the transmission dominates (R/T 0.04-0.3) in a narrow view (15-25 deg) of a glancing pane
    (66-80 deg), random axis, single or thin slab, exposure 3 or 10, layers sliding 0, 0.2 or 0.5 px per strided frame:
    the family chosen (by the cone, by the content, or refused) against the true phi_perp.
    """
    from reconstruct.pane.selfcal import SelfCalConfig, self_calibrate
    from tests.recon._pane_groups import make_pane_group

    rng = np.random.default_rng(seed)
    for k in range(n_groups):
        tilt, az, fov = float(rng.uniform(66, 80)), float(rng.uniform(0, 360)), float(rng.uniform(15, 25))
        rg, ex, mo = float(rng.uniform(0.15, 0.6)), float(rng.choice([3.0, 10.0])), float(rng.choice([0.0, 0.2, 0.5]))
        model = str(rng.choice(["single", "thin_slab"]))
        g, _ = make_pane_group(tilt, az, fov_deg=fov, r_gain=rg, t_level=1.0, exposure=ex, motion_px=mo, model=model, seed=100 + k, H=64, W=96, M=34)
        r = self_calibrate(g.I, g.phi_nominal, SelfCalConfig(fov_deg=fov, valley_step_deg=4.0))
        cone = r.diagnostics.get("cone") or {}
        row = {"tilt": tilt, "azimuth": az, "fov": fov, "R_over_T": 0.5 * rg, "exposure": ex, "motion_px": mo, "model": model, "twin_ratio": r.twin_ratio,
               "by": cone.get("by"), "content": (cone.get("content") or {}).get("corr_family"), "ok": r.ok, "model_used": r.model}
        if r.ok:
            row["theta_err_deg"], row["phi_perp_err_deg"] = _errors_deg(g, r)
            row["family"] = "right" if row["phi_perp_err_deg"] < 10 else "twin"
        print(json.dumps(row), flush=True)


def fov(path: str, split: str = "test") -> None:
    """Each group calibrated twice, with its scene's field of view given and withheld (fitted, as ``polspike reconstruct``
    does for a .dat without --fov-deg): median phi_perp error and mean theta error against the group's true maps.
    """
    from reconstruct.evaluate.harness import EvalConfig, group_zeta, load_groups
    from reconstruct.pane.selfcal import group_self_zeta

    for g in load_groups(path, split, EvalConfig()):
        row = {"group": g.name, "fov_deg": g.fov_deg}
        for mode in ("scene", "fitted"):
            group_zeta(g, EvalConfig(zeta="self", self_fov=mode))
            r = group_self_zeta.last
            if r.ok:
                th, pp = _errors_deg(g, r)
                row[mode] = {"fov_deg": r.fov_deg, "twin_ratio": r.twin_ratio, "phi_perp_err_deg": pp, "theta_err_deg": th}
            else:
                row[mode] = {"refused": r.reason.split(":")[0]}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    a = sys.argv[1:]
    if not a or a[0] not in ("closed-form", "dataset", "speed", "stress", "twin-heldout", "fov"):
        sys.exit(__doc__)
    if a[0] == "fov":
        fov(a[1], a[2] if len(a) > 2 else "test")
        sys.exit(0)
    if a[0] == "twin-heldout":
        twin_heldout()
        sys.exit(0)
    if a[0] == "stress":
        stress(a[1], a[2], a[3] if len(a) > 3 else None)
        sys.exit(0)
    if a[0] == "closed-form":
        closed_form()
    elif a[0] == "dataset":
        kw = {}
        if "--pane-model" in a:
            kw["pane_model"] = a[a.index("--pane-model") + 1]
        if "--max-frames" in a:
            MAX_FRAMES = int(a[a.index("--max-frames") + 1])
        if "--pane-n" in a:
            kw["pane_n"] = float(a[a.index("--pane-n") + 1])
        dataset(a[1], **kw)
    else:
        speed(a[1], a[2] if len(a) > 2 else None)
