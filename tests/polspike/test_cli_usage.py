"""Usage errors and help text through the installed console script.

The command tree is read from the real app (``typer.main.get_command(get_app())``), never
hard-coded, so commands and options added later are covered without editing this file.  Every
probe runs the installed ``polspike`` entry point in a subprocess (not CliRunner): the bug this
guards against lived in the entry point's exception mapping, which CliRunner bypasses.

For every command and group:
* an unknown option (a near miss of one of its real options) -> exit 2, click's usage line, one
  ``Error:`` line naming the typo and offering the real option, no traceback;
* a value of the wrong type for one int/float option -> exit 2, the option named;
* a missing required argument (or option, if it has no required argument) -> exit 2, that
  parameter named;
* every group: an unknown subcommand (near miss) -> exit 2 with click's "Did you mean".
and every command's ``--help`` shows each ``[bracketed]`` token of its help strings verbatim.

The probes run 4 at a time (startup of the script dominates: ~0.3-0.5 s each).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import types
import typing
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import typer
import typer.main

from polspike.cli import get_app

HELP_OPTS = {"--help", "-h"}


def _script() -> str:
    cand = Path(sys.executable).with_name("polspike")
    if cand.exists():
        return str(cand)
    found = shutil.which("polspike")
    if found:
        return found
    pytest.fail("the console script 'polspike' is not installed next to this interpreter (pip install -e .)")


def _tree() -> list[tuple[tuple[str, ...], typing.Any]]:
    root = typer.main.get_command(get_app())
    out: list[tuple[tuple[str, ...], typing.Any]] = []

    def walk(cmd: typing.Any, path: tuple[str, ...]) -> None:
        out.append((path, cmd))
        for name, sub in sorted((getattr(cmd, "commands", None) or {}).items()):
            if not getattr(sub, "hidden", False):
                walk(sub, path + (name,))

    walk(root, ())
    return out


def _visible(cmd: typing.Any) -> list[typing.Any]:
    return [p for p in cmd.params if not getattr(p, "hidden", False)]


def _long_opts(cmd: typing.Any) -> list[str]:
    return [o for p in _visible(cmd) if p.param_type_name == "option" for o in p.opts if o.startswith("--")]


def _annotation(param: typing.Any) -> typing.Any:
    """The Python type of a typer parameter (typer >= 0.2x keeps it on ``type_descriptor``)."""
    desc = getattr(param, "type_descriptor", None)
    if desc is None:
        return None
    ann = desc.annotation
    if typing.get_origin(ann) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(ann) if a is not type(None)]
        ann = rest[0] if len(rest) == 1 else None
    return ann


def _numeric(param: typing.Any) -> str | None:
    """'int' / 'float' for a single-valued numeric option taking a value, else None."""
    if param.param_type_name != "option" or getattr(param, "is_flag", False) or getattr(param, "count", False) or param.nargs != 1:
        return None
    ann = _annotation(param)
    if ann is not None:
        return {int: "int", float: "float"}.get(ann)
    name = getattr(getattr(param, "type", None), "name", "")  # plain click parameter types
    return {"integer": "int", "integer range": "int", "float": "float", "float range": "float"}.get(name)


def _choices(param: typing.Any) -> list[str]:
    desc = getattr(param, "type_descriptor", None)
    if desc is not None and getattr(desc, "is_choice", False) and desc.choices:
        return [str(getattr(c, "value", c)) for c in desc.choices]
    return [str(c) for c in getattr(getattr(param, "type", None), "choices", None) or ()]


def _dummy(param: typing.Any) -> str:
    """A value that converts for ``param`` (its checks may still fail later; we never get there)."""
    kind = _numeric(param)
    return "1" if kind == "int" else "1.0" if kind == "float" else (_choices(param) or ["x"])[0]


def _near_miss(word: str, taken: set[str]) -> str:
    """A typo of ``word`` that is not itself valid: drop the last character, else append one."""
    for typo in (word[:-1], word + "x", word + "zz"):
        if typo not in taken and len(typo.lstrip("-")) >= 3:
            return typo
    raise AssertionError(f"no near miss for {word!r}")


@dataclass
class Probe:
    label: str
    argv: list[str]
    must_name: list[str]  # substrings the error must contain
    any_of: list[str] = field(default_factory=list)  # at least one of these must appear too


def _usage_probes() -> list[Probe]:
    probes: list[Probe] = []
    for path, cmd in _tree():
        where = " ".join(("polspike",) + path)
        longs = _long_opts(cmd)
        # 1. unknown option: a near miss of a real option (prefer a command's own over --help)
        real = next((o for o in longs if o not in HELP_OPTS and len(o) >= 5), None) or "--help"
        typo = _near_miss(real, set(longs))
        probes.append(Probe(f"{where}: unknown option {typo}", [*path, typo, "1"], [typo, real]))
        subs = sorted(n for n, s in (getattr(cmd, "commands", None) or {}).items() if not getattr(s, "hidden", False))
        if subs:
            # 2g. unknown subcommand, near miss -> "Did you mean"
            typo_cmd = _near_miss(subs[0], set(subs))
            probes.append(Probe(f"{where}: unknown command {typo_cmd}", [*path, typo_cmd], [typo_cmd, subs[0]], any_of=["Did you mean", "Possible"]))
            continue
        params = _visible(cmd)
        # 2. wrong-typed value for the first int/float option
        num = next((p for p in params if _numeric(p)), None)
        if num is not None:
            opt = next(o for o in num.opts if o.startswith("--"))
            probes.append(Probe(f"{where}: {opt} abc ({_numeric(num)})", [*path, opt, "abc"], [opt], any_of=["Invalid value", "invalid"]))
        # 3. missing required argument (or option): every other required option given, no positionals
        req_args = [p for p in params if p.required and p.param_type_name == "argument"]
        req_opts = [p for p in params if p.required and p.param_type_name == "option"]
        if req_args:
            target, given = req_args[0], req_opts
        elif req_opts:
            target, given = req_opts[0], req_opts[1:]
        else:
            continue
        argv = [*path]
        for p in given:
            argv += [next(o for o in p.opts if o.startswith("--")), _dummy(p)]
        name = next((o for o in target.opts if o.startswith("--")), target.name) if target.param_type_name == "option" else target.name
        probes.append(Probe(f"{where}: missing {name}", argv, [name], any_of=["Missing", "missing"]))
    return probes


def _run_all(argvs: list[list[str]], cwd: Path) -> list[subprocess.CompletedProcess]:
    exe = _script()
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1", TERM="dumb")

    def run(argv: list[str]) -> subprocess.CompletedProcess:
        return subprocess.run([exe, *argv], capture_output=True, text=True, cwd=cwd, env=env, timeout=120, stdin=subprocess.DEVNULL)

    with ThreadPoolExecutor(max_workers=4) as pool:
        return list(pool.map(run, argvs))


def test_every_usage_error_is_short_exit_2_no_traceback(tmp_path):
    probes = _usage_probes()
    kinds = {p.label.split(": ", 1)[1].split()[0] for p in probes}
    # the walk reaches every kind of probe on today's tree (not vacuous)
    assert len(probes) >= 20 and {"unknown", "missing"} <= kinds and any("abc" in p.label for p in probes), [p.label for p in probes]
    results = _run_all([p.argv for p in probes], tmp_path)
    bad = []
    for p, r in zip(probes, results):
        err = r.stderr
        lines = [ln for ln in err.splitlines() if ln.strip()]
        errors = [ln for ln in lines if ln.startswith("Error:")]
        problems = []
        if r.returncode != 2:
            problems.append(f"exit {r.returncode}")
        if "Traceback" in err:
            problems.append("traceback")
        if not lines or not lines[0].startswith("Usage: polspike"):
            problems.append("no usage line first")
        if len(errors) != 1 or lines[-1] != errors[0]:
            problems.append("not exactly one final 'Error:' line")
        if len(lines) > 4:
            problems.append(f"{len(lines)} lines")
        problems += [f"{s!r} not named" for s in p.must_name if s not in err]
        if p.any_of and not any(s in err for s in p.any_of):
            problems.append(f"none of {p.any_of}")
        if problems:
            bad.append(f"{p.label}: {problems}\n  argv={p.argv}\n  stderr={err[-600:]!r}")
    assert not bad, "\n".join(bad)
    assert not list(tmp_path.iterdir()), "a usage error must not run the command"


def test_issue_examples_exit_2(tmp_path):
    """Usage examples that are still errors."""
    tree = dict(_tree())
    examples = [(["nosuchcmd"], "No such command")]
    zeta = tree.get(("zeta",))
    if zeta is not None and "--bogus" not in _long_opts(zeta):
        examples.append((["zeta", "--bogus", "1"], "--bogus"))
    if zeta is not None and any(_numeric(p) and "--n" in p.opts for p in zeta.params):
        examples.append((["zeta", "--n", "abc", "--theta-deg", "40"], "--n"))
    render = tree.get(("render",))
    if render is not None and any(p.required and p.param_type_name == "argument" for p in render.params):
        examples.append((["render"], "Missing"))
    rec = tree.get(("reconstruct",))
    if rec is not None:  # the issue's `--method irls`, or a near miss of it once --method exists
        opts = set(_long_opts(rec))
        opt = "--method" if "--method" not in opts else _near_miss("--method", opts)
        examples.append((["reconstruct", "x.dat", opt, "irls", "--out", "o"], opt))
    assert len(examples) >= 4
    for (argv, frag), r in zip(examples, _run_all([a for a, _ in examples], tmp_path)):
        assert r.returncode == 2 and frag in r.stderr and "Traceback" not in r.stderr, (argv, r.returncode, r.stderr[-800:])


BRACKET = re.compile(r"\[[^\[\]\n]+\]")


def _norm(text: str) -> str:
    """Help output without rich's box drawing and with runs of whitespace collapsed."""
    return " ".join(re.sub(r"[│╭╮╰╯─┃━┏┓┗┛]", " ", text).split())


