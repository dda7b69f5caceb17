"""Reproduce the tables of docs/calibrate_pane.md (issue 21).

    PYTHONPATH=. python docs/calibrate_pane_report.py out/datasets/eval_paper [--fov-given] [--solvers] [--frames 40]

For every group of the dataset: calibrate-pane on its spikes (default options; --fov-given passes the
scene's fov), errors of theta / phi_perp against the group's stored maps, the fitted vs true tilt, fov,
n and model; with --solvers, T PSNR of LS / ridge / IRLS / RWPS with zeta from the true maps and from the
fitted maps (same frames, same solver configuration, same run).  Prints one JSON line per group and a
markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--fov-given", action="store_true")
    ap.add_argument("--solvers", action="store_true")
    ap.add_argument("--frames", type=int, default=40)
    a = ap.parse_args()
    from polspike.pipeline.calibrate_pane import CalibratePaneConfig, calibrate_input
    from reconstruct.evaluate import EvalConfig, evaluate_groups
    from reconstruct.groups import load_store_group
    from reconstruct.zeta_source import PaneMaps
    from spike_sim.store import open_group

    rows = []
    for gd in sorted((Path(a.dataset) / "groups").iterdir()):
        spec = json.loads((gd / "group_spec.json").read_text())["scene"]
        t0 = time.time()
        res, _, _, _ = calibrate_input(gd, CalibratePaneConfig(fov_deg=spec["camera"]["fov_deg"] if a.fov_given else 0.0))
        r = res["report"]
        if not res["ok"]:
            rows.append({"group": gd.name, "refused": r["reason"]})
            print(json.dumps(rows[-1]), flush=True)
            continue
        with open_group(gd) as g:
            mp = g.maps()
        th = np.degrees(np.abs(res["maps"]["theta"] - mp["theta"]))
        dp = np.degrees(np.abs(np.mod(res["maps"]["phi_perp"] - mp["phi_perp"] + np.pi / 2, np.pi) - np.pi / 2))
        p, idn = r["params"], r["identifiability"]
        row = {"group": gd.name, "s": round(time.time() - t0, 1), "tilt": [spec["pane"]["tilt_deg"], p["tilt_deg"]], "sigma_tilt": r["uncertainty_1sigma"]["tilt_deg"],
               "fov": [spec["camera"]["fov_deg"], p["fov_deg"]], "theta_err_median": float(np.median(th)), "phi_perp_err_median": float(np.median(dp)),
               "n": [spec["pane"]["n"], p["n"], idn["n"]["identified"]], "model": [spec["pane"]["model"], p["model"], idn["model"]["identified"]]}
        if a.solvers:
            cfg = EvalConfig(zeta="gt", methods="ls,ridge,irls,rwps", max_frames=a.frames, figure_frames=0)
            grp = load_store_group(gd, max_frames=a.frames)
            m = res["maps"]
            fitted = PaneMaps(R_perp=m["R_perp"], R_par=m["R_par"], phi_perp=m["phi_perp"])
            for label, maps in (("true", grp.maps), ("fitted", fitted)):
                rep = evaluate_groups([dataclasses.replace(grp, maps=maps)], cfg)
                row[f"psnr_T_{label}"] = {x["method"]: x["psnr_T"] for x in rep.rows if x.get("group") == "overall"}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| group | tilt true / fitted | 1-sigma | fov true / fitted | theta err | phi_perp err | n true / used (identified) | model true / used (identified) |" + (" delta T PSNR ls / ridge / irls / rwps |" if a.solvers else ""))
    print("|---|---|---|---|---|---|---|---|" + ("---|" if a.solvers else ""))
    for r in rows:
        if "refused" in r:
            print(f"| {r['group']} | refused: {r['refused'][:60]} |")
            continue
        line = (f"| {r['group']} | {r['tilt'][0]:.2f} / {r['tilt'][1]:.2f} | {r['sigma_tilt']:.2f} | {r['fov'][0]:.2f} / {r['fov'][1]:.2f} | {r['theta_err_median']:.3f} | "
                f"{r['phi_perp_err_median']:.3f} | {r['n'][0]:.3f} / {r['n'][1]:.3f} ({r['n'][2]}) | {r['model'][0]} / {r['model'][1]} ({r['model'][2]}) |")
        if a.solvers:
            line += " " + " / ".join(f"{r['psnr_T_fitted'][k] - r['psnr_T_true'][k]:+.2f}" for k in ("ls", "ridge", "irls", "rwps")) + " |"
        print(line)


if __name__ == "__main__":
    main()
