"""The documentation site: it builds strictly, and every command it shows works.

* ``mkdocs build --strict`` (skipped only when mkdocs and its plugins are not installed; the ``test``
  extra installs them).
* Every ``polspike`` line of a fenced ``bash`` block of any page parses against the real CLI; in the
  getting-started page and the how-to guides the blocks then run for real, in page order, in a
  scratch folder that sees the repository's scenes/, datasets/ and reconstruct/configs/. A ``toml``
  block with ``title="PATH"`` is written to PATH first (the page's own example file). Blocks fenced
  ``{.bash .long}`` (hours on a CPU, or needing a cluster or a recording you bring) are parsed only.
  A ``python`` block of those pages runs too, where it stands in the page.
  A line ending in ``# exit N`` must exit with code N.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests._cli_checks import make_scratch, parses, run_cli

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
#: the pages whose commands run, and those that take over ~20 s on two cores (marked slow; the README tour
#: runs the getting-started commands in the default suite)
PAGES = ["getting-started.md", *sorted(p.relative_to(DOCS).as_posix() for p in (DOCS / "how-to").glob("*.md") if p.name != "index.md")]
SLOW_PAGES = {"getting-started.md", "how-to/calibrate-pane.md", "how-to/train.md", "how-to/reconstruct-dat.md", "how-to/validate-zeta.md"}

FENCE = re.compile(r"^```([^\n]*)\n(.*?)^```", re.S | re.M)


def blocks(page: str) -> list[tuple[str, str, str]]:
    """(kind, title, body) of every fenced block: kind is run, long, file, python or other."""
    out = []
    for info, body in FENCE.findall((DOCS / page).read_text()):
        info = info.strip()
        m = re.search(r'title="([^"]+)"', info)
        if info == "bash":
            out.append(("run", "", body))
        elif info.startswith("{") and ".bash" in info and ".long" in info:
            out.append(("long", "", body))
        elif info.startswith("toml") and m:
            out.append(("file", m.group(1), body))
        elif info == "python":
            out.append(("python", "", body))
        else:
            out.append(("other", "", body))
    return out


def commands(body: str) -> list[tuple[list[str], int]]:
    """(argv after 'polspike', expected exit code) of each polspike line."""
    out = []
    body = re.sub(r"\\\n\s*", " ", body)  # a command continued over lines with a backslash is one command
    for line in body.splitlines():
        code = 0
        m = re.search(r"#\s*exit (\d+)\s*$", line)
        if m:
            code = int(m.group(1))
        line = line.split(" #")[0].strip()
        if line.startswith("polspike"):
            out.append((shlex.split(line)[1:], code))
    return out


#: every page with commands: the run pages and the rest (concepts, reference, results), whose commands are parsed
ALL_PAGES = sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md") if "scripts" not in p.parts)
ALL = [(page, argv) for page in ALL_PAGES for kind, _, body in blocks(page) if kind in ("run", "long") for argv, _ in commands(body)]


def test_every_how_to_page_has_commands():
    for page in PAGES:
        assert any(kind == "run" and commands(body) for kind, _, body in blocks(page)), f"{page} shows no runnable polspike command"


@pytest.mark.parametrize("page,args", ALL, ids=[f"{p}: {' '.join(a)[:50]}" for p, a in ALL])
def test_docs_command_parses(page, args):
    """Option names, types and ranges are accepted by the real CLI (the command body is not run)."""
    parses(args)


def _run_page(page: str, tmp_path: Path) -> None:
    cwd = make_scratch(tmp_path)
    env = dict(os.environ, COLUMNS="120", PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    for kind, title, body in blocks(page):
        if kind == "file":
            target = cwd / title
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(body)
        if kind == "python":
            r = subprocess.run([sys.executable, "-c", body], capture_output=True, text=True, cwd=cwd, timeout=900, env=env)
            assert r.returncode == 0, (page, body, r.stderr[-3000:])
        if kind != "run":
            continue
        for argv, code in commands(body):
            r = run_cli(argv, cwd)
            assert r.returncode == code, (page, argv, r.returncode, r.stdout[-1500:], r.stderr[-3000:])


@pytest.mark.parametrize("page", [pytest.param(p, marks=pytest.mark.slow) if p in SLOW_PAGES else p for p in PAGES])
def test_docs_page_runs(page, tmp_path):
    _run_page(page, tmp_path)


def _have_mkdocs() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("mkdocs", "material", "mkdocstrings", "mkdocs_gen_files"))


@pytest.mark.skipif(not _have_mkdocs(), reason="mkdocs, mkdocs-material, mkdocstrings or mkdocs-gen-files not installed (pip install -e '.[docs]')")
def test_site_builds_strict_without_warning(tmp_path):
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1", DISABLE_MKDOCS_2_WARNING="true",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                       capture_output=True, text=True, cwd=REPO, timeout=900, env=env)
    assert r.returncode == 0, r.stderr[-4000:]
    warnings = [ln for ln in r.stderr.splitlines() if ln.startswith("WARNING")]
    assert not warnings, warnings
    for page in ("index.html", "reference/cli/index.html", "reference/configs/index.html", "reference/api/index.html"):
        assert (tmp_path / "site" / page).is_file(), page
    cli = (tmp_path / "site" / "reference" / "cli" / "index.html").read_text()
    for cmd in ("polspike render", "polspike dataset build", "polspike reconstruct", "--tier"):
        assert cmd in cli, f"the generated CLI reference misses {cmd!r}"



PACKAGES = ("polinfra", "polphysics", "generator", "spike_sim", "reconstruct", "polspike")
_DOTTED = re.compile(r"(?<![\w/.-])((?:%s)(?:\.[A-Za-z_]\w*)+)" % "|".join(PACKAGES))
_PATH = re.compile(r"(?<![\w/.-])((?:%s)/[\w/]+\.py)" % "|".join(PACKAGES))
_FILE_SUFFIXES = {"json", "toml", "h5", "md", "py", "csv", "png", "mp4", "exr", "npz", "dat"}
#: run in a clean interpreter (tests/ on sys.path here shadows the package names): the names that do not resolve
_PROBE = """
import importlib, json, sys
def ok(name):
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False
print(json.dumps([n for n in json.loads(sys.argv[1]) if not ok(n)]))
"""


def test_code_names_in_the_docs_exist():
    """Every module, function or file of the packages that README.md or a docs page names in code
    (``reconstruct.physics.span.zbar_of``, ``generator/pane_fit.py``) exists: a module that moves must take
    its mentions along.
    """
    import json

    names, paths = set(), set()
    for page in [REPO / "README.md", *DOCS.rglob("*.md")]:
        for code in re.findall(r"`([^`\n]+)`", page.read_text()):
            names.update(n for n in _DOTTED.findall(code) if n.rsplit(".", 1)[-1] not in _FILE_SUFFIXES)
            paths.update(_PATH.findall(code))
    assert len(names) >= 10 and len(paths) >= 3, (len(names), len(paths))  # the search finds them
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(sorted(names))], capture_output=True, text=True, cwd=REPO, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    missing = json.loads(r.stdout.strip().splitlines()[-1]) + sorted(p for p in paths if not (REPO / p).is_file())
    assert not missing, f"named in the docs but not in the code: {missing}"