def _help_texts(cmd: typing.Any) -> list[str]:
    texts = [cmd.help.split("\f")[0] if isinstance(cmd.help, str) else None, getattr(cmd, "epilog", None)]
    texts += [getattr(p, "help", None) for p in _visible(cmd)]
    return [t for t in texts if isinstance(t, str)]


def test_help_keeps_every_bracketed_word(tmp_path):
    tree = _tree()
    wanted = {path: sorted({" ".join(m.split()) for t in _help_texts(cmd) for m in BRACKET.findall(t)}) for path, cmd in tree}
    assert sum(map(len, wanted.values())) >= 5, "no [bracketed] words in the help strings: this test would test nothing"
    results = _run_all([[*path, "--help"] for path, _ in tree], tmp_path)
    bad = []
    for (path, _), r in zip(tree, results):
        out = _norm(r.stdout)
        if r.returncode != 0 or "Traceback" in r.stderr:
            bad.append(f"{path}: --help exit {r.returncode}: {r.stderr[-300:]}")
            continue
        lost = [w for w in wanted[path] if w not in out]
        if lost:
            bad.append(f"polspike {' '.join(path)} --help lost {lost}")
        if "\\[" in out:
            bad.append(f"polspike {' '.join(path)} --help shows an escaping backslash")
    assert not bad, "\n".join(bad)
    train = dict(tree).get(("train",))
    if train is not None and "[net]" in wanted[("train",)]:
        assert "[net]" in _norm(results[[p for p, _ in tree].index(("train",))].stdout)


