"""Every command in the README works: all of them parse against the real CLI, and the cheap ones run.

The README's ```bash blocks are the source: a line starting with ``polspike`` is a command.  The
first CLI-tour block runs for real, in order (later commands use earlier outputs), in a scratch
folder that sees the repository's scenes/, datasets/ and reconstruct/configs/.  Commands that take
minutes to hours (the second block) are parsed only: their option names and values must be valid.
Every subcommand has an example in the README or in the documentation's pages (tests/test_docs.py
runs those).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from tests._cli_checks import make_scratch, parses, run_cli
from tests._tour_checks import tour_check

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SKIP_RUN = {"demo": "run by tests/pipeline/test_demo.py (reduced)"}


def bash_blocks() -> list[list[list[str]]]:
    text = README.read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    out = []
    for b in blocks:
        cmds = []
        for line in b.splitlines():
            line = line.split(" #")[0].strip()
            if line.startswith("polspike"):
                cmds.append(shlex.split(line)[1:])
        if cmds:
            out.append(cmds)
    return out


BLOCKS = bash_blocks()
ALL = [c for b in BLOCKS for c in b]
TOUR = BLOCKS[0] if BLOCKS else []


def docs_commands() -> list[list[str]]:
    """Every polspike line of the fenced bash blocks (run or long) of the documentation's pages."""
    out = []
    for page in sorted((REPO / "docs").rglob("*.md")):
        for info, body in re.findall(r"^```([^\n]*)\n(.*?)^```", page.read_text(), flags=re.S | re.M):
            if ".bash" not in info and info.strip() != "bash":
                continue
            body = re.sub(r"\\\n\s*", " ", body)  # a command continued with a backslash is one command
            for line in body.splitlines():
                line = line.split(" #")[0].strip()
                if line.startswith("polspike"):
                    out.append(shlex.split(line)[1:])
    return out


def test_readme_and_docs_have_a_command_per_subcommand():
    import typer.main

    from polspike.cli import get_app

    root = typer.main.get_command(get_app())
    shown = ALL + docs_commands()
    used = {c[0] for c in shown if c and not c[0].startswith("-")}
    missing = set(root.commands) - used - {"evaluate-checkpoint"}
    assert not missing, f"neither the README nor the docs show an example of: {sorted(missing)}"
    benches = {c[1] for c in shown if len(c) > 1 and c[0] == "bench"}
    assert not set(root.commands["bench"].commands) - benches, sorted(set(root.commands["bench"].commands) - benches)
    subs = {c[1] for c in shown if len(c) > 1 and c[0] == "dataset"}
    assert not set(root.commands["dataset"].commands) - subs, sorted(set(root.commands["dataset"].commands) - subs)


@pytest.mark.parametrize("args", ALL, ids=[" ".join(a)[:60] for a in ALL])
def test_readme_command_parses(args):
    """Option names, types and ranges are accepted by the real CLI (the command body is not run)."""
    parses(args)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return make_scratch(tmp_path_factory.mktemp("readme"))


@pytest.mark.parametrize("args", TOUR, ids=[" ".join(a)[:60] for a in TOUR])
def test_readme_tour_runs(args, scratch):
    """The command exits 0, and what it prints or writes holds the content the README promises (tour_checks)."""
    if args and args[0] in SKIP_RUN:
        pytest.skip(SKIP_RUN[args[0]])
    check = tour_check(args)
    assert check is not None, f"no content check for the tour command {args}: add one to tests/_tour_checks.py"
    r = run_cli(args, scratch, timeout=600)
    assert r.returncode == 0, (args, r.stdout[-1500:], r.stderr[-3000:])
    check(scratch, args, r.stdout)
