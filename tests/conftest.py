"""Shared fixtures: seeded rng, the shared data folder, a tiny scene."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("DRJIT_LIBLLVM_PATH", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def np_rng() -> np.random.Generator:
    """A seeded numpy Generator (never the global RNG)."""
    return np.random.default_rng(12345)


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or skip with the reason when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def tiny_scene():
    """A 41 x 25 pixel brewster-like scene (odd sizes: the centre pixel is on the axis)."""
    import dataclasses

    from generator.scene import load_scene

    s = load_scene("brewster")
    cam = dataclasses.replace(s.camera, width=41, height=25)
    return dataclasses.replace(s, camera=cam, render=dataclasses.replace(s.render, duration_s=0.02, fps=100.0))


class ConsoleScript:
    """Runs the installed ``polspike`` console script (the one next to this interpreter) in a subprocess."""

    def __init__(self) -> None:
        import sys

        self.exe = Path(sys.executable).parent / "polspike"
        assert self.exe.is_file(), f"console script {self.exe} missing: pip install -e '.[test]'"

    def __call__(self, *args, timeout: float = 300, env: dict | None = None, cwd: Path | None = None):
        import subprocess

        full_env = {**os.environ, **(env or {})}
        return subprocess.run([str(self.exe), *map(str, args)], capture_output=True, text=True, timeout=timeout, env=full_env, cwd=cwd or REPO)

    @staticmethod
    def one_line_exit_2(r, *fragments: str) -> str:
        """Exit code 2, no traceback, exactly one non-empty line on stderr that holds every fragment."""
        assert r.returncode == 2, (r.returncode, r.stdout[-400:], r.stderr[-1500:])
        assert "Traceback" not in r.stderr, r.stderr[-1500:]
        lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
        assert len(lines) == 1, r.stderr
        for f in fragments:
            assert f in lines[0], (f, lines[0])
        return lines[0]


@pytest.fixture
def polspike_cli() -> ConsoleScript:
    """The installed ``polspike`` console script: ``polspike_cli(*args)`` -> CompletedProcess."""
    return ConsoleScript()


@pytest.fixture
def polspike_main(capsys, monkeypatch):
    """Run the console-script entry point ``polspike.cli.app`` in this process (same error mapping as the
    installed script, without a subprocess): ``polspike_main(*args)`` -> CompletedProcess-like result
    with ``returncode``, ``stdout``, ``stderr``; check it with ``polspike_main.one_line_exit_2(r, ...)``.
    """
    import subprocess
    import sys

    from polspike.cli import app

    def run(*args):
        capsys.readouterr()
        monkeypatch.setattr(sys, "argv", ["polspike", *map(str, args)])
        code = 0
        try:
            app()
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(["polspike", *map(str, args)], code, out, err)

    run.one_line_exit_2 = ConsoleScript.one_line_exit_2
    return run
