"""What tests/test_readme.py and tests/test_docs.py share: the parse-only check of a command line against the
real CLI, the scratch folder the shown commands run in, and the running of one command in it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _exit_if_set(ctx, param, value):
    if value:
        raise SystemExit(0)
    return value


def parses(args) -> None:
    """Option names, types and ranges of ``polspike ARGS`` are accepted by the real CLI; no command body runs
    (every callback is replaced by a no-op; ``--version``, eager, exits as ``--help`` does).
    """
    import typer.main

    from polspike.cli import get_app

    root = typer.main.get_command(get_app())

    def stub(cmd):
        for param in getattr(cmd, "params", ()):
            if param.name == "version":
                param.callback = _exit_if_set
        if hasattr(cmd, "commands"):
            for sub in cmd.commands.values():
                stub(sub)
        elif cmd.callback is not None:
            cmd.callback = lambda *a, **k: None

    stub(root)
    try:
        root.main(args=list(args), prog_name="polspike", standalone_mode=False)
    except SystemExit as exc:  # --help exits 0
        assert exc.code in (0, None), args


def takes_quiet(args) -> bool:
    """Whether the (sub)command that ``args`` names has a ``--quiet`` option."""
    import typer.main

    from polspike.cli import get_app

    cmd = typer.main.get_command(get_app())
    for a in args:
        if hasattr(cmd, "commands") and a in cmd.commands:
            cmd = cmd.commands[a]
    return any("--quiet" in getattr(p, "opts", []) for p in getattr(cmd, "params", []))


def make_scratch(d: Path) -> Path:
    """``d`` set up to see the repository's scenes/, datasets/ and reconstruct/configs/ (as a checkout does)."""
    for sub in ("scenes", "datasets"):
        (d / sub).symlink_to(REPO / sub)
    (d / "reconstruct").mkdir()
    (d / "reconstruct" / "configs").symlink_to(REPO / "reconstruct" / "configs")
    return d


def run_cli(args, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    """``polspike ARGS`` (plus ``--quiet`` where the command takes it) in ``cwd``, on this checkout's code."""
    env = dict(os.environ, COLUMNS="120", PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    quiet = ["--quiet"] if takes_quiet(args) else []
    return subprocess.run([sys.executable, "-c", "from polspike.cli import app; app()", *args, *quiet],
                          capture_output=True, text=True, cwd=cwd, timeout=timeout, env=env)
