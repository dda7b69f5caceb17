"""Dataset builds: small.toml builds and verifies, local and Dask executors give the same content
checksums, finished groups are skipped by checksum, a kill -9 mid-group resumes cleanly, a corrupted
byte is named by verify (exit 2, one line) and repaired by the next build.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from polinfra.errors import OutputError
from polspike.pipeline.dataset import BuildCallbacks, build_dataset, content_sha256, verify_dataset, verify_group_files
from polspike.pipeline.manifest import MANIFESTS_DIR, dump_manifest, load_manifest

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-c", "from polspike.cli import app; app()"]
SMALL = MANIFESTS_DIR / "small.toml"


def _contents(root: Path) -> dict[str, str]:
    doc = json.loads((root / "dataset.json").read_text())
    return {g["name"]: g["content_sha256"] for g in doc["groups"]}


def _bytes(root: Path) -> dict[str, str]:
    """sha256 of every file of a built dataset except build_log.json (the one file with timings)."""
    from polspike.pipeline.dataset import file_sha256

    out = {str(p.relative_to(root)): file_sha256(p) for p in sorted(root.rglob("*")) if p.is_file() and p.name not in ("build_log.json", ".lock")}
    assert any(k.endswith("spikes.h5") for k in out)
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """small.toml built once, in this process (local executor, one worker)."""
    out = tmp_path_factory.mktemp("ds") / "small"
    events = []
    r = build_dataset(SMALL, out, callbacks=BuildCallbacks(overall=lambda d, t: events.append((d, t))))
    assert sorted(r["built"]) == sorted(g.name for g in load_manifest(SMALL).groups)
    assert events[-1][0] == events[-1][1] > 0  # overall progress reaches the total
    return out


def test_small_builds_and_verifies(built):
    doc = json.loads((built / "dataset.json").read_text())
    assert doc["complete"] and doc["format"] == "polspike-dataset/1"
    assert (built / "manifest.toml").read_bytes() == SMALL.read_bytes()
    assert not (built / ".tmp").exists()
    r = verify_dataset(built)
    assert r == {"ok": True, "bad": {}, "problems": [], "n_groups": 3}
    for g in doc["groups"]:
        gd = built / g["path"]
        assert sorted(p.name for p in gd.iterdir()) == ["checksums.json", "group.json", "group_spec.json", "spikes.h5"]
        assert content_sha256(gd) == g["content_sha256"]


def test_dataset_json_is_read_by_the_reconstructor(built):
    from reconstruct.stream.groups import list_groups, load_store_group

    train = list_groups(built, "train")
    test = list_groups(built, "test")
    assert [n for n, _ in train] == ["train_brewster", "train_oblique"]
    assert [n for n, _ in test] == ["test_near_normal"]
    eg = load_store_group(test[0][1])
    assert eg.I.shape[1:] == (40, 64) and eg.T is not None and eg.maps is not None
    assert eg.has_gt.any()
    assert np.isfinite(eg.I).all() and float(eg.I.mean()) > 0.0


def test_dask_local_cluster_matches_local_checksums(built, tmp_path):
    distributed = pytest.importorskip("distributed")
    # processes=False: one in-process worker with 2 threads keeps the test fast (about 1 s to start);
    # the build connects to it by its scheduler address, as `--scheduler ADDR` does to a real cluster,
    # and runs the same task function a process-based cluster runs.
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        r = build_dataset(SMALL, tmp_path / "dask", executor="dask", scheduler=cluster.scheduler_address, workers=2, poll_s=0.05)
    assert len(r["built"]) == 3
    assert _contents(tmp_path / "dask") == _contents(built)
    # byte identity: every file but build_log.json, including spikes.h5 and dataset.json
    assert _bytes(tmp_path / "dask") == _bytes(built)
    assert verify_dataset(tmp_path / "dask")["ok"]


def test_group_files_hold_no_wall_clock_timings(built):
    import h5py

    log_doc = json.loads((built / "build_log.json").read_text())
    assert log_doc["groups"]["train_brewster"]["total_s"] > 0  # the timings live here
    for gd in sorted((built / "groups").iterdir()):
        gj = json.loads((gd / "group.json").read_text())
        assert gj["summary"]["group_dir"] == f"groups/{gd.name}"
        assert not {"seconds", "sim_seconds", "pixel_steps_per_s"} & set(gj["summary"]), gd.name
        with h5py.File(gd / "spikes.h5", "r") as f:
            summ = json.loads(f.attrs["summary_json"])
            assert not {"group_dir", "seconds", "sim_seconds", "pixel_steps_per_s"} & set(summ)
            objs = [f["spikes"], f["maps"], f["gt/T"], f["polarizer"]]
            # no object timestamps: HDF5 reports 0 for an object whose times are not tracked
            assert all(h5py.h5g.get_objinfo(f.id, o.name.encode()).mtime == 0 for o in objs)


def test_rebuild_skips_finished_groups_by_checksum(built, tmp_path):
    out = tmp_path / "copy"
    shutil.copytree(built, out)
    ino = {p.name: (p / "spikes.h5").stat().st_ino for p in (out / "groups").iterdir()}
    r = build_dataset(SMALL, out)
    assert r["built"] == [] and len(r["skipped"]) == 3
    assert {p.name: (p / "spikes.h5").stat().st_ino for p in (out / "groups").iterdir()} == ino
    # a finished group whose settings changed is rebuilt, the others stay
    data = tomllib.loads(SMALL.read_text())
    data["groups"][1]["seed"] = 99
    changed = tmp_path / "changed.toml"
    changed.write_text(dump_manifest(data))  # scenes/... paths resolve from the repo root
    r = build_dataset(changed, out)
    assert r["built"] == ["train_oblique"]
    assert _contents(out)["train_brewster"] == _contents(built)["train_brewster"]
    assert _contents(out)["train_oblique"] != _contents(built)["train_oblique"]


def test_corrupted_byte_is_named_by_verify_and_rebuilt(built, tmp_path):
    out = tmp_path / "bad"
    shutil.copytree(built, out)
    h5 = out / "groups" / "train_oblique" / "spikes.h5"
    raw = bytearray(h5.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    h5.write_bytes(bytes(raw))
    r = verify_dataset(out)
    assert not r["ok"] and list(r["bad"]) == ["train_oblique"]
    assert any("sha256" in e for e in r["bad"]["train_oblique"])
    cli = subprocess.run(CLI + ["dataset", "verify", str(out)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert cli.returncode == 2
    lines = [ln for ln in cli.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "train_oblique" in lines[0] and "train_brewster" not in lines[0], cli.stderr
    ok = subprocess.run(CLI + ["dataset", "verify", str(built)], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert ok.returncode == 0 and "ok" in ok.stdout
    r = build_dataset(SMALL, out)
    assert r["built"] == ["train_oblique"] and len(r["skipped"]) == 2
    assert _contents(out) == _contents(built)
    assert verify_dataset(out)["ok"]


def test_build_resumes_after_kill_9_mid_group(tmp_path):
    data = tomllib.loads(SMALL.read_text())
    data["defaults"]["duration_s"] = 0.4  # long enough to be killed inside the second group
    man = tmp_path / "kill.toml"
    man.write_text(dump_manifest(data))
    out = tmp_path / "k"
    names = [g["name"] for g in data["groups"]]
    proc = subprocess.Popen(CLI + ["dataset", "build", str(man), "--out", str(out), "--quiet"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline:
            if (out / "groups" / names[0]).exists() and any((out / ".tmp").glob(f"{names[1]}.*/.spikes.tmp-*")):
                break
            if proc.poll() is not None:
                pytest.fail(f"build ended before the kill: {proc.stderr.read().decode()[-400:]}")
            time.sleep(0.02)
        else:
            pytest.fail("the build never reached the second group")
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    # nothing partial under a final name: every visible group verifies
    visible = sorted(p.name for p in (out / "groups").iterdir())
    assert names[0] in visible and names[2] not in visible
    for n in visible:
        assert verify_group_files(out / "groups" / n) == [], n
    assert list((out / ".tmp").iterdir())  # the partial group is left in .tmp
    ino = (out / "groups" / names[0] / "spikes.h5").stat().st_ino
    doc = json.loads((out / "dataset.json").read_text())
    assert not doc["complete"]
    r = build_dataset(man, out)
    assert names[0] in r["skipped"] and names[2] in r["built"]
    assert (out / "groups" / names[0] / "spikes.h5").stat().st_ino == ino
    assert verify_dataset(out)["ok"]
    assert not (out / ".tmp").exists()
    # the resumed build has the bytes of an uninterrupted one (every file except build_log.json)
    build_dataset(man, tmp_path / "straight")
    assert _bytes(out) == _bytes(tmp_path / "straight")


def test_second_build_on_the_same_folder_is_refused(built, tmp_path):
    import fcntl

    out = tmp_path / "locked"
    out.mkdir()
    with open(out / ".lock", "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        with pytest.raises(OutputError, match="another build"):
            build_dataset(SMALL, out)


def test_bench_dataset_cli_json(tmp_path):
    r = subprocess.run(
        CLI + ["bench", "dataset", "--json", "--out", str(tmp_path), "--width", "32", "--height", "20", "--duration-s", "0.02"],
        capture_output=True, text=True, cwd=REPO, timeout=300,
    )
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res == json.loads((tmp_path / "bench_dataset.json").read_text())
    (row,) = res["rows"]
    assert row["tier"] == "analytic" and row["scaled"] is True
    assert row["s_per_1s_group"] > 0 and row["bytes_per_1s_group"] > row["bytes_measured"] > 0 and row["peak_rss_mib"] > 50


@pytest.mark.slow
def test_process_pool_and_process_cluster_match(built, tmp_path):
    """The spawn process pool and a process-based Dask LocalCluster (slow to start) give the same content."""
    r = build_dataset(SMALL, tmp_path / "pool", workers=2, poll_s=0.1)
    assert len(r["built"]) == 3
    assert _contents(tmp_path / "pool") == _contents(built)
    assert _bytes(tmp_path / "pool") == _bytes(built)
    pytest.importorskip("distributed")
    r = build_dataset(SMALL, tmp_path / "cluster", workers=2, executor="dask", poll_s=0.1)
    assert len(r["built"]) == 3
    assert _contents(tmp_path / "cluster") == _contents(built)
    assert _bytes(tmp_path / "cluster") == _bytes(built)


@pytest.mark.slow
@pytest.mark.mitsuba
def test_maps_tier_group_builds_and_verifies(tmp_path):
    """A tiny maps-tier group: Mitsuba renders the pane maps into DIR/.tmp, which is removed after."""
    from _mitsuba_common import require_mitsuba

    require_mitsuba()
    data = {
        "name": "maps",
        "defaults": {"duration_s": 0.01, "camera": {"width": 24, "height": 16}, "render": {"spp": 1}},
        "groups": [
            {"name": "m0", "split": "train", "scene": "brewster", "tier": "maps"},
            {"name": "a0", "split": "test", "scene": "brewster", "tier": "analytic",
             "layers": {"transmission": {"source": "skimage:rocket"}, "reflection": {"source": "procedural:rings", "sprites": []}}},
        ],
    }
    man = tmp_path / "maps.toml"
    man.write_text(dump_manifest(data))
    r = build_dataset(man, tmp_path / "d")
    assert sorted(r["built"]) == ["a0", "m0"]
    assert verify_dataset(tmp_path / "d")["ok"]
    assert not (tmp_path / "d" / ".tmp").exists()


def test_too_little_disk_space_is_refused_before_building(tmp_path, monkeypatch):
    import collections

    import polspike.pipeline.dataset as ds

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(ds.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 1000, 1000))
    with pytest.raises(OutputError, match="GB free"):
        build_dataset(SMALL, tmp_path / "full")
    assert not any((tmp_path / "full" / "groups").iterdir())


def test_cli_build_with_progress_bars_and_verify_partial(built, tmp_path):
    from typer.testing import CliRunner

    from polspike.cli import get_app

    runner = CliRunner()
    out = tmp_path / "one"
    r = runner.invoke(get_app(), ["dataset", "build", str(SMALL), "--out", str(out), "--group", "test_near_normal"])
    assert r.exit_code == 0, r.output
    text = " ".join(r.output.split())  # rich wraps long lines
    assert "built test_near_normal" in text and "built 1, skipped 0" in text
    assert _contents(out) == {"test_near_normal": _contents(built)["test_near_normal"]}
    r = runner.invoke(get_app(), ["dataset", "verify", str(out), "--partial"])
    assert r.exit_code == 0 and "ok: 1 groups" in " ".join(r.output.split())


@pytest.mark.slow
@pytest.mark.mitsuba
def test_mitsuba_tier_groups_are_byte_identical_in_process_and_in_a_pool(tmp_path):
    """maps, full and a 3-D object scene (full) groups: the same bytes in this process and on a spawn pool."""
    from _mitsuba_common import require_mitsuba

    require_mitsuba()
    man = {
        "format": "polspike-manifest/1", "name": "mi", "description": "Mitsuba tiers, byte identity",
        "defaults": {"duration_s": 0.01, "keyframe_fps": 100.0, "camera": {"width": 32, "height": 20}, "spike_sim": {"preset": "default"}},
        "groups": [
            {"name": "maps_brewster", "split": "train", "tier": "maps", "scene": "scenes/brewster.toml", "seed": 1},
            {"name": "full_brewster", "split": "train", "tier": "full", "scene": "scenes/brewster.toml", "seed": 2, "render": {"spp": 8}},
            {"name": "shop", "split": "test", "tier": "full", "scene": "scenes/shop_window.toml", "seed": 3, "render": {"spp": 8}},
        ],
    }
    mpath = tmp_path / "mi.toml"
    mpath.write_text(dump_manifest(man))
    build_dataset(mpath, tmp_path / "a")
    build_dataset(mpath, tmp_path / "b", workers=2, poll_s=0.1)
    assert _bytes(tmp_path / "a") == _bytes(tmp_path / "b")
