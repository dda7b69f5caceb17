"""The pipeline's import rules, checked on the source with ast.

- reconstruct never imports generator (it must run on real captures);
- spike_sim never imports generator;
- only generator imports mitsuba/drjit, and only inside functions (lazy);
- polspike's library modules (not the CLI, commands or the pipeline orchestration layer) import no stage;
- no stage imports polspike.pipeline or the CLI.
"""

from __future__ import annotations

import ast
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
    for pkg in ("polspike", "spike_sim", "reconstruct", "generator"):
        for f in _files(pkg):
            top, allimp = _imports(f)
            assert not ({"mitsuba", "drjit"} & top), f"{f} imports mitsuba at module level"
            if pkg != "generator" and f.name != "render_bench.py":
                assert not ({"mitsuba", "drjit"} & allimp), f"{f} imports mitsuba outside generator"


def test_polspike_library_imports_no_stage():
    for f in _files("polspike"):
        if "commands" in f.parts or "pipeline" in f.parts or f.name == "cli.py":
            continue
        _, allimp = _imports(f)
        assert not ({"generator", "spike_sim", "reconstruct"} & allimp), f"{f} imports a pipeline stage"


def test_stages_do_not_import_orchestration():
    for pkg in ("generator", "spike_sim", "reconstruct"):
        for f in _files(pkg):
            src = f.read_text()
            assert "polspike.pipeline" not in src and "polspike.cli" not in src and "polspike.commands" not in src, f
