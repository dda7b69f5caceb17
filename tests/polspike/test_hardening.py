"""Bad input across the CLI and library: one line, exit code 2, nothing half-written; a bounded fuzz."""

from __future__ import annotations

import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from polinfra.errors import PolspikeError

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-c", "from polspike.cli import app; app()"]


def run(args, **kw):
    return subprocess.run(CLI + list(args), capture_output=True, text=True, cwd=REPO, timeout=300, **kw)


def _one_line_exit_2(r):
    assert r.returncode == 2, (r.returncode, r.stdout[-500:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    assert len([ln for ln in r.stderr.strip().splitlines() if ln.strip()]) == 1, r.stderr


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("[camera]\nwidth = 400\nheight = ", "malformed TOML"),  # truncated
        ("[camera\n", "malformed TOML"),
        ("[camera]\nwidht = 3\n", "unknown key camera.widht"),
        ("[camera]\nwidth = 'big'\n", "camera.width"),
        ("[render]\nduration_s = -1\n", "render.duration_s"),
        ("[layers.transmission]\nbrightness = -0.5\n", "brightness"),
        ("[polarizer]\nphase_deg = 1000\n", "polarizer.phase_deg"),
        ("[pane]\ntilt_deg = 95\n", "pane.tilt_deg"),
    ],
)
def test_bad_scene_files(tmp_path, text, fragment):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    r = run(["render", str(p), "--out", str(tmp_path / "o")])
    _one_line_exit_2(r)
    assert fragment in r.stderr
    assert not (tmp_path / "o").exists()


def test_non_utf8_scene(tmp_path):
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe\x00garbage")
    _one_line_exit_2(run(["render", str(p), "--out", str(tmp_path / "o")]))


def test_unwritable_output(tmp_path):
    f = tmp_path / "a_file"
    f.write_text("x")
    r = run(["render", "brewster", "--out", str(f / "sub"), "--duration", "0.01"])
    _one_line_exit_2(r)
    assert "--out" in r.stderr


def _limit_file_size():
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))


def test_full_disk_leaves_no_partial_file(tmp_path):
    """A size-limited process (RLIMIT_FSIZE) stands in for a full disk: error, and no half frame under its name."""
    out = tmp_path / "o"
    r = run(["render", "brewster", "--out", str(out), "--duration", "0.02", "--quiet"], preexec_fn=_limit_file_size)
    _one_line_exit_2(r)
    assert "no space left" in r.stderr
    frames = list((out / "frames").glob("*.exr")) if (out / "frames").exists() else []
    leftovers = [p for p in out.rglob("*") if ".tmp-" in p.name]
    assert not leftovers
    from polinfra.exr import read_exr

    for fr in frames:  # whatever exists under a final name is whole
        read_exr(fr)


def _tables(keys: list[str], extra_leaves: tuple[str, ...] = ()):
    """Nested TOML-like tables over ``keys`` with hostile leaves (NaN, inf, wrong types) and a few plausible strings."""
    leaves = [st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12)]
    if extra_leaves:
        leaves.append(st.sampled_from(extra_leaves))
    kst = st.sampled_from(keys)
    vals = st.recursive(st.one_of(*leaves), lambda ch: st.one_of(st.lists(ch, max_size=4), st.dictionaries(kst, ch, max_size=4)), max_leaves=12)
    return st.dictionaries(kst, vals, max_size=5)


def _ok_or_one_line_project_error(fn, *args) -> None:
    try:
        fn(*args)
    except PolspikeError as exc:
        assert "\n" not in str(exc)


_SCENE_KEYS = ["camera", "pane", "layers", "polarizer", "render", "name", "width", "n", "tilt_deg", "model", "source", "x"]
_MANIFEST_KEYS = ["name", "groups", "defaults", "split", "tier", "seed", "duration_s", "scene", "pane", "camera",
                  "layers", "spike_sim", "preset", "n", "tilt_deg", "width", "source", "format", "x"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=_tables(_SCENE_KEYS))
def test_fuzz_scene_loader_raises_only_project_errors(data):
    from generator.scene import scene_from_dict

    _ok_or_one_line_project_error(scene_from_dict, data, "fuzz")


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=_tables(_MANIFEST_KEYS, ("train", "test", "analytic", "brewster", "ideal", "skimage:moon")))
def test_fuzz_manifest_loader(data):
    """Random manifest tables: a Manifest or a one-line project error, never another exception."""
    from polspike.pipeline.manifest import parse_manifest

    _ok_or_one_line_project_error(parse_manifest, data, "fuzz.toml")


@settings(max_examples=100, deadline=None)
@given(text=st.text(max_size=300))
def test_fuzz_manifest_text(tmp_path_factory, text):
    """Random (often malformed or truncated) TOML text through the manifest file loader."""
    from polspike.pipeline.manifest import load_manifest

    p = tmp_path_factory.mktemp("mf") / "m.toml"
    p.write_text(text, encoding="utf-8")
    _ok_or_one_line_project_error(load_manifest, p)


@settings(max_examples=150, deadline=None)
@given(text=st.text(max_size=200))
def test_fuzz_toml_text(tmp_path_factory, text):
    from generator.scene import load_scene

    p = tmp_path_factory.mktemp("fz") / "s.toml"
    p.write_text(text, encoding="utf-8")
    try:
        load_scene(p)
    except PolspikeError:
        pass
