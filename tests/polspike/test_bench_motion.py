"""``polspike bench motion`` through the installed console script (tiny configuration)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = Path(sys.executable).parent / "polspike"
CLI = [str(SCRIPT)] if SCRIPT.is_file() else [sys.executable, "-c", "from polspike.cli import app; app()"]


def run(*args):
    return subprocess.run(CLI + list(args), capture_output=True, text=True, cwd=REPO, timeout=900)


@pytest.mark.slow
def test_bench_motion_tiny(tmp_path):
    """Two pans of one scene: JSON, table and plot written, every method scored on T (R for the layered ones), and
    each row's verdict on the project's rule recomputed from its scores (net+floor >= rwps and the spike mean).
    """
    out = tmp_path / "m"
    r = run("bench", "motion", "--out", str(out), "--motions", "pan", "--speeds", "0,3", "--reflections", "weak", "--lights", "bright",
            "--width", "32", "--height", "32", "--methods", "tfp,mean17,rwps,net+floor")
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads((out / "motion.json").read_text())
    rows = {row["speed"]: row for row in res["rows"]}
    assert set(rows) == {0.0, 3.0}
    for row in rows.values():
        assert set(row["scores"]) == {"tfp", "mean17", "rwps", "net+floor"}
        assert all(v["T_psnr"] is not None and 0 < v["T_psnr"] < 100 for v in row["scores"].values())
        assert row["scores"]["tfp"]["R_psnr"] is None and row["scores"]["rwps"]["R_psnr"] is not None
        sc = row["scores"]
        margin = sc["net+floor"]["T_psnr"] - max(sc["rwps"]["T_psnr"], sc["mean17"]["T_psnr"])
        assert row["margin_db"] == pytest.approx(margin) and row["holds"] == (margin >= 0)
        assert row["judged"] == "net+floor" and row["margin_core_db"] == pytest.approx(margin) and row["holds_core"] == (margin >= 0)
    assert "net+floor" in (out / "motion.md").read_text()
    assert (out / "motion.png").stat().st_size > 1000


@pytest.mark.parametrize("args, fragment", [(["--motions", "fly"], "--motions"), (["--speeds", "fast"], "--speeds"), (["--methods", "magic"], "--methods"),
                                            (["--width", "30"], "--width"), (["--calibrate", "never"], "--calibrate"),
                                            (["--rir", "phase"], "--rir")])
def test_bench_motion_bad_input_exit_2_one_line(tmp_path, args, fragment):
    r = run("bench", "motion", "--out", str(tmp_path / "m"), *args)
    assert r.returncode == 2
    assert fragment in r.stderr and "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.splitlines() if ln.strip()]) <= 2
