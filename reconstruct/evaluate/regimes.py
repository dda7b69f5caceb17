"""Evaluation by regime: groups keyed by their regime tag, tables per regime."""

from __future__ import annotations

import dataclasses
import logging
from collections import defaultdict
from collections.abc import Callable, Iterable

import numpy as np

from polinfra.errors import ConfigError
from reconstruct.evaluate.harness import ANCHOR_SUFFIX, BASELINES, BOUND_GOAL_DB, NET_METHOD, REGIME_FACTORS, SHARE_FRAME_KEYS, SHARE_NOTE, EvalConfig, _fmt, evaluate_groups, parse_methods
from reconstruct.physics.rir import RirConfig
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SOLVERS, SolverConfig
from reconstruct.physics.zeta import ZETA_SOURCES
from reconstruct.stream.groups import EvalGroup

log = logging.getLogger(__name__)


def regime_of(name: str) -> dict[str, str]:
    """{factor: level} parsed from a stress group name (unknown parts are ignored)."""
    out = {}
    for part in name.split("_"):
        f, _, lv = part.partition("-")
        if f in REGIME_FACTORS and lv in REGIME_FACTORS[f]:
            out[f] = lv
    return out


def evaluate_by_regime(
    groups: list[EvalGroup],
    cfg: EvalConfig,
    zetas: Iterable[str] = ("gt", "learned"),
    network: bool = True,
    solver_cfg: SolverConfig = PHYSICS_SOLVER_CONFIG,
    rir_cfg: RirConfig = RirConfig(),
    progress: Callable[[int, int], None] | None = None,
    net_zetas: Iterable[str] = ("learned",),
) -> dict:
    """Every solver with every zeta source (by name, :data:`reconstruct.physics.zeta.ZETA_SOURCES`),
    the baselines and the network (``cfg.checkpoint``; once per zeta of ``net_zetas``: ``learned``
    = its own, columns ``net`` / ``net:solver``; others, e.g. ``self``, columns ``net@self`` /
    ``net:solver@self``) on each group, then one row per regime level.

    Returns:
        {"columns": [...], "groups": [{"group", "regime", column: PSNR T}], "rows": [{"regime",
        "n_groups", column: mean PSNR T over the level's groups}], "ssim": same for SSIM T,
        "rows_R" / "ssim_R": same for R (None where a column has no R, e.g. the baselines),
        "groups_R": per-group {column: [PSNR R, SSIM R]},
        "rows_R_share" / "ssim_R_share": PSNR / SSIM of R over the pixels with reflected share rho >= 0.2
        (:data:`SHARE_KEYS`), each row also with the level's mean of :data:`SHARE_FRAME_KEYS` (fraction of
        such pixels, R bound of the LS with the true zeta, ...) and "n_bound" / "n_bound_ge_22" (groups with
        a bound / with a bound >= :data:`BOUND_GOAL_DB`), "groups_R_share": per-group {column:
        [PSNR, SSIM]} of that, "groups_share": per-group :data:`SHARE_FRAME_KEYS`}.
    """
    zetas = list(dict.fromkeys(zetas))
    net_zetas = list(dict.fromkeys(net_zetas)) if network else []
    bad = [z for z in zetas if z not in ZETA_SOURCES] + [z for z in net_zetas if z not in (*ZETA_SOURCES, "none")]
    if bad:
        raise ConfigError(f"unknown zeta source(s) {bad}; choose from {list(ZETA_SOURCES)} (network columns also none)")
    solvers = [m for m in parse_methods(cfg.methods) if m in SOLVERS] or list(SOLVERS)
    keys = ("psnr_T", "ssim_T", "psnr_R", "ssim_R", "psnr_R_share", "ssim_R_share")
    per: dict[str, dict[str, dict[str, float]]] = {k: defaultdict(dict) for k in keys}
    gshare: dict[str, dict] = {}  # per group: SHARE_FRAME_KEYS (method-independent; from the first run that has them)
    columns: list[str] = []  # baselines first, in BASELINES order, where the groups have them (spike_mean: stored groups)
    runs = [(z, solvers, None) for z in zetas] + [(None, [NET_METHOD], nz) for nz in net_zetas]
    for j, (z, methods, nz) in enumerate(runs):
        c = dataclasses.replace(cfg, zeta=z or "gt", methods=",".join(methods), figure_frames=0, **({} if nz is None else {"net_zeta": nz}))
        rep = evaluate_groups(groups, c, solver_cfg, rir_cfg)
        for r in rep.rows:
            if r["group"] == "overall":
                continue
            m = r["method"]
            if m in BASELINES:
                if j > 0:
                    continue
                col = m
            elif z is None:
                anch = m.endswith(ANCHOR_SUFFIX)
                col = ("net:solver" if ":solver" in m else "net") + ("" if nz == "learned" else f"@{nz}") + (ANCHOR_SUFFIX if anch else "")
            else:
                col = f"{m}@{z}"
            for k in keys:
                per[k][r["group"]][col] = r[k]
            if r.get("share_frac") is not None and r["group"] not in gshare:
                gshare[r["group"]] = {k: r.get(k) for k in SHARE_FRAME_KEYS}
            if col not in columns:
                columns.append(col)
        columns.sort(key=lambda c: BASELINES.index(c) if c in BASELINES else len(BASELINES))  # stable: the rest keep their order
        if progress:
            progress(j + 1, len(runs))
    grows = [{"group": g, "regime": regime_of(g), **v} for g, v in per["psnr_T"].items()]
    out_rows: dict[str, list] = {k: [] for k in keys}
    for f, levels in REGIME_FACTORS.items():
        for lv in levels:
            names = [g["group"] for g in grows if g["regime"].get(f) == lv]
            if not names:
                continue
            sh = {k: _mean_or_none([gshare.get(n, {}).get(k) for n in names]) for k in SHARE_FRAME_KEYS}
            bnd = [gshare[n]["psnr_R_bound"] for n in names if gshare.get(n, {}).get("psnr_R_bound") is not None]
            sh.update(n_bound=len(bnd), n_bound_ge_22=sum(b >= BOUND_GOAL_DB for b in bnd))  # a dB mean hides -50 dB groups
            for k in keys:
                extra = sh if k.endswith("_share") else {}
                out_rows[k].append({"regime": f"{f}={lv}", "n_groups": len(names), **{c: _mean_or_none([per[k][n].get(c) for n in names]) for c in columns}, **extra})
    groups_R = {g["group"]: {c: [per["psnr_R"][g["group"]].get(c), per["ssim_R"][g["group"]].get(c)] for c in columns} for g in grows}
    groups_R_share = {g["group"]: {c: [per["psnr_R_share"][g["group"]].get(c), per["ssim_R_share"][g["group"]].get(c)] for c in columns} for g in grows}
    groups_share = {g["group"]: gshare.get(g["group"], {k: None for k in SHARE_FRAME_KEYS}) for g in grows}
    return {"columns": columns, "groups": grows, "rows": out_rows["psnr_T"], "ssim": out_rows["ssim_T"], "rows_R": out_rows["psnr_R"], "ssim_R": out_rows["ssim_R"], "groups_R": groups_R,
            "rows_R_share": out_rows["psnr_R_share"], "ssim_R_share": out_rows["ssim_R_share"], "groups_R_share": groups_R_share, "groups_share": groups_share}


