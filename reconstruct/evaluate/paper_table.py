"""The test split in the paper's layout: Table 1 (final T of the full network and its three ablations,
with baselines) and supp. Table 3 (each solver: solver-only / final after the same refinement); and the window
analysis of supp. Table 1 (:func:`window_sweep`, ``polspike evaluate --sweep``).

``polspike evaluate-paper DATASET --full CKPT [--full CKPT2] [--no-rir ...] [--no-attention ...]
[--no-conf ...]`` runs :func:`reconstruct.evaluate.harness.evaluate_groups` once per checkpoint and variant
on the same groups and windows (N = 7, dt = 0.65 ms by default), and writes ``paper_table.md``,
``paper_table.csv`` and ``paper_table.json``.  Every column is the mean over the checkpoints given
for it (e.g. two training seeds); the per-checkpoint numbers are listed too.

Columns of Table 1:

* ``TFP``: 2 x the window mean (what the stream shows, reflection included);
* ``Spike mean`` (stored groups): 2 x the spikes per step / exposure over 17.5 ms (the
  "doing nothing" reference);
* ``RWPS (zeta Z)``: the physics solver alone on the zeta source of ``--zeta`` (default ``self``,
  the pane fitted to each group's stream: no oracle);
* ``Ours``: the final output of the ``--full`` checkpoints;
* ``w/o RIR alignment``: the ``--no-rir`` checkpoints (trained without RIR); when none are given,
  the ``--full`` checkpoints with RIR switched off at test time (RIR has no weights; the column
  says "test-time");
* ``w/o Angle attention``: the ``--no-attention`` checkpoints (must be trained so; omitted if none);
* ``w/o conf``: the ``--no-conf`` checkpoints; when none are given, the ``--full`` checkpoints with
  Conf zeroed at test time (marked "test-time": the paper retrains).

Supp. Table 3: for each solver, the ``--full`` checkpoints with that solver before their
refinement (``solver_method`` swapped at load, :data:`reconstruct.evaluate.harness.EvalConfig.net_solver`):
"solver-only" is the solver's output on the learned zeta and w, "final" the refined one.

The paper's own numbers (Table 1, supp. Table 3) are printed beside ours for reference.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

from polinfra.errors import ConfigError
from reconstruct.evaluate.harness import EvalConfig, evaluate_groups, finite_means, load_groups
from reconstruct.physics.rir import RirConfig
from reconstruct.physics.solvers import PHYSICS_SOLVER_CONFIG, SOLVERS, SolverConfig
from reconstruct.stream.groups import EvalGroup

__all__ = ["PAPER_TABLE1", "PAPER_TABLE3", "ABLATIONS", "paper_tables", "paper_markdown", "paper_csv", "window_sweep", "sweep_markdown"]

METRICS = ("psnr_T", "ssim_T", "psnr_R", "ssim_R")

PAPER_TABLE1 = {"Ours": (27.0598, 0.8638), "w/o RIR alignment": (26.7932, 0.8436), "w/o Angle attention": (26.9651, 0.8553), "w/o conf": (26.8910, 0.8470)}
"""Paper Table 1: (PSNR, SSIM) of T on its synthetic test set."""

PAPER_TABLE3 = {"ls": ((16.732, 22.842), (0.617, 0.765)), "ridge": ((18.241, 26.233), (0.654, 0.822)), "irls": ((16.910, 24.121), (0.622, 0.783)), "rwps": ((20.613, 27.060), (0.701, 0.864))}
"""Supp. Table 3: per solver ((PSNR solver-only, final), (SSIM solver-only, final)) of T."""

ABLATIONS = (("Ours", "full"), ("w/o RIR alignment", "no_rir"), ("w/o Angle attention", "no_attention"), ("w/o conf", "no_conf"))
"""(Table 1 column, checkpoint key) of the network columns."""


def _overall(rep, method: str) -> dict[str, float | None]:
    for r in rep.rows:
        if r["group"] == "overall" and r["method"] == method:
            return {k: r[k] for k in METRICS} | {"n_frames": r["n_frames"]}
    raise ConfigError(f"no overall row {method!r} in the evaluation")  # pragma: no cover - evaluate_groups always writes it


def _mean(runs: list[dict]) -> dict[str, float | None]:
    return finite_means(runs, METRICS)


def paper_tables(
    groups: Sequence[EvalGroup],
    checkpoints: dict[str, Sequence[str]],
    cfg: EvalConfig = EvalConfig(zeta="self"),
    solvers: Sequence[str] = SOLVERS,
    solver_cfg: SolverConfig = PHYSICS_SOLVER_CONFIG,
    progress: Callable[[int, int], None] | None = None,
    net_zeta: str = "learned",
) -> dict[str, Any]:
    """Table 1 and supp. Table 3 on ``groups`` (module docstring).

    Args:
        groups: test groups (aggregated with cfg's window and stride).
        checkpoints: {"full": [...], "no_rir": [...], "no_attention": [...], "no_conf": [...]}; "full" required.
        cfg: window, frames, device, tile; ``zeta`` is the physics baseline's zeta source.
        solvers: the solvers of supp. Table 3 (empty: skip it).
        solver_cfg: the physics baseline's solver parameters.
        net_zeta: zeta of every network run: ``learned`` (its own) or ``self`` / ``gt`` / ``physics`` / ``none``
            (:data:`reconstruct.evaluate.harness.EvalConfig.net_zeta`).

    Returns:
        {"table1": {column: {"mean": metrics, "runs": [{"checkpoint", **metrics}], "note"}},
         "table3": {solver: {"solver_only": {...}, "final": {...}}}, "config": ...}.
    """
    full = list(checkpoints.get("full") or [])
    if not full:
        raise ConfigError("the paper table needs at least one --full checkpoint")
    unknown = set(checkpoints) - {k for _, k in ABLATIONS}
    if unknown:
        raise ConfigError(f"unknown checkpoint column(s) {sorted(unknown)}; use {[k for _, k in ABLATIONS]}")
    bad = [s for s in solvers if s not in SOLVERS]
    if bad:
        raise ConfigError(f"unknown solver(s) {bad}; choose from {list(SOLVERS)}")
    if net_zeta not in ("learned", "self", "gt", "physics", "none"):
        raise ConfigError(f"net_zeta {net_zeta!r}: choose learned, self, gt, physics or none")
    base = dataclasses.replace(cfg, figure_frames=0, net_zeta="learned", net_solver="", no_attention=False, no_conf=False, rir=True)
    nz = {"zeta": "learned" if net_zeta == "none" else net_zeta, "net_zeta": net_zeta}  # the network runs: learned (and none) need no per-group zeta
    jobs: list[tuple[str, str, str, EvalConfig]] = []  # (table, column, checkpoint, cfg)
    jobs.append(("table1", "physics", "", dataclasses.replace(base, methods="rwps")))
    for col, key in ABLATIONS:
        ck = list(checkpoints.get(key) or [])
        test_time = not ck and key in ("no_rir", "no_conf")
        for path in ck or (full if test_time else []):
            c = dataclasses.replace(base, methods="full", **nz, checkpoint=str(path), rir=key != "no_rir", no_attention=key == "no_attention", no_conf=key == "no_conf")
            jobs.append(("table1", col + (" (test-time)" if test_time else ""), str(path), c))
    for s in solvers:
        for path in full:
            jobs.append(("table3", s, str(path), dataclasses.replace(base, methods="full", **nz, checkpoint=str(path), net_solver=s)))
    t1: dict[str, dict] = {}
    t3: dict[str, dict] = {}
    tfp = None
    for j, (table, col, path, c) in enumerate(jobs):
        rep = evaluate_groups(groups, c, solver_cfg)
        if table == "table1" and col == "physics":
            tfp = _overall(rep, "tfp")
            t1["TFP"] = {"mean": _mean([tfp]), "runs": [{"checkpoint": "", **tfp}], "note": "2 x window mean"}
            if any(r["method"] == "spike_mean" for r in rep.rows):  # stored groups: the 17.5 ms spike mean ("doing nothing")
                sm = _overall(rep, "spike_mean")
                t1["Spike mean"] = {"mean": _mean([sm]), "runs": [{"checkpoint": "", **sm}], "note": "2 x spikes / step / exposure over 17.5 ms"}
            ph = _overall(rep, "rwps")
            t1[f"RWPS (zeta {c.zeta})"] = {"mean": _mean([ph]), "runs": [{"checkpoint": "", **ph}], "note": "physics solver alone"}
        else:
            label = rep.config["network"]["label"] + ("" if net_zeta == "learned" else f"@{net_zeta}")
            final, solver_only = _overall(rep, label), _overall(rep, label + ":solver")
            if table == "table1":
                e = t1.setdefault(col, {"runs": [], "note": "checkpoint switched at test time, not retrained" if "test-time" in col else ""})
                if col.startswith("w/o RIR") and "test-time" in col and not rep.config["network"]["trained"]["use_rir"]:
                    e["note"] = "the full checkpoint was trained without RIR: this column is it as trained; Ours runs it with RIR (RIR has no weights)"
                e["runs"].append({"checkpoint": path, "label": label, **final})
                e["mean"] = _mean(e["runs"])
            else:
                e = t3.setdefault(col, {"solver_only": {"runs": []}, "final": {"runs": []}})
                e["solver_only"]["runs"].append({"checkpoint": path, "label": label, **solver_only})
                e["final"]["runs"].append({"checkpoint": path, "label": label, **final})
                for st in ("solver_only", "final"):
                    e[st]["mean"] = _mean(e[st]["runs"])
        if progress:
            progress(j + 1, len(jobs))
    conf = {"n_obs": cfg.n_obs, "dt_ms": cfg.dt_ms, "stride_deg": cfg.stride_deg, "max_frames": cfg.max_frames, "physics_zeta": cfg.zeta, "net_zeta": net_zeta,
            "groups": [g.name for g in groups], "checkpoints": {k: list(v) for k, v in checkpoints.items()}, "n_seeds": len(full),
            "net_ensemble": cfg.net_ensemble, "floor": cfg.floor, "floor_anchor": cfg.floor_anchor or ("checkpoint's" if cfg.floor else "")}
    return {"table1": t1, "table3": t3, "config": conf}


def _f(v, nd):
    return "n/a" if v is None else f"{v:.{nd}f}"


def paper_markdown(res: dict) -> str:
    """Table 1 and supp. Table 3 in the paper's layout (metrics as rows), then the per-checkpoint runs."""
    c = res["config"]
    t1, t3 = res["table1"], res["table3"]
    cols = list(t1)
    out = [f"# Test split in the paper's layout (N = {c['n_obs']}, dt = {c['dt_ms']} ms; {len(c['groups'])} groups; network zeta {c.get('net_zeta', 'learned')}"
           + (f", at most {c['max_frames']} frames each" if c["max_frames"] else "") + f"; network columns: mean of {c['n_seeds']} checkpoint(s)"
           + (f", each a self-ensemble of {c['net_ensemble']} symmetries" if c.get("net_ensemble", 1) > 1 else "") + ("; no data-consistency floor" if c.get("floor", True) is False else "") + ")", "",
           "## Table 1", "", "| Metric | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for k, name, nd in (("psnr_T", "PSNR T (dB)", 2), ("ssim_T", "SSIM T", 3), ("psnr_R", "PSNR R (dB)", 2), ("ssim_R", "SSIM R", 3)):
        out.append(f"| {name} | " + " | ".join(_f(t1[col]["mean"][k], nd) for col in cols) + " |")
    out.append("| LPIPS | " + " | ".join("n/a" for _ in cols) + " |")
    notes = [f"{col}: {t1[col]['note']}" for col in cols if t1[col].get("note") and col not in ("TFP",) and not col.startswith("RWPS")]
    if notes:
        out += ["", "Notes: " + "; ".join(notes) + "."]
    out += ["", "Paper Table 1 (its test set, T): " + "; ".join(f"{k} {p:.2f} dB / {s:.3f}" for k, (p, s) in PAPER_TABLE1.items()) + ".",
            "LPIPS needs pretrained backbone weights (no download here). \"test-time\": the switch is turned off on the full checkpoint, not retrained."]
    if t3:
        sv = list(t3)
        out += ["", "## Supp. Table 3 (solver-only / final, T)", "", "| Metric | " + " | ".join(s.upper() if s != "ridge" else "Ridge" for s in sv) + " |", "|---|" + "---:|" * len(sv)]
        for k, name, nd in (("psnr_T", "PSNR T (dB)", 2), ("ssim_T", "SSIM T", 3), ("psnr_R", "PSNR R (dB)", 2), ("ssim_R", "SSIM R", 3)):
            out.append(f"| {name} | " + " | ".join(f"{_f(t3[s]['solver_only']['mean'][k], nd)} / {_f(t3[s]['final']['mean'][k], nd)}" for s in sv) + " |")
        out += ["", "Paper supp. Table 3 (PSNR / SSIM, solver-only / final): " + "; ".join(f"{s} {a[0]:.2f} / {a[1]:.2f} dB, {b[0]:.3f} / {b[1]:.3f}" for s, (a, b) in PAPER_TABLE3.items()) + "."]
    out += ["", "## Per checkpoint", "", "| table | column | checkpoint | PSNR T | SSIM T | PSNR R | SSIM R |", "|---|---|---|---:|---:|---:|---:|"]
    for row in paper_csv(res, header=False):
        tab, col, stage, ck, *m = row
        if ck == "mean":
            continue
        out.append(f"| {tab} | {col}{'' if not stage else ' ' + stage} | {ck or '-'} | " + " | ".join(_f(v, 3 if i % 2 else 2) for i, v in enumerate(m)) + " |")
    return "\n".join(out) + "\n"


def paper_csv(res: dict, header: bool = True) -> list[list]:
    """Rows (table, column, stage, checkpoint or "mean", psnr_T, ssim_T, psnr_R, ssim_R)."""
    rows: list[list] = [["table", "column", "stage", "checkpoint", *METRICS]] if header else []
    for col, e in res["table1"].items():
        for r in e["runs"]:
            rows.append(["table1", col, "", r["checkpoint"], *[r[k] for k in METRICS]])
        rows.append(["table1", col, "", "mean", *[e["mean"][k] for k in METRICS]])
    for s, e in res["table3"].items():
        for st in ("solver_only", "final"):
            for r in e[st]["runs"]:
                rows.append(["table3", s, st, r["checkpoint"], *[r[k] for k in METRICS]])
            rows.append(["table3", s, st, "mean", *[e[st]["mean"][k] for k in METRICS]])
    return rows


def window_sweep(groups: list[EvalGroup] | None, dataset: str, split: str, cfg: EvalConfig, n_values=(5, 7, 9), dt_values=(0.30, 0.65, 1.10), synthetic=None, solver_cfg: SolverConfig = PHYSICS_SOLVER_CONFIG, rir_cfg: RirConfig = RirConfig()) -> list[dict]:
    """Supp. Table 1 analysis: PSNR / SSIM of T for every (N, dt) pair, solvers of cfg.methods.

    Groups are re-aggregated for each dt (the window changes the frames).
    """
    rows = []
    for dt in dt_values:
        c_dt = dataclasses.replace(cfg, dt_ms=float(dt), figure_frames=0)
        gs = load_groups(dataset, split, dataclasses.replace(c_dt, n_obs=max(n_values)), synthetic)
        for n in n_values:
            rep = evaluate_groups(gs, dataclasses.replace(c_dt, n_obs=int(n)), solver_cfg, rir_cfg)
            for r in rep.rows:
                if r["group"] == "overall":
                    rows.append({"n_obs": int(n), "dt_ms": float(dt), **{k: r[k] for k in ("method", "n_frames", "psnr_T", "ssim_T", "psnr_R", "ssim_R")}})
    return rows


def sweep_markdown(rows: list[dict]) -> str:
    """Markdown table of :func:`window_sweep` rows."""
    head = "| N | dt (ms) | method | frames | PSNR T (dB) | SSIM T |\n|---:|---:|---|---:|---:|---:|\n"
    return head + "\n".join(f"| {r['n_obs']} | {r['dt_ms']:.2f} | {r['method']} | {r['n_frames']} | {_f(r['psnr_T'], 2)} | {_f(r['ssim_T'], 3)} |" for r in rows) + "\n"
