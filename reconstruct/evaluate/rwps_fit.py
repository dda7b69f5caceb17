"""Fit the adaptive RWPS constants (Conf -> lambda) on training groups.

The adaptive mapping of :mod:`reconstruct.physics.solvers` (``lambda_map = "adaptive"``) has these
constants: ``snr_kappa`` (the reflection SNR q at which Conf = 1/2), ``lambda_low`` (lambda
where the modulation is strong and well conditioned, Conf -> 1), ``lambda_high`` (the prior's
strength where the system is near-singular, Conf -> 0), the prior itself (``rwps_prior``: toward
zero like ridge, or toward R = T) and the Huber passes (``rwps_irls_iters``; an earlier grid with
3 passes and lambda_low = 0.001 lost everywhere to 0 passes and lambda_low = 0, README).  :func:`fit_rwps` scores every point of a
small grid on the RIR-aligned windows of *training* groups with the true zeta and scores each by
its margin over the better of its neighbours,

    objective = mean_g m_g + 10 mean_g min(0, m_g + 0.3),    m_g = PSNR_rwps(g) - max(PSNR_ls(g), PSNR_ridge(g)),

(PSNR of T, mean over the group's frames): RWPS should win where it can, and every group where it
loses to the better of LS and ridge by more than 0.3 dB costs ten times the excess (the goal is
RWPS >= max(LS, ridge) - 0.3 dB everywhere).  The objective is flat near its top (differences of
0.01-0.1 dB against a standard error over the 40 training groups of ~0.25 dB), so :func:`select_best`
keeps, among the rows within one standard error of the best, the one with the least prior influence
where the data are good (smallest snr_kappa x lambda_high; the training data are mostly dim and say
little about bright, well-conditioned windows, where any leftover lambda only biases R - T).
The pooled prior (``rwps_prior = "pooled"``, ``prior_pool``, ``prior_kappa``) is in the grid beside
the prior toward R = T.  ``polspike fit-rwps DATASET --split train`` runs it and writes the table.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable

import numpy as np
import torch

from reconstruct.evaluate.harness import EvalConfig, group_zeta
from reconstruct.evaluate.metrics import psnr
from reconstruct.physics.rir import RirConfig, estimate_shifts, warp
from reconstruct.physics.solvers import SolverConfig, solve
from reconstruct.stream.groups import EvalGroup

__all__ = ["GRID", "POOLED_ONLY", "aligned_windows", "group_scores", "fit_rwps", "fit_markdown", "select_best"]

GRID: dict[str, tuple] = {
    "snr_kappa": (0.03, 0.1, 0.3, 1.0),
    "lambda_low": (0.0,),
    "lambda_high": (0.3, 1.0),
    "rwps_irls_iters": (0,),
    "rwps_prior": ("equal", "pooled"),
    "prior_pool": (15, 31, 61),
    "prior_kappa": (0.001, 0.003, 0.01),
}
"""Grid searched by :func:`fit_rwps`."""

POOLED_ONLY = ("prior_pool", "prior_kappa")
"""Grid keys that only act with ``rwps_prior = "pooled"``."""


def aligned_windows(groups: list[EvalGroup], cfg: EvalConfig, rir_cfg: RirConfig = RirConfig()) -> dict[str, list[tuple[torch.Tensor, torch.Tensor, np.ndarray]]]:
    """Per group: list of (zeta, I, GT T) windows, RIR-aligned as in :func:`reconstruct.evaluate.harness.evaluate_groups`."""
    K = cfg.n_obs // 2
    dtype = torch.float64 if cfg.dtype == "float64" else torch.float32
    out: dict[str, list] = {}
    for g in groups:
        Z = group_zeta(g, cfg)
        M = g.I.shape[0]
        has = np.ones(M, bool) if g.has_gt is None else g.has_gt
        centres = [i for i in range(K, M - K) if has[i] and g.T is not None]
        if cfg.max_frames:
            centres = centres[: cfg.max_frames]
        items = []
        for i in centres:
            Iw = torch.from_numpy(np.ascontiguousarray(g.I[i - K : i + K + 1])).to(dtype)
            Pw = torch.from_numpy(np.asarray(g.phi_nominal[i - K : i + K + 1], np.float64)).to(dtype)
            Zw = torch.from_numpy(np.ascontiguousarray(Z[i - K : i + K + 1])).to(dtype)
            if cfg.rir and cfg.n_obs > 1:
                sh = estimate_shifts(Iw, Pw, config=rir_cfg).to(dtype)
                Iw, Zw = warp(Iw[None], sh[None])[0], warp(Zw[None], sh[None])[0]
            items.append((Zw, Iw, g.T[i]))
        out[g.name] = items
    return out


def group_scores(windows: dict[str, list], method: str, solver_cfg: SolverConfig) -> dict[str, float]:
    """Mean PSNR of T per group for one solver."""
    res = {}
    for name, items in windows.items():
        if not items:
            continue
        Z = torch.stack([z for z, _, _ in items])
        I = torch.stack([x for _, x, _ in items])
        T = solve(method, Z, I, config=solver_cfg).T.numpy()
        res[name] = float(np.mean([psnr(T[j], items[j][2]) for j in range(len(items))]))
    return res


def fit_rwps(windows: dict[str, list], base: SolverConfig = SolverConfig(), grid: dict = GRID, progress: Callable[[int, int], None] | None = None) -> dict:
    """Grid search of the adaptive constants (module docstring).

    Returns:
        {"best": {constants}, "objective": float, "ls": {...}, "ridge": {...}, "table": [rows],
        "groups": [names]}; each row: the constants, objective, min and mean margin, mean PSNR.
    """
    ls = group_scores(windows, "ls", base)
    ridge = group_scores(windows, "ridge", base)
    ref = {g: max(ls[g], ridge[g]) for g in ls}
    keys = list(grid)
    combos = list(itertools.product(*(grid[k] for k in keys)))
    rows = []
    for j, vals in enumerate(combos):
        c = dict(zip(keys, vals))
        if c["lambda_low"] > c["lambda_high"]:
            continue
        if c.get("rwps_prior", "pooled") != "pooled" and any(c[k] != grid[k][0] for k in POOLED_ONLY if k in c):
            continue  # prior_pool / prior_kappa do nothing without the pooled prior: one row per other prior
        c["rwps_irls_iters"] = int(c["rwps_irls_iters"])
        for k in POOLED_ONLY:
            if k in c:
                c[k] = type(getattr(base, k))(c[k])
        sc = dataclasses.replace(base, lambda_map="adaptive", **c)
        rw = group_scores(windows, "rwps", sc)
        m = np.array([rw[g] - ref[g] for g in ref])
        t = m + 10.0 * np.minimum(0.0, m + 0.3)  # per-group term of the objective
        se = float(t.std(ddof=1) / np.sqrt(len(t))) if len(t) > 1 else 0.0
        rows.append({**c, "objective": float(t.mean()), "objective_se": se, "n_lose": int((m < -0.3).sum()), "min_margin": float(m.min()), "mean_margin": float(m.mean()), "mean_psnr": float(np.mean(list(rw.values())))})
        if progress:
            progress(j + 1, len(combos))
    best = select_best(rows)
    return {"best": {k: best[k] for k in keys}, "objective": best["objective"], "ls": ls, "ridge": ridge, "table": rows, "groups": list(ref)}


def select_best(rows: list[dict]) -> dict:
    """One-standard-error rule: among the rows whose objective is within one standard error (over the
    groups) of the top row's, the one with the least prior influence where the data are good
    (smallest snr_kappa x lambda_high: lambda ~ lambda_high snr_kappa / q at high SNR q), ties by objective.
    """
    top = max(rows, key=lambda r: (r["objective"], r["mean_psnr"]))
    near = [r for r in rows if r["objective"] >= top["objective"] - top.get("objective_se", 0.0)]
    return min(near, key=lambda r: (r.get("snr_kappa", 1.0) * r.get("lambda_high", 1.0), -r["objective"], -r["mean_psnr"]))


def fit_markdown(res: dict, top: int = 12) -> str:
    """The ``top`` rows of a :func:`fit_rwps` result by objective, as a markdown table (every grid key a column)."""
    keys = list(res["best"])
    rows = sorted(res["table"], key=lambda r: -r["objective"])[:top]
    head = "| " + " | ".join(keys) + " | objective | groups losing > 0.3 dB | min margin | mean margin | mean PSNR T |\n"
    head += "|" + "---:|" * len(keys) + "---:|---:|---:|---:|---:|\n"
    fmt = lambda v: f"{v:g}" if isinstance(v, (int, float)) else str(v)  # noqa: E731
    return head + "\n".join("| " + " | ".join(fmt(r[k]) for k in keys) + f" | {r['objective']:.3f} | {r['n_lose']} | {r['min_margin']:.3f} | {r['mean_margin']:.3f} | {r['mean_psnr']:.2f} |" for r in rows) + "\n"
