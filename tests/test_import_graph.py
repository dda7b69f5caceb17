"""The pipeline's import rules, checked on the source with ast.

Floors, bottom to top: polinfra -> polphysics -> generator, spike_sim -> reconstruct -> polspike.
Each top-level package lists the project packages it may import (ALLOWED); an import that
runs back up a floor fails here. Besides:
- reconstruct never imports generator (it must run on real captures);
- only generator imports mitsuba/drjit, and only inside functions (lazy);
- importing the foundation loads no pipeline stage (checked on sys.modules in a fresh interpreter).
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _imports(path: Path):
    tree = ast.parse(path.read_text())
    top_level = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top_level |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            top_level.add(node.module.split(".")[0])
    everywhere = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            everywhere |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            everywhere.add(node.module.split(".")[0])
    return top_level, everywhere


def _files(pkg):
    return sorted((REPO / pkg).rglob("*.py"))


def test_reconstruct_and_spike_sim_never_import_generator():
    for pkg in ("reconstruct", "spike_sim"):
        for f in _files(pkg):
            _, allimp = _imports(f)
            assert "generator" not in allimp, f"{f} imports generator"


def test_mitsuba_only_lazily_in_generator():
    for pkg in PROJECT:
        for f in _files(pkg):
            top, allimp = _imports(f)
            assert not ({"mitsuba", "drjit"} & top), f"{f} imports mitsuba at module level"
            if pkg != "generator" and f.name != "render_bench.py":
                assert not ({"mitsuba", "drjit"} & allimp), f"{f} imports mitsuba outside generator"


PROJECT = ("polinfra", "polphysics", "generator", "spike_sim", "reconstruct", "polspike")
ALLOWED = {
    "polinfra": set(),
    "polphysics": {"polinfra"},
    "generator": {"polinfra", "polphysics"},
    "spike_sim": {"polinfra", "polphysics"},
    "reconstruct": {"polinfra", "polphysics", "spike_sim"},
    "polspike": set(PROJECT),
}


def _project_imports(path: Path) -> set[str]:
    _, everywhere = _imports(path)
    return everywhere & set(PROJECT)


def test_every_python_package_is_a_known_floor():
    tops = {p.parent.name for p in REPO.glob("*/__init__.py")}
    assert tops == set(PROJECT), f"top-level packages {sorted(tops)} differ from the floors {PROJECT}; add the new one to ALLOWED"


def test_each_floor_imports_only_what_it_may():
    bad = []
    for pkg in PROJECT:
        for f in _files(pkg):
            extra = _project_imports(f) - ALLOWED[pkg] - {pkg}
            if extra:
                bad.append(f"{f.relative_to(REPO)} imports {sorted(extra)}")
    assert not bad, "imports that run back up a floor:\n" + "\n".join(bad)


def test_top_level_import_graph_has_no_loop():
    edges = {pkg: set() for pkg in PROJECT}
    for pkg in PROJECT:
        for f in _files(pkg):
            edges[pkg] |= _project_imports(f) - {pkg}
    state: dict[str, int] = {}

    def visit(node, path):
        if state.get(node) == 1:
            raise AssertionError(f"import loop: {' -> '.join(path + [node])}")
        if state.get(node) == 2:
            return
        state[node] = 1
        for nxt in sorted(edges[node]):
            visit(nxt, path + [node])
        state[node] = 2

    for pkg in PROJECT:
        visit(pkg, [])


def test_layering_rule_catches_an_upward_import(tmp_path):
    """The checker itself: a foundation module that imports a stage is reported."""
    f = tmp_path / "bad.py"
    f.write_text("def f():\n    from generator.scene import load_scene\n")
    assert _project_imports(f) - ALLOWED["polinfra"] == {"generator"}


def test_importing_the_foundation_loads_no_stage():
    code = (
        "import sys, pkgutil, importlib, polinfra, polphysics\n"
        "for pkg in (polinfra, polphysics):\n"
        "    for m in pkgutil.iter_modules(pkg.__path__):\n"
        "        importlib.import_module(pkg.__name__ + '.' + m.name)\n"
        "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in ('generator', 'spike_sim', 'reconstruct', 'polspike'))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert out.stdout.strip() == "", f"importing the foundation loaded: {out.stdout.strip()}"


def test_every_package_docstring_says_what_it_is():
    for pkg in PROJECT:
        doc = ast.get_docstring(ast.parse((REPO / pkg / "__init__.py").read_text())) or ""
        first = doc.splitlines()[0] if doc else ""
        assert first.startswith(f"{pkg}: ") and len(first) > len(pkg) + 20, f"{pkg}/__init__.py: first docstring line should say what the package is: {first!r}"


def test_stages_do_not_import_orchestration():
    for pkg in ("generator", "spike_sim", "reconstruct"):
        for f in _files(pkg):
            src = f.read_text()
            assert "polspike.pipeline" not in src and "polspike.cli" not in src and "polspike.commands" not in src, f


def test_every_random_draw_in_the_tests_is_seeded():
    """No test draws from torch's global generator or numpy's legacy global one: torch.rand / randn / randint /
    randperm (and *_like) take ``generator=``, numpy draws come from a seeded ``default_rng(seed)``.
    """
    import re

    tests = Path(__file__).resolve().parent
    torch_draw = re.compile(r"torch\.(rand|randn|randint|randperm|rand_like|randn_like|randint_like)\(")
    numpy_global = re.compile(r"np\.random\.(rand|randn|random|randint|normal|uniform|choice|permutation|shuffle|seed)\(|default_rng\(\)")
    bad = []
    for p in sorted(tests.rglob("*.py")):
        for n, line in enumerate(p.read_text().splitlines(), 1):
            if (torch_draw.search(line) and "generator=" not in line) or numpy_global.search(line):
                bad.append(f"{p.relative_to(tests)}:{n}: {line.strip()}")
    assert not bad, "unseeded random draws:\n" + "\n".join(bad)
