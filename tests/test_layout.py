"""The house rules, checked on the source with ast.

- Inside ``reconstruct/`` the sub-packages are floors, bottom to top::

      physics -> stream -> pane -> net -> video -> evaluate

  ``physics`` (harmonic fit, RIR, solvers, zeta maps) reads arrays only; ``stream`` (sources, groups,
  display) reads spikes; ``pane`` (the self-calibration and calibrate-pane's fit) reads frames from a
  stream; ``net`` (the network, its training and checkpoints); ``video`` runs a model over a stream;
  ``evaluate`` scores all of them.  A module imports its own floor and the floors below, never above.
- No import circle between files anywhere in the project, counting the imports inside functions
  too (a lazy import hides a circle from the interpreter, not from the reader).
- No module of the library floors is longer than ``MAX_LINES``; ``polspike/commands/*`` and
  ``polspike/cli.py`` (command wiring) are exempt, and so is a module whose docstring says
  ``Kept whole:`` followed by the reason.

Each checker is a plain function over a source root, so the tests below also run it on a small
tree with a deliberate break and see it fail.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROJECT = ("polinfra", "polphysics", "generator", "spike_sim", "reconstruct", "polspike")
RECONSTRUCT_FLOORS = ("physics", "stream", "pane", "net", "video", "evaluate")
MAX_LINES = 700
EXEMPT_MARK = "Kept whole:"


def _modules(root: Path, packages=PROJECT) -> dict[str, Path]:
    mods = {}
    for pkg in packages:
        for f in sorted((root / pkg).rglob("*.py")):
            name = ".".join(f.relative_to(root).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = f
    return mods


def import_graph(root: Path, packages=PROJECT) -> dict[str, set[str]]:
    """Module -> the project modules it imports anywhere in its body (module level or inside functions)."""
    mods = _modules(root, packages)
    graph = {}
    for name, f in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module in mods:
                    deps.add(node.module)
                deps |= {f"{node.module}.{a.name}" for a in node.names if f"{node.module}.{a.name}" in mods}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name in mods}
        graph[name] = deps - {name}
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def floor_violations(graph: dict[str, set[str]], package: str = "reconstruct", floors=RECONSTRUCT_FLOORS) -> list[str]:
    """Imports from a sub-package of ``package`` into a higher floor, and modules of ``package`` outside every floor."""
    rank = {f: i for i, f in enumerate(floors)}
    bad = []
    for mod, deps in graph.items():
        parts = mod.split(".")
        if parts[0] != package or len(parts) < 2:
            continue
        if parts[1] not in rank:
            bad.append(f"{mod} lies outside the floors {floors}")
            continue
        for d in sorted(deps):
            dp = d.split(".")
            if dp[0] == package and len(dp) > 1 and dp[1] in rank and rank[dp[1]] > rank[parts[1]]:
                bad.append(f"{mod} ({parts[1]}) imports {d} ({dp[1]}), a higher floor")
    return bad


def long_modules(root: Path, packages=PROJECT, max_lines: int = MAX_LINES) -> list[str]:
    """Library modules over ``max_lines`` lines, less the command wiring and modules marked as kept whole."""
    bad = []
    for name, f in _modules(root, packages).items():
        if name.startswith("polspike.commands") or name == "polspike.cli":
            continue
        n = len(f.read_text().splitlines())
        if n <= max_lines:
            continue
        doc = ast.get_docstring(ast.parse(f.read_text())) or ""
        if EXEMPT_MARK in doc:
            continue
        bad.append(f"{f.relative_to(root)}: {n} lines > {max_lines}")
    return bad


# -- the project ---------------------------------------------------------------------------------


def test_reconstruct_sub_packages_keep_their_floors():
    bad = floor_violations(import_graph(REPO))
    assert not bad, "imports that run up a floor inside reconstruct/:\n" + "\n".join(bad)


def test_reconstruct_modules_all_live_in_a_floor():
    top = sorted(p.name for p in (REPO / "reconstruct").glob("*.py") if p.name != "__init__.py")
    assert not top, f"modules directly under reconstruct/ (put each in one of {RECONSTRUCT_FLOORS}): {top}"
    subs = sorted(p.parent.name for p in (REPO / "reconstruct").glob("*/__init__.py"))
    assert subs == sorted(RECONSTRUCT_FLOORS)


def test_no_import_circle_between_files():
    circles = import_circles(import_graph(REPO))
    assert not circles, "import circles (imports inside functions count):\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_no_library_module_over_the_line_limit():
    bad = long_modules(REPO)
    assert not bad, f"modules over {MAX_LINES} lines (split by concern, or say '{EXEMPT_MARK} <why>' in the docstring):\n" + "\n".join(bad)


# -- each rule fails on a deliberate break --------------------------------------------------------


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        p = tmp_path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    for d in {(tmp_path / rel).parent for rel in files}:
        while d != tmp_path:
            (d / "__init__.py").touch()
            d = d.parent
    return tmp_path


def test_floor_rule_fails_on_physics_importing_net(tmp_path):
    root = _tree(tmp_path, {
        "reconstruct/physics/solvers.py": "def f():\n    from reconstruct.net.network import PolSpikeNet\n",
        "reconstruct/net/network.py": "from reconstruct.physics.solvers import f\nPolSpikeNet = 1\n",
    })
    bad = floor_violations(import_graph(root, ("reconstruct",)))
    assert bad == ["reconstruct.physics.solvers (physics) imports reconstruct.net.network (net), a higher floor"]


def test_floor_rule_fails_on_a_module_outside_the_floors(tmp_path):
    root = _tree(tmp_path, {"reconstruct/misc/helpers.py": "x = 1\n"})
    assert floor_violations(import_graph(root, ("reconstruct",))) == [
        "reconstruct.misc lies outside the floors ('physics', 'stream', 'pane', 'net', 'video', 'evaluate')",
        "reconstruct.misc.helpers lies outside the floors ('physics', 'stream', 'pane', 'net', 'video', 'evaluate')",
    ]


def test_circle_rule_fails_on_a_lazy_circle(tmp_path):
    root = _tree(tmp_path, {
        "generator/a.py": "from generator.b import g\n",
        "generator/b.py": "def g():\n    from generator import a\n",
        "generator/c.py": "from generator.a import g\n",
    })
    assert import_circles(import_graph(root, ("generator",))) == [["generator.a", "generator.b"]]


def test_line_rule_fails_on_a_long_module_unless_it_says_why(tmp_path):
    long_body = "x = 1\n" * (MAX_LINES + 1)
    root = _tree(tmp_path, {
        "spike_sim/big.py": '"""A big module."""\n' + long_body,
        "spike_sim/whole.py": f'"""A big module.\n\n{EXEMPT_MARK} one generated table.\n"""\n' + long_body,
        "polspike/commands/wiring.py": long_body,
    })
    assert long_modules(root, ("spike_sim", "polspike")) == [f"spike_sim/big.py: {MAX_LINES + 2} lines > {MAX_LINES}"]