# -- in process: the entry point's mapping for each kind of click exception ------------------------


def _patched_cli():
    """polspike.cli with every real command already registered (so none lands on a test app)."""
    import polspike.cli as cli

    cli.get_app()
    return cli


def _run_entry(monkeypatch, capsys, exc: BaseException) -> tuple[int | None, str]:
    cli = _patched_cli()
    app = typer.Typer(add_completion=False)

    @app.command()
    def boom() -> None:
        raise exc

    @app.command()
    def other() -> None:  # two commands so typer keeps a group
        pass

    monkeypatch.setattr(cli, "app_typer", app)
    monkeypatch.setattr(sys, "argv", ["polspike", "boom"])
    with pytest.raises(SystemExit) as info:
        cli.app()
    return info.value.code, capsys.readouterr().err


def test_entry_point_maps_plain_click_vendored_and_shaped_errors(monkeypatch, capsys):
    """Plain click's, typer's own and an unknown click copy's (duck-typed) errors all exit 2, no traceback."""
    click = pytest.importorskip("click")

    class Shaped(Exception):  # a click copy we do not know by module: only the shape of ClickException
        exit_code = 2

        def show(self, file=None) -> None:
            print("Error: shaped usage error", file=sys.stderr)

    cases = [
        (click.exceptions.NoSuchOption("--plaim", possibilities=["--plain"]), ["--plaim", "--plain"]),
        (typer.BadParameter("vendored bad value"), ["vendored bad value"]),
        (Shaped(), ["shaped usage error"]),
    ]
    for exc, frags in cases:
        code, err = _run_entry(monkeypatch, capsys, exc)
        assert code == 2, (type(exc), code, err)
        assert "Traceback" not in err and all(f in err for f in frags), (type(exc), err)


def test_entry_point_keeps_other_exceptions_and_project_error_brackets(monkeypatch, capsys):
    """A bug keeps its traceback (not swallowed as a usage error); a project error keeps its [brackets]."""
    from polinfra.errors import ConfigError

    cli = _patched_cli()
    app = typer.Typer(add_completion=False)

    @app.command()
    def boom() -> None:
        raise ZeroDivisionError("a bug")

    @app.command()
    def cfg() -> None:
        raise ConfigError("unknown key 'x' in [net]")

    monkeypatch.setattr(cli, "app_typer", app)
    monkeypatch.setattr(sys, "argv", ["polspike", "boom"])
    with pytest.raises(ZeroDivisionError):
        cli.app()
    monkeypatch.setattr(sys, "argv", ["polspike", "cfg"])
    with pytest.raises(SystemExit) as info:
        cli.app()
    err = capsys.readouterr().err
    assert info.value.code == 2 and "[net]" in err and len(err.strip().splitlines()) == 1, err


def test_entry_point_keeps_exit_codes_of_typer_exit_and_ctrl_c(monkeypatch, capsys):
    """In non-standalone mode click returns (not raises) these codes; the entry point must still exit with them."""
    for exc, want in ((typer.Exit(3), 3), (KeyboardInterrupt(), 130)):
        code, err = _run_entry(monkeypatch, capsys, exc)
        assert code == want and "Traceback" not in err, (type(exc), code, err)
    cli = _patched_cli()
    app = typer.Typer(add_completion=False)

    @app.command()
    def ok() -> None:
        print("fine")

    @app.command()
    def other() -> None:
        pass

    monkeypatch.setattr(cli, "app_typer", app)
    monkeypatch.setattr(sys, "argv", ["polspike", "ok"])
    cli.app()  # a normal run returns without SystemExit
    assert capsys.readouterr().out.strip() == "fine"
