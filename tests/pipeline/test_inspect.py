"""polspike/pipeline/inspect.py and `polspike dataset inspect`: files, wiring, and the physics in the figures' data."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from polinfra.errors import ConfigError, DataFormatError
from polphysics.polarizer import PolarizerConfig
from polphysics.zeta import mix_eq1, stokes_from_layers
from polspike.pipeline.inspect import FIGURES, inspect_group, resolve_group
from spike_sim.config import DEFAULT
from spike_sim.simulate import keyframes_from_arrays, simulate

REPO = Path(__file__).resolve().parents[2]
H, W = 12, 20


def _group(path: Path, seed: int) -> None:
    """A 40 ms group from an analytic source (paper Eq. (1)-(2) Stokes, moving layers, pane maps)."""
    rng = np.random.default_rng(seed)
    K = 3
    T = rng.uniform(0.2, 1.0, (K, H, W)).astype(np.float32)
    R = rng.uniform(0.2, 1.0, (K, H, W)).astype(np.float32)
    theta = np.radians(np.linspace(20, 75, W, dtype=np.float32))[None].repeat(H, 0)
    Rp = (0.05 + 0.3 * (theta - theta.min())).astype(np.float32)
    Rs = (0.3 * Rp).astype(np.float32)
    pp = np.full((H, W), 0.5, np.float32) + np.linspace(0, 0.6, H, dtype=np.float32)[:, None]
    maps = {"theta": theta, "phi_perp": pp, "R_perp": Rp, "R_par": Rs, "T_perp": 1 - Rp, "T_par": 1 - Rs}
    st = np.stack([stokes_from_layers(T[k], R[k], Rp, Rs, 1 - Rp, 1 - Rs, pp) for k in range(K)]).astype(np.float32)
    src = keyframes_from_arrays(np.linspace(0, 0.04, K), st, (T, R), maps, polarizer=PolarizerConfig(phase_deg=12.0, jitter_deg=0.1))
    simulate(src, 0.04, seed, dataclasses.replace(DEFAULT, height=H, width=W, exposure=1.5), out=path, chunk_steps=200, store_zeta=True)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("insp")
    _group(root / "groups" / "a", 1)
    _group(root / "groups" / "b", 2)
    (root / "dataset.json").write_text(json.dumps({"groups": [{"name": "a", "path": "groups/a", "split": "train"}, {"name": "b", "path": "groups/b", "split": "test"}]}))
    return root


def test_figures_and_data_are_consistent(dataset, tmp_path):
    s = inspect_group(dataset, tmp_path / "o", group="b", time_s=0.02, dpi=60)
    out = tmp_path / "o"
    for f in (*FIGURES, "inspect_data.npz", "inspect.json"):
        assert (out / f).is_file() and (out / f).stat().st_size > 1000 or f == "inspect.json", f
    assert not list(out.glob(".*tmp-*"))  # atomic writes leave no temporaries
    assert s["group"] == "b" and abs(s["time_s"] - 0.02) < 2e-3 and s == json.loads((out / "inspect.json").read_text())
    d = dict(np.load(out / "inspect_data.npz"))
    assert 0.0 <= d["dop"].min() and d["dop"].max() <= 1.0
    assert 0.0 <= d["aolp"].min() and d["aolp"].max() < np.pi
    S0, S1, S2 = d["S"]
    assert np.all(S0 + 1e-6 >= np.hypot(S1, S2))  # physical Stokes
    # zeta recomputed from the maps at the frame's true angle equals the stored gt/zeta (float16)
    np.testing.assert_allclose(d["zeta"], d["zeta_stored"], atol=1e-3)
    lo, hi = np.minimum(d["R_perp"], d["R_par"]), np.maximum(d["R_perp"], d["R_par"])
    assert np.all(d["zeta"] >= lo - 1e-6) and np.all(d["zeta"] <= hi + 1e-6)
    # behind the polarizer: Stokes form equals paper Eq. (1) (lossless pane), and the spikes agree on average
    np.testing.assert_allclose(d["mixed_gt"], mix_eq1(d["R"], d["T"], d["zeta"]), atol=1e-5)
    assert abs(float(d["mixed_I"].mean() - d["mixed_gt"].mean())) < 0.03
    assert d["obs_I"].shape == (7, H, W) and d["obs_phi"].shape == (7,)
    step = np.diff(np.unwrap(2 * d["obs_phi"])) / 2
    np.testing.assert_allclose(np.degrees(step), 31.5, atol=0.55)  # the stride between observations, to one step (0.54 deg)
    assert d["raster"].shape[1] == 6 and d["raster"].sum() > 0 and d["raster"].shape[0] == d["raster_t_s"].size


def test_group_directory_and_errors(dataset, tmp_path):
    assert resolve_group(dataset / "groups" / "a") == ("a", dataset / "groups" / "a")
    assert resolve_group(dataset)[0] == "a"
    with pytest.raises(DataFormatError, match="choose --group from: a, b"):
        resolve_group(dataset, "nope")
    with pytest.raises(ConfigError, match="outside"):
        inspect_group(dataset, tmp_path / "o", time_s=5.0)
    r = CliRunner().invoke(__import__("polspike.cli", fromlist=["get_app"]).get_app(), ["dataset", "inspect", str(dataset / "groups" / "a"), "--out", str(tmp_path / "v"), "--video", "--video-frames", "4", "--dpi", "50", "--quiet"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "v" / "video.mp4").stat().st_size > 0 and json.loads((tmp_path / "v" / "inspect.json").read_text())["video_frames"] == 4
    p = subprocess.run([str(Path(sys.executable).parent / "polspike"), "dataset", "inspect", str(dataset), "--group", "nope", "--out", str(tmp_path / "x")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "nope" in lines[0] and "a, b" in lines[0], p.stderr
