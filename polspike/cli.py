"""The ``polspike`` command line: one typer app, thin commands.

Each subcommand parses its options, loads the config, calls one library
function and prints a summary.  Commands live in :mod:`polspike.commands`
(one small module per pipeline stage) and register themselves on :data:`app`.
:class:`~polinfra.errors.PolspikeError` is caught once, here, and printed as
one line with exit code 2; any other exception keeps its traceback.
"""

from __future__ import annotations

import logging
import sys

import typer

from polinfra.errors import PolspikeError

app_typer = typer.Typer(
    name="polspike",
    help="Synthetic spike-camera data behind a glass pane and a rotating polarizer, and its reflection-removal reconstructor.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks: each writes JSON and prints a table; speed as ratios to a reference run in the same process.", no_args_is_help=True)
dataset_app = typer.Typer(help="Dataset manifests: build, verify, inspect, sample new ones.", no_args_is_help=True)
app_typer.add_typer(bench_app, name="bench")
app_typer.add_typer(dataset_app, name="dataset")


@app_typer.callback()
def _main(verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More logging (-v info, -vv debug).")) -> None:
    from rich.logging import RichHandler

    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(message)s", handlers=[RichHandler(show_path=False, rich_tracebacks=False)], force=True)


def _register() -> None:
    import importlib
    import pkgutil

    import polspike.commands as pkg

    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        importlib.import_module(f"polspike.commands.{mod}")


def app() -> None:
    """Console-script entry point: run the CLI, mapping PolspikeError to exit 2."""
    _register()
    try:
        app_typer(standalone_mode=False)
    except PolspikeError as exc:
        from rich.console import Console

        Console(stderr=True).print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except Exception as exc:  # click usage errors come through here in standalone_mode=False
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(2)
        raise


def get_app() -> typer.Typer:
    """The typer app with every command registered (for tests via CliRunner)."""
    _register()
    return app_typer
