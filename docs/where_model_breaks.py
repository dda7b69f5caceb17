"""Table and plot of docs/where_model_breaks.md: T PSNR / SSIM of the physics solvers and the shipped network
against each group's departure from paper Eq. (1) (3-D object scenes vs layer scenes).

    python docs/where_model_breaks.py --objects out/datasets/objects3d --objects-eval out/evaluate/objects3d \
        --layers out/datasets/eval_paper4 --layers-eval out/evaluate/eval_paper4 --out docs

Reads each evaluation's results.json (``polspike evaluate``) and each group's departure maps (``dop_T``,
``eq12_err`` in its store, written by the full tier for object scenes; layer scenes follow Eq. (1) by
construction, departure 0).  Writes ``where_model_breaks_table.md`` and ``img/where_model_breaks.png``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

METHODS = ("ls", "ridge", "irls", "rwps", "full-norir")
"""Physics solvers and the shipped network (evaluated without RIR, as it was trained)."""


def _departures(dataset: Path) -> dict[str, dict]:
    from polspike.pipeline.inspect import group_names, inspection_data

    out = {}
    for name, gdir, _split in group_names(dataset):
        d = inspection_data(gdir)
        if "eq12_err" in d:
            out[name] = {"dop_T_mean": float(np.nanmean(d["dop_T"])), "eq12_mean": float(np.nanmean(d["eq12_err"])),
                         "eq12_p99": float(np.nanpercentile(d["eq12_err"], 99)), "polT_p99": float(np.nanpercentile(d["polT_model_err"], 99)),
                         "T_mean": float(np.mean(d["T"]))}
        else:
            out[name] = {"dop_T_mean": 0.0, "eq12_mean": 0.0, "eq12_p99": 0.0, "polT_p99": 0.0, "T_mean": float(np.mean(d["T"]))}
    return out


def _scores(eval_dirs: list[Path]) -> dict[tuple[str, str], dict]:
    """Per (group, method) rows of one or more evaluations; "overall" = frame-weighted mean over all groups."""
    out: dict[tuple[str, str], dict] = {}
    for d in eval_dirs:
        for r in json.loads((d / "results.json").read_text())["rows"]:
            if r["group"] != "overall":
                out[(r["group"], r["method"])] = r
    for m in {k[1] for k in out}:
        rs = [r for (g, mm), r in out.items() if mm == m]
        n = np.array([r["n_frames"] for r in rs], float)
        out[("overall", m)] = {k: (float(np.sum(n * np.array([r[k] for r in rs], float)) / n.sum()) if all(r.get(k) is not None for r in rs) else None)
                               for k in ("psnr_T", "ssim_T", "psnr_R", "ssim_R")}
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--objects", type=Path, required=True)
    ap.add_argument("--objects-eval", type=Path, nargs="+", required=True)
    ap.add_argument("--layers", type=Path, required=True)
    ap.add_argument("--layers-eval", type=Path, nargs="+", required=True)
    ap.add_argument("--out", type=Path, default=Path("docs"))
    a = ap.parse_args()
    sets = [("objects3d", _departures(a.objects), _scores(a.objects_eval)), ("layers", _departures(a.layers), _scores(a.layers_eval))]
    methods = [m for m in METHODS if any((g, m) in sc for _, dep, sc in sets for g in dep)]
    head = "| set | group | DoP of T (mean) | Eq. (1) error p99 (mean) | polarized-T model p99 | " + " | ".join(f"{m} T PSNR / SSIM" for m in methods) + " |"
    lines = [head, "|" + "---|" * (5 + len(methods))]
    for label, dep, sc in sets:
        for g, dv in dep.items():
            cells = []
            for m in methods:
                r = sc.get((g, m))
                cells.append("n/a" if r is None else f"{r['psnr_T']:.2f} / {r['ssim_T']:.3f}")
            lines.append(f"| {label} | {g} | {dv['dop_T_mean']:.3f} | {dv['eq12_p99']:.3f} ({dv['eq12_mean']:.4f}) | {dv['polT_p99']:.3f} | " + " | ".join(cells) + " |")
        cells = []
        for m in methods:
            r = sc.get(("overall", m))
            cells.append("n/a" if r is None else f"**{r['psnr_T']:.2f} / {r['ssim_T']:.3f}**")
        lines.append(f"| {label} | overall | | | | " + " | ".join(cells) + " |")
    (a.out / "where_model_breaks_table.md").write_text("\n".join(lines) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    colours = dict(zip(METHODS, ("C0", "C1", "C2", "C3", "k")))  # network: black
    for ax, key, xl in ((axes[0], "eq12_p99", "departure from Eq. (1): p99 worst-phi |I - I_Eq(1)| (radiance)"), (axes[1], "dop_T_mean", "DoP of T alone (mean over pixels)")):
        for label, dep, sc in sets:
            for m in methods:
                xs = [dep[g][key] for g in dep if (g, m) in sc]
                ys = [sc[(g, m)]["psnr_T"] for g in dep if (g, m) in sc]
                ax.scatter(xs, ys, c=colours[m], marker="o" if label == "objects3d" else "s", s=36, label=f"{m} ({label})" if ax is axes[0] else None)
        ax.set_xlabel(xl)
        ax.set_ylabel("T PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6, ncol=2)
    fig.suptitle("T PSNR against the scene's departure from paper Eq. (1) (squares: layer scenes, Eq. (1) exact; circles: 3-D objects)", fontsize=9)
    fig.tight_layout()
    (a.out / "img").mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out / "img" / "where_model_breaks.png", dpi=110)


if __name__ == "__main__":
    main()