def _mean_or_none(v: list) -> float | None:
    v = [x for x in v if x is not None and np.isfinite(x)]
    return float(np.mean(v)) if v else None


def regime_markdown(res: dict, metric: str = "rows") -> str:
    """Markdown table of :func:`evaluate_by_regime` rows: ``metric`` = "rows" (PSNR of T, dB, the default),
    "ssim" (SSIM of T), "rows_R" (PSNR of R, dB), "ssim_R" (SSIM of R), "rows_R_share" / "ssim_R_share" (R over
    the pixels with reflected share >= 0.2, led by their fraction and the R bound); n/a where a column has no value.
    """
    cols = res["columns"]
    rows = res.get(metric)
    if rows is None:
        raise ConfigError(f"no {metric!r} table in this result; choose rows, ssim, rows_R, ssim_R, rows_R_share or ssim_R_share")
    nd = 3 if metric.startswith("ssim") else 2
    if metric.endswith(("_R", "_R_share")):  # the baselines estimate no R
        cols = [c for c in cols if any(r.get(c) is not None for r in rows)]
    extra = SHARE_EXTRA if metric.endswith("_share") else ()
    head = "| regime | groups | " + "".join(f"{t} | " for t, _ in extra) + " | ".join(cols) + " |\n|---|---:|" + "---:|" * (len(extra) + len(cols)) + "\n"
    return head + "\n".join(f"| {r['regime']} | {r['n_groups']} | " + "".join(f"{fm(r)} | " for _, fm in extra) + " | ".join(_fmt(r[c], nd) for c in cols) + " |" for r in rows) + "\n"


SHARE_EXTRA = (
    ("rho>=0.2 frac", lambda r: _fmt(r.get("share_frac"), 3)),
    ("R bound (LS, true zeta)", lambda r: _fmt(r.get("psnr_R_bound"), 2)),
    ("groups with bound >= 22 dB", lambda r: "n/a" if not r.get("n_bound") else f"{r['n_bound_ge_22']}/{r['n_bound']}"),
    ("rho>=0.2 px with bound >= 22 dB", lambda r: _fmt(r.get("bound_frac_22"), 3)),
    ("flat R (oracle level)", lambda r: _fmt(r.get("psnr_R_flat"), 2)),
)
"""Leading columns of the reflected-share tables: (title, formatter of the row)."""


REGIME_TABLES = (("rows", "PSNR of T (dB)"), ("ssim", "SSIM of T"), ("rows_R", "PSNR of R (dB)"), ("ssim_R", "SSIM of R"),
                 ("rows_R_share", "PSNR of R where the reflection is >= 20 % of the light (dB)"), ("ssim_R_share", "SSIM of R where the reflection is >= 20 % of the light"))
"""The tables of ``by_regime.md``: (key of :func:`evaluate_by_regime`'s result, title)."""


def regime_report(res: dict) -> str:
    """``by_regime.md``: the per-regime tables (PSNR / SSIM of T, of R, and of R where the reflected share is >= 0.2)."""
    return "\n".join(f"## {title} per regime level\n\n" + regime_markdown(res, key) for key, title in REGIME_TABLES if res.get(key) is not None) + f"\n{SHARE_NOTE}\n"
