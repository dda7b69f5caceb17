"""Build-time reference pages (run by mkdocs-gen-files): the CLI, every TOML schema and the Python API.

Everything is read from the code when the site is built, so the pages follow the code:

* ``reference/cli.md``: the typer app's click tree (every command, argument and option, its type,
  default and help);
* ``reference/configs.md``: every typed config dataclass (fields declared with
  :func:`polinfra.config.opt`), found by walking the packages, with its nested sections;
* ``reference/api/...``: one page per module, found by walking the packages (``pkgutil``), rendered
  by mkdocstrings; a module that moves gets its page under its new name.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import pkgutil
import typing
from pathlib import Path

import mkdocs_gen_files

log = logging.getLogger("mkdocs.plugins.gen_ref")

PACKAGES = ("polinfra", "polphysics", "generator", "spike_sim", "reconstruct", "polspike")
PACKAGE_ROLE = {
    "polinfra": "errors, strict typed TOML configs, atomic I/O, EXR, progress, plots",
    "polphysics": "Fresnel, pane models, geometry, zeta (paper Eq. (1)-(2)), Stokes, the rotating polarizer",
    "generator": "scenes, layer content and motion, the analytic / maps / full tiers, validate-zeta",
    "spike_sim": "the 20 kHz integrate-and-fire camera, Eq. (3) aggregation, .dat I/O, the group store",
    "reconstruct": "alignment, the physics solvers, self-calibration, PolSpikeNet, training, evaluation, video",
    "polspike": "the CLI, the dataset pipeline, benches, the demo and its report",
}
#: Where each top-level schema is written, by class name (not module path: modules move).
SCHEMA_TITLES = {
    "SceneConfig": "Scene file",
    "_ManifestHead": "Dataset manifest",
    "GroupSpec": "Manifest group",
    "SpikeSimConfig": "Spike simulator",
    "TrainConfig": "Training config",
}
SCHEMA_FILES = {
    "SceneConfig": "a scene file, `scenes/*.toml` (`polspike render`, `validate-zeta`, manifests' `scene = ...`)",
    "_ManifestHead": "the head of a dataset manifest, `datasets/manifests/*.toml` (`polspike dataset build`)",
    "GroupSpec": "each `[[groups]]` entry of a dataset manifest (and its `[defaults]` table)",
    "SpikeSimConfig": "the `spike_sim` table of a manifest group (after `preset = ...`), and the simulator's Python config",
    "TrainConfig": "a training config, `reconstruct/configs/*.toml` (`polspike train`)",
}


def _md(text: str) -> str:
    """One table cell: no pipes, no raw HTML, one line."""
    return " ".join(str(text).split()).replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


# ---------------------------------------------------------------------------------------------- CLI
def _ann_name(p) -> str:
    desc = getattr(p, "type_descriptor", None)
    ann = getattr(desc, "annotation", None)
    if ann is None:
        return ""
    name = getattr(ann, "__name__", None) or str(ann).replace("typing.", "")
    return {"Path": "path", "str": "text", "int": "integer", "float": "number", "bool": "flag"}.get(name, name)


def _param_row(p) -> str:
    is_arg = type(p).__name__.endswith("Argument")
    names = p.name.upper() if is_arg else ", ".join(f"`{o}`" for o in [*p.opts, *p.secondary_opts])
    if is_arg:
        names = f"`{names}`"
    default = p.default
    shown = "" if (p.required or default is None or callable(default) or getattr(p, "count", False) and default == 0) else f"`{default}`"
    if getattr(p, "is_flag", False) and default is False:
        shown = "off"
    kind = "flag" if getattr(p, "is_flag", False) else ("count" if getattr(p, "count", False) else _ann_name(p))
    req = " (required)" if p.required else ""
    return f"| {names}{req} | {kind} | {_md(shown)} | {_md(getattr(p, 'help', '') or '')} |"


def _walk_commands(cmd, path: list[str]):
    yield path, cmd
    for name, sub in sorted((getattr(cmd, "commands", None) or {}).items()):
        if not getattr(sub, "hidden", False):
            yield from _walk_commands(sub, [*path, name])


def cli_page() -> str:
    import typer.main

    from polspike.cli import get_app

    root = typer.main.get_command(get_app())
    out = [
        "# Command line",
        "",
        "Generated from the `polspike` typer app when this site was built: every command, its arguments and",
        "options with type, default and meaning. `polspike COMMAND --help` prints the same in the terminal.",
        "Bad input prints one line (`error: ...`) and exits with code 2; `validate-zeta` and `calibrate` exit",
        "with code 1 on a \"fail\" verdict.",
        "",
    ]
    cmds = list(_walk_commands(root, ["polspike"]))
    out += ["| command | what it does |", "|---|---|"]
    for path, cmd in cmds[1:]:
        if getattr(cmd, "commands", None):
            continue
        anchor = "-".join(path).lower()
        out.append(f"| [`{' '.join(path)}`](#{anchor}) | {_md((cmd.help or '').strip().split(chr(10))[0])} |")
    out.append("")
    for path, cmd in cmds:
        title = " ".join(path)
        anchor = "-".join(path).lower()
        out += [f"## `{title}` {{#{anchor}}}", ""]
        if cmd.help:
            out += [cmd.help.strip().replace("\b\n", ""), ""]
        if getattr(cmd, "commands", None):
            subs = ", ".join(f"[`{n}`](#{anchor}-{n.lower()})" for n in sorted(cmd.commands))
            out += [f"Subcommands: {subs}.", ""]
        params = [p for p in cmd.params if not getattr(p, "hidden", False)]
        if params:
            out += ["| argument / option | type | default | meaning |", "|---|---|---|---|"]
            out += [_param_row(p) for p in params]
            out.append("")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------ configs
def _modules(pkg: str) -> list[str]:
    root = importlib.import_module(pkg)
    return [pkg] + sorted(m.name for m in pkgutil.walk_packages(root.__path__, pkg + "."))


def _is_config(obj) -> bool:
    if not (isinstance(obj, type) and dataclasses.is_dataclass(obj)):
        return False
    fs = dataclasses.fields(obj)
    return bool(fs) and any("doc" in f.metadata for f in fs)


def find_configs() -> dict[str, type]:
    """Every typed config dataclass of the packages, by ``module.Class``."""
    found: dict[str, type] = {}
    for pkg in PACKAGES:
        for m in _modules(pkg):
            try:
                mod = importlib.import_module(m)
            except Exception as exc:  # a module that cannot import (optional backend) has no schema to show
                log.info("gen_ref: skipping %s (%s)", m, exc)
                continue
            for name, obj in vars(mod).items():
                if _is_config(obj) and obj.__module__ == m:
                    found[f"{m}.{name}"] = obj
    return found


def _nested(tp) -> list[type]:
    if _is_config(tp):
        return [tp]
    return [c for a in typing.get_args(tp) for c in _nested(a)]


def _default(f) -> str:
    if f.default is not dataclasses.MISSING:
        return "" if _is_config(type(f.default)) else repr(f.default)
    if f.default_factory is not dataclasses.MISSING:
        v = f.default_factory()
        return "" if _is_config(type(v)) else repr(v)
    return "required"


def _schema_table(cls: type, section: str) -> list[str]:
    from polinfra.config import describe

    hints = typing.get_type_hints(cls)
    out = []
    if section:
        out += [f"### `[{section}]`", ""]
    doc = (cls.__doc__ or "").strip()
    if doc and not doc.startswith(cls.__name__ + "("):  # a dataclass without a docstring gets its signature
        out += [_md(doc.split("\n\n")[0]), ""]
    out += ["| key | type | default | meaning, unit, range |", "|---|---|---|---|"]
    subs = []
    rows = {r[0]: r for r in describe(cls)}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        nested = _nested(hints[f.name])
        tp = "table" if nested else _md(rows[f.name][1])
        text = f.metadata.get("doc", "")
        rng = rows[f.name][3][len(text):].strip()
        if rng:
            text += f"; {rng}"
        if f.metadata.get("choices"):
            text += "; one of " + ", ".join(map(str, f.metadata["choices"]))
        out.append(f"| `{f.name}` | {tp} | {_md(_default(f))} | {_md(text)} |")
        for n in nested:
            subs.append((n, f"{section}.{f.name}" if section else f.name))
    out.append("")
    for n, sec in subs:
        out += _schema_table(n, sec)
    return out


def configs_page() -> str:
    configs = find_configs()
    nested_somewhere = set()
    for cls in configs.values():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            nested_somewhere.update(_nested(hints[f.name]))
    roots = [(k, c) for k, c in configs.items() if c not in nested_somewhere]
    roots.sort(key=lambda kc: (kc[1].__name__ not in SCHEMA_FILES, list(SCHEMA_FILES).index(kc[1].__name__) if kc[1].__name__ in SCHEMA_FILES else 0, kc[0]))
    out = [
        "# TOML schemas",
        "",
        "Generated from the typed config dataclasses when this site was built (every field is declared with",
        "`polinfra.config.opt`: meaning, unit, default and allowed range). Loading is strict: an unknown key, a",
        "value of the wrong type or out of range is refused with one line naming the file, the key, the value",
        "and what is allowed. Nested tables are the dotted sections below each schema.",
        "",
    ]
    for qual, cls in roots:
        where = SCHEMA_FILES.get(cls.__name__, "the options of the command or library call that takes it")
        name = cls.__name__.lstrip("_")
        title = f"{SCHEMA_TITLES[cls.__name__]} (`{name}`)" if cls.__name__ in SCHEMA_TITLES else f"`{name}`"
        out += [f"## {title} {{#{name.lower()}}}", "", f"Written in: {where}. Defined in `{cls.__module__}`.", ""]
        out += _schema_table(cls, "")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------- API
def api_pages() -> None:
    index = [
        "# Python API",
        "",
        "One page per module, found by walking the packages when this site was built (docstrings rendered by",
        "mkdocstrings). The packages are layered: each imports only those above it in this list.",
        "",
    ]
    for pkg in PACKAGES:
        index += [f"## `{pkg}`", "", PACKAGE_ROLE[pkg] + ".", ""]
        for m in _modules(pkg):
            parts = m.split(".")
            if parts[-1].startswith("_") and parts[-1] != "__init__":
                continue
            doc_path = Path("reference", "api", *parts).with_suffix(".md") if m != pkg else Path("reference", "api", pkg, "index.md")
            with mkdocs_gen_files.open(doc_path, "w") as fh:
                fh.write(f"# `{m}`\n\n::: {m}\n")
            rel = doc_path.relative_to("reference/api").as_posix()
            depth = "&nbsp;&nbsp;" * (len(parts) - 1)
            index.append(f"- {depth}[`{m}`]({rel})")
        index.append("")
    with mkdocs_gen_files.open("reference/api/index.md", "w") as fh:
        fh.write("\n".join(index))


with mkdocs_gen_files.open("reference/cli.md", "w") as fh:
    fh.write(cli_page())
with mkdocs_gen_files.open("reference/configs.md", "w") as fh:
    fh.write(configs_page())
api_pages()

# the changelog lives at the repository root; the site shows it as a page
_changelog = Path(__file__).resolve().parents[2] / "CHANGELOG.md"
with mkdocs_gen_files.open("changelog.md", "w") as fh:
    fh.write(_changelog.read_text() if _changelog.is_file() else "# Changelog\n")
