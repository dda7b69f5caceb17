"""Measurements behind docs/selfcal.md (self-calibrated zeta and physics-only streaming).

Usage (from the repository root, venv active; one torch thread):

    python docs/selfcal_report.py closed-form                       # closed-form pane groups (tests/reconstruct/_pane_groups.py)
    python docs/selfcal_report.py dataset out/datasets/selfcal_strong [--pane-model M --pane-n N --max-frames 8]   # built groups (docs/selfcal_strong.toml)
    python docs/selfcal_report.py speed GROUP_DIR [WEIGHTS]          # frames/s: physics-only streams vs the network, same run

Each prints one JSON line per row and writes nothing else.
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
    from reconstruct.evaluate import EvalConfig, evaluate_groups

    row = {}
    for src in sources:
        rep = evaluate_groups([g], EvalConfig(zeta=src, methods="ls,ridge,irls,rwps", max_frames=max_frames, figure_frames=0, **kw))
        for rr in rep.rows:
            if rr["group"] == "overall":
                row[f"{rr['method']}:{src}"] = rr["psnr_T"]
    return row


def _geometry(g, r, Zs, Zg) -> dict:
    return {
        "tilt_fit_deg": r.tilt_deg,
        "theta_err_deg": float(np.degrees(np.abs(r.theta - g.theta)).mean()),
        "phi_perp_err_deg_median": float(np.median(np.degrees(np.abs(np.mod(r.maps.phi_perp - g.maps.phi_perp + np.pi / 2, np.pi) - np.pi / 2)))),
        "zeta_mae": float(np.abs(Zs - Zg).mean()),
        "zeta_mae_rel": float(np.abs(Zs - Zg).mean() / Zg.mean()),
        "z": r.diagnostics["z"],
    }


def closed_form() -> None:
    from reconstruct.selfcal import group_self_zeta
    from tests.reconstruct._pane_groups import make_pane_group

    for tilt, az, rg in [(35, 20, 3.0), (55, 120, 3.0), (70, 250, 3.0), (55, 300, 5.0), (45, 200, 2.0)]:
        g, N = make_pane_group(tilt, az, r_gain=rg, seed=tilt)
        t0 = time.perf_counter()
        Zs = group_self_zeta(g)
        r = group_self_zeta.last
        row = {"tilt": tilt, "axis": az, "r_gain": rg, "ok": r.ok, "calib_s": time.perf_counter() - t0}
        if r.ok:
            row["normal_err_deg"] = math.degrees(math.acos(min(1.0, abs(float(r.normal @ N)))))
            row.update(_geometry(g, r, Zs, g.gt_zeta))
        row.update(_psnr_rows(g))
        print(json.dumps(row), flush=True)


def dataset(path: str, pane_model: str = "single", pane_n: float = 1.5) -> None:
    from reconstruct.evaluate import EvalConfig, group_zeta, load_groups
    from reconstruct.selfcal import group_self_zeta

    for g in load_groups(path, "test", EvalConfig()):
        t0 = time.perf_counter()
        Zs = group_self_zeta(g, pane_n, pane_model)
        r = group_self_zeta.last
        row = {"group": g.name, "fov_deg": g.fov_deg, "pane_model": pane_model, "pane_n": pane_n, "ok": r.ok, "calib_s": time.perf_counter() - t0}
        if r.ok:
            row.update(_geometry(g, r, Zs, group_zeta(g, EvalConfig(zeta="gt"))))
        row.update(_psnr_rows(g, ("gt", "self", "physics"), max_frames=MAX_FRAMES, pane_model=pane_model, pane_n=pane_n))
        print(json.dumps(row), flush=True)


def speed(group_dir: str, weights: str | None = None) -> None:
    from reconstruct.checkpoint import DEFAULT_WEIGHTS, load_model
    from reconstruct.physics_video import build_physics_model
    from reconstruct.video import ReconstructConfig, group_source, reconstruct_stream

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


if __name__ == "__main__":
    a = sys.argv[1:]
    if not a or a[0] not in ("closed-form", "dataset", "speed"):
        sys.exit(__doc__)
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
