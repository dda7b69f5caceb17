"""The ``polspike`` command line: one typer app, thin commands.

Each subcommand parses its options, loads the config, calls one library
function and prints a summary.  Commands live in :mod:`polspike.commands`
(one small module per pipeline stage) and register themselves on :data:`app`.

Errors are mapped once, here:

* :class:`~polinfra.errors.PolspikeError` -> ``error: <message>`` on one line,
  exit code 2;
* usage errors (unknown option or command, a value of the wrong type, a
  missing argument) -> click's short usage line, a ``Try ... --help`` hint and
  one ``Error: ...`` line (with click's "did you mean" where it has one), exit
  code 2.  Typer >= 0.2x raises the exceptions of its *vendored* click
  (``typer._click``), older typer those of plain ``click``; both are caught
  (:func:`_is_click_exception`);
* any other exception keeps its traceback (a bug, not bad input).

Help strings are rendered by typer's rich formatter, which reads ``[word]`` as
rich markup and drops it; :class:`_PolspikeGroup` escapes the markup in every
help string of the tree before it runs, so ``[net]`` or ``[default: ...]``
print as written.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import typer
from typer.core import TyperGroup

from polinfra.errors import PolspikeError

#: Markup mode of every typer app here.  With "rich" help strings are escaped
#: (see :func:`_escape_help_markup`); with None typer prints plain click help.
_MARKUP_MODE = "rich"


def _escape_help_markup(cmd: Any) -> None:
    """Escape rich markup in the help strings of ``cmd`` and its subcommands, once.

    Only commands whose help typer renders as rich markup are touched (with
    another markup mode the backslashes would show).  Idempotent per command
    object: typer builds a fresh click tree on every run.
    """
    if getattr(cmd, "_polspike_help_escaped", False):
        return
    if getattr(cmd, "rich_markup_mode", None) == "rich":
        from rich.markup import escape

        for attr in ("help", "short_help", "epilog"):
            text = getattr(cmd, attr, None)
            if isinstance(text, str):
                setattr(cmd, attr, escape(text))
        for param in getattr(cmd, "params", ()):
            text = getattr(param, "help", None)
            if isinstance(text, str):
                param.help = escape(text)
    cmd._polspike_help_escaped = True
    for sub in (getattr(cmd, "commands", None) or {}).values():
        _escape_help_markup(sub)


class _PolspikeGroup(TyperGroup):
    """Root group: escapes help markup in the whole tree before parsing (CLI and CliRunner alike)."""

    def main(self, *args: Any, **kwargs: Any) -> Any:
        _escape_help_markup(self)
        return super().main(*args, **kwargs)


app_typer = typer.Typer(
    name="polspike",
    help="Synthetic spike-camera data behind a glass pane and a rotating polarizer, and its reflection-removal reconstructor.",
    cls=_PolspikeGroup,
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=_MARKUP_MODE,
)
bench_app = typer.Typer(help="Benchmarks: each writes JSON and prints a table; speed as ratios to a reference run in the same process.", no_args_is_help=True, rich_markup_mode=_MARKUP_MODE)
dataset_app = typer.Typer(help="Dataset manifests: build, verify, inspect, sample new ones.", no_args_is_help=True, rich_markup_mode=_MARKUP_MODE)
app_typer.add_typer(bench_app, name="bench")
app_typer.add_typer(dataset_app, name="dataset")


def version_line() -> str:
    """``polspike <version>, checkpoint <name>``: the package version and the default checkpoint's file name."""
    from polspike import __version__
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS

    return f"polspike {__version__}, checkpoint {DEFAULT_WEIGHTS.name}"


def _print_version(value: bool) -> None:
    if value:
        typer.echo(version_line())
        raise typer.Exit()


@app_typer.callback()
def _main(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More logging (-v info, -vv debug)."),
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True, help="Print the package version and the default checkpoint's name, then exit."),
) -> None:
    from rich.logging import RichHandler

    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(message)s", handlers=[RichHandler(show_path=False, rich_tracebacks=False)], force=True)


def _register() -> None:
    import importlib
    import pkgutil

    import polspike.commands as pkg

    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        importlib.import_module(f"polspike.commands.{mod}")


def _click_exception_bases() -> tuple[type, ...]:
    """The ``ClickException`` classes in play: the one typer raises, and plain click's if installed.

    Typer's is found from typer itself (the base named ``ClickException`` in
    the MRO of ``typer.BadParameter``), so it follows wherever typer keeps its
    click -- vendored (``typer._click``) or the ``click`` package.
    """
    bases: list[type] = [c for c in type.mro(typer.BadParameter) if c.__name__ == "ClickException"]
    try:
        import click.exceptions as plain

        bases.append(plain.ClickException)
    except ImportError:  # pragma: no cover - typer with a vendored click needs no click package
        pass
    return tuple(dict.fromkeys(bases))


def _is_click_exception(exc: BaseException) -> bool:
    """True for click usage/input errors of any click copy (by class, else by shape)."""
    if isinstance(exc, _click_exception_bases()):
        return True
    # Duck-typed fallback for a click copy not known by module (shape of ClickException).
    return callable(getattr(exc, "show", None)) and isinstance(getattr(exc, "exit_code", None), int)


def app() -> None:
    """Console-script entry point: run the CLI; bad input of any kind -> short message, exit 2."""
    _register()
    try:
        rv = app_typer(standalone_mode=False)
    except PolspikeError as exc:
        from rich.console import Console
        from rich.markup import escape

        Console(stderr=True).print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except Exception as exc:
        if _is_click_exception(exc):
            # click's own rendering: usage line, "Try ... --help", "Error: ..." (help text for NoArgsIsHelp).
            exc.show()  # type: ignore[attr-defined]
            sys.exit(2)
        raise
    # In non-standalone mode click *returns* the code of a typer.Exit (and 130 for Ctrl-C)
    # instead of raising; commands themselves return None.
    if isinstance(rv, int) and not isinstance(rv, bool) and rv != 0:
        sys.exit(rv)


def get_app() -> typer.Typer:
    """The typer app with every command registered (for tests via CliRunner)."""
    _register()
    return app_typer
