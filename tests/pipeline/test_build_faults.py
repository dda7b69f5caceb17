"""Dataset builds under process pools and real kill -9s: the same bytes as one uninterrupted in-process build.

The kills are injected with the test-only hook of :mod:`polinfra.faults`
(``POLSPIKE_FAULT_AT=POINT[@N]``: the build process SIGKILLs itself at that point), so each one
lands at a precise moment instead of at a polled guess:

* ``atomic:spikes.h5@1`` - inside the first group: its spike store is written but not yet
  renamed into the group's work folder (nothing of the group published);
* ``dataset.publish@1`` - the first group complete and fsynced in ``DIR/.tmp``, just before the
  rename that publishes it;
* ``atomic:dataset.json@2`` - the first group published, ``dataset.json`` being rewritten with
  its record (the temporary file written, the rename not done).

After each kill: nothing partial under a final name, the next build resumes (reusing what was
published) and ends with every file byte-identical to the uninterrupted build.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import pytest

from polspike.pipeline.dataset import build_dataset, file_sha256, verify_dataset, verify_group_files
from polspike.pipeline.manifest import MANIFESTS_DIR, load_manifest

SMALL = MANIFESTS_DIR / "small.toml"
NAMES = [g.name for g in load_manifest(SMALL).groups]


def _bytes(root: Path) -> dict[str, str]:
    """sha256 of every file of a built dataset except build_log.json (wall-clock timings) and the lock."""
    out = {str(p.relative_to(root)): file_sha256(p) for p in sorted(root.rglob("*")) if p.is_file() and p.name not in ("build_log.json", ".lock")}
    assert sum(k.endswith("spikes.h5") for k in out) == len(NAMES), sorted(out)
    return out


def _contents(root: Path) -> dict[str, str]:
    return {g["name"]: g["content_sha256"] for g in json.loads((root / "dataset.json").read_text())["groups"]}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """small.toml built once without interruption, in this process, one worker."""
    out = tmp_path_factory.mktemp("ref") / "small"
    build_dataset(SMALL, out)
    return out


def test_spawn_pool_of_two_workers_gives_the_in_process_bytes(reference, tmp_path):
    """workers=2: a spawn-context process pool builds the groups in other interpreters, two at a time."""
    r = build_dataset(SMALL, tmp_path / "pool", workers=2, poll_s=0.05)
    assert sorted(r["built"]) == sorted(NAMES)
    log = json.loads((tmp_path / "pool" / "build_log.json").read_text())
    assert log["executor"] == "local" and log["workers"] == 2
    assert _contents(tmp_path / "pool") == _contents(reference)
    assert _bytes(tmp_path / "pool") == _bytes(reference)


def _killed_build(polspike_cli, out: Path, point: str):
    r = polspike_cli("dataset", "build", SMALL, "--out", out, "--quiet", env={"POLSPIKE_FAULT_AT": point}, timeout=300)
    assert r.returncode == -signal.SIGKILL, (point, r.returncode, r.stderr[-800:])  # killed, not finished or failed
    return r


def _visible_groups_verify(out: Path) -> list[str]:
    visible = sorted(p.name for p in (out / "groups").iterdir()) if (out / "groups").is_dir() else []
    for n in visible:
        assert verify_group_files(out / "groups" / n) == [], n
    return visible


@pytest.mark.parametrize("point", ["atomic:spikes.h5@1", "dataset.publish@1", "atomic:dataset.json@2"])
def test_kill_9_then_resume_gives_the_uninterrupted_bytes(polspike_cli, reference, tmp_path, point):
    out = tmp_path / "k"
    _killed_build(polspike_cli, out, point)
    visible = _visible_groups_verify(out)
    doc = json.loads((out / "dataset.json").read_text())  # never torn: the old or the new version
    assert not doc["complete"]
    if point == "atomic:dataset.json@2":
        # the first group is published and verifies, but the rewrite that records it never landed
        assert visible == [NAMES[0]] and doc["groups"] == []
        assert list(out.glob(".dataset.tmp-*.json")), "the killed rewrite leaves its temporary file"
    else:
        assert visible == []  # killed inside the first group: nothing of it is visible
        work = list((out / ".tmp").glob(f"{NAMES[0]}.*"))
        assert work, "the partial group stays in .tmp"
        if point == "dataset.publish@1":  # complete but unpublished: its checksums were written
            assert any((w / "checksums.json").is_file() for w in work)
    ino = (out / "groups" / NAMES[0] / "spikes.h5").stat().st_ino if visible else None
    r = build_dataset(SMALL, out)
    if visible:
        assert NAMES[0] in r["skipped"] and (out / "groups" / NAMES[0] / "spikes.h5").stat().st_ino == ino
    assert sorted(r["built"] + r["skipped"]) == sorted(NAMES)
    assert verify_dataset(out)["ok"]
    assert not (out / ".tmp").exists()
    assert _bytes(out) == _bytes(reference)


def test_fault_hook_is_inert_without_the_variable(monkeypatch):
    """Unset (or naming another point), a fault point does nothing; set, it is a real SIGKILL."""
    import sys

    from polinfra.faults import ENV, fault_point

    monkeypatch.delenv(ENV, raising=False)
    fault_point("dataset.publish")
    monkeypatch.setenv(ENV, "atomic:other.json")
    fault_point("dataset.publish")
    code = "from polinfra.faults import fault_point\nfault_point('p')\nfault_point('p')\nprint('survived')"
    r = subprocess.run([sys.executable, "-c", code], env={**os.environ, ENV: "p@2"}, capture_output=True, text=True, timeout=60)
    assert r.returncode == -signal.SIGKILL and "survived" not in r.stdout
