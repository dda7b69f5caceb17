"""Every command and every option of the CLI explains itself (help with units and defaults)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import typer.main
from typer.testing import CliRunner

from polspike.cli import get_app

if TYPE_CHECKING:
    import click


def _walk(cmd: click.Command, path: tuple[str, ...] = ()):
    yield path, cmd
    if hasattr(cmd, "commands"):
        for name, sub in cmd.commands.items():
            yield from _walk(sub, path + (name,))


def test_every_command_and_option_has_help():
    root = typer.main.get_command(get_app())
    missing = []
    n_cmds = 0
    for path, cmd in _walk(root):
        n_cmds += 1
        if path and not (cmd.help or cmd.short_help):
            missing.append(" ".join(path) + ": no command help")
        for p in cmd.params:
            if getattr(p, "param_type_name", "") == "option" and p.name != "help" and not (p.help or "").strip():
                missing.append(f"{' '.join(path)} {p.opts[0]}: no help")
    assert n_cmds > 10
    assert not missing, missing


def test_help_runs_for_every_command():
    root = typer.main.get_command(get_app())
    runner = CliRunner()
    for path, _ in _walk(root):
        r = runner.invoke(get_app(), list(path) + ["--help"])
        assert r.exit_code == 0, (path, r.output[-500:])
        assert "Usage" in r.output
