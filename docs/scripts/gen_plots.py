"""Build-time result plots (run by mkdocs-gen-files), drawn from the tables of the pages themselves.

Each figure reads a markdown table of a page (found by its header row), so a figure can never
disagree with the numbers printed beside it. Written to ``img/generated/`` of the built site.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import mkdocs_gen_files  # noqa: E402

DOCS = Path(__file__).resolve().parents[1]
REPO = DOCS.parent


def table(path: Path, header_start: str) -> list[list[str]]:
    """The body rows (cells stripped of markup) of the table whose header row starts with ``header_start``."""
    lines = path.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header_start))
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith("|"):
            break
        rows.append([re.sub(r"[*`]", "", c).strip() for c in ln.strip().strip("|").split("|")])
    return rows


def num(cell: str) -> float:
    m = re.search(r"-?\d+(?:\.\d+)?", cell)
    return float(m.group()) if m else float("nan")


def save(fig, name: str) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    with mkdocs_gen_files.open(f"img/generated/{name}", "wb") as fh:
        fh.write(buf.getvalue())


def solvers_vs_paper() -> None:
    rows = table(DOCS / "results" / "solvers.md", "| method | ours, PSNR / SSIM | paper")
    keep = [r for r in rows if r[2] not in ("-", "")][:4]
    names = [r[0].split(" (")[0] for r in keep]
    ours, paper = [num(r[1]) for r in keep], [num(r[2]) for r in keep]
    fig, ax = plt.subplots(figsize=(6, 3.2))
    x = range(len(names))
    ax.bar([i - 0.2 for i in x], ours, 0.4, label="ours (true zeta)")
    ax.bar([i + 0.2 for i in x], paper, 0.4, label="paper, supp. Table 3")
    tfp = num(next(r for r in rows if r[0].startswith("TFP"))[1])
    ax.axhline(tfp, color="0.4", ls="--", lw=1, label=f"TFP {tfp:.2f}")
    ax.set_xticks(list(x), names)
    ax.set_ylabel("PSNR of T (dB)")
    ax.set_ylim(min(ours + paper) - 3, max(ours + paper) + 2)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("Solver-only, paper-difficulty test split")
    save(fig, "solvers_vs_paper.png")


def stress_levels() -> None:
    rows = table(DOCS / "results" / "stress.md", "| level | TFP | best physics")
    levels = [r[0] for r in rows]
    cols = {"TFP": [num(r[1]) for r in rows], "best physics (self zeta)": [num(r[2]) for r in rows], "network (shipped)": [num(r[3]) for r in rows]}
    fig, ax = plt.subplots(figsize=(8, 3.4))
    w = 0.27
    for j, (lab, vals) in enumerate(cols.items()):
        ax.bar([i + (j - 1) * w for i in range(len(levels))], vals, w, label=lab)
    ax.set_xticks(range(len(levels)), levels, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("PSNR of T (dB)")
    top = max(max(v) for v in cols.values())
    ax.set_ylim(10, top + 6)
    ax.legend(fontsize=8, ncol=3, loc="upper center")
    ax.set_title("The stress set, per level")
    save(fig, "stress_levels.png")


def checkpoints() -> None:
    rows = table(REPO / "CHANGELOG.md", "| checkpoint | test T PSNR")
    names = [r[0] for r in rows]
    t = [num(r[1]) for r in rows]
    r_ = [num(r[3]) for r in rows]
    stress = [num(r[4]) for r in rows]
    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    ax.plot(names, t, "o-", label="test T")
    ax.plot(names, r_, "s-", label="test R")
    ax.plot(names, stress, "^-", label="stress set, mean T")
    ax.axhline(27.06, color="0.4", ls="--", lw=1, label="paper T 27.06")
    ax.set_ylabel("PSNR (dB)")
    ax.legend(fontsize=8)
    ax.set_title("Checkpoints on the paper-difficulty test split")
    save(fig, "checkpoints.png")


solvers_vs_paper()
stress_levels()
checkpoints()
