"""Dataset manifests: ``datasets/manifests/*.toml`` -> resolved, validated groups.

A manifest lists the groups of a dataset.  Each group is one spike stream with
its ground truth: a scene (a ``scenes/*.toml`` file and/or inline tables that
overlay :class:`generator.scene.SceneConfig`), the generator tier that renders
it, a seed, a duration, the spike simulator settings and its split.

Layout (format ``polspike-manifest/1``)::

    format = "polspike-manifest/1"
    name = "small"
    description = "..."
    allow_shared_content = false     # true disables the train/test content check

    [defaults]                       # any group key except name/split; groups overlay it
    tier = "analytic"
    duration_s = 1.0
    [defaults.camera]
    width = 400
    height = 250

    [[groups]]
    name = "train_000"               # folder name: letters, digits, '_', '-', '.'
    split = "train"                  # train | test
    scene = "scenes/brewster.toml"   # optional base scene (manifest folder, then repo root, then a default name)
    tier = "analytic"                # analytic | maps | full | auto (with tolerance = EPS: the planner picks
                                     # the cheapest tier and spp predicted to meet it; recorded as tier_plan)
    seed = 1                         # sensor/noise seed and render seed
    duration_s = 1.0                 # stream length (s)
    keyframe_fps = 100.0             # radiance keyframes per second (default: the scene's render.fps)
    [groups.camera]                  # overlays SceneConfig.camera (width, height, fov_deg, position, look_at, up, roll_deg)
    [groups.pane]                    # overlays SceneConfig.pane (model, n, glass, distance_m, tilt_deg, tilt_axis_deg, normal, ...)
    [groups.layers.transmission]     # overlays the T layer (source, distance_m, brightness, motion, sprites, ...)
    [groups.layers.reflection]       # overlays the R layer
    [groups.polarizer]               # overlays PolarizerConfig (rate_hz, phase_deg, extinction_ratio, ...)
    [groups.render]                  # overlays RenderSettings (spp, spectral: maps/full tiers; supersample: analytic on the pixel area)
    [groups.objects]                 # SceneConfig.objects: 3-D shapes / lights (full tier; sampler profile objects3d)
    [groups.spike_sim]               # preset = "default" | "ideal" | "noisy" | "plain_if", plus any SpikeSimConfig field
                                     # (or spike_sim = "ideal": a bare preset name)

Resolution order for a group's scene: SceneConfig defaults < base scene file <
``[defaults]`` tables < the group's own tables; the scene's ``name`` becomes the
group name and ``render.duration_s/seed/fps`` follow the group.  Everything is
validated strictly when the manifest is loaded (unknown keys, out-of-range
values and a pane that does not cover the view raise a one-line
:class:`~polinfra.errors.ConfigError` / :class:`~polinfra.errors.SceneError`
naming the file and the group).

Split: the split is per group, and by default no *layer content* may appear in
both splits (:func:`content_keys`: a layer or sprite source; procedural noise
counts per seed, ``skimage:cat`` is ``skimage:chelsea``).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import os
import re
from pathlib import Path
from typing import Any

from polinfra.config import from_dict, load_toml, opt, to_dict
from polinfra.errors import ConfigError, PolspikeError

__all__ = [
    "checked_manifest_text",
    "MANIFEST_FORMAT",
    "GroupSpec",
    "ResolvedGroup",
    "Manifest",
    "load_manifest",
    "parse_manifest",
    "content_keys",
    "check_split",
    "dump_manifest",
    "MANIFESTS_DIR",
]

MANIFEST_FORMAT = "polspike-manifest/1"
REPO_ROOT = Path(__file__).resolve().parents[2]
MANIFESTS_DIR = REPO_ROOT / "datasets" / "manifests"
"""Folder of the shipped manifests."""

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,99}$")
_SCENE_SECTIONS = ("camera", "pane", "layers", "polarizer", "render", "objects")
_CONTENT_ALIASES = {"skimage:cat": "skimage:chelsea"}  # skimage.data.cat() is the chelsea image
_CONTENT_FREE = frozenset({"procedural:flat", "procedural:disk"})  # no texture: shared use is no leak


@dataclasses.dataclass(frozen=True)
class GroupSpec:
    """One ``[[groups]]`` entry as written (scene tables are overlays, validated on resolution)."""

    name: str = opt(doc="group name = folder name under DIR/groups (letters, digits, '_', '-', '.')")
    split: str = opt(doc="train or test", choices=("train", "test"))
    scene: str | None = opt(None, "base scene TOML (path relative to the manifest, the repo root, or a default scene name)")
    description: str = opt("", "free text")
    tier: str = opt("analytic", "generator tier: analytic | maps | full | auto (the cheapest predicted to meet tolerance)", choices=("analytic", "maps", "full", "auto"))
    tolerance: float | None = opt(None, "tier = auto: largest acceptable p99 radiance error (generator.planner)", lo=0.0, hi=10.0, lo_open=True)
    seed: int = opt(0, "sensor/noise seed (also the render seed)", lo=0, hi=2**31 - 1)
    duration_s: float = opt(1.0, "stream length in seconds", lo=0.0, hi=3600.0, lo_open=True)
    keyframe_fps: float | None = opt(None, "radiance keyframes per second (default: the scene's render.fps)", lo=0.01, hi=20000.0)
    camera: Any = opt(None, "overlay on SceneConfig.camera")
    pane: Any = opt(None, "overlay on SceneConfig.pane")
    layers: Any = opt(None, "overlay on SceneConfig.layers (transmission / reflection tables)")
    polarizer: Any = opt(None, "overlay on SceneConfig.polarizer")
    render: Any = opt(None, "overlay on SceneConfig.render (spp, spectral)")
    objects: Any = opt(None, "SceneConfig.objects: 3-D shapes and lights on both sides of the pane (full tier only)")
    spike_sim: Any = opt(None, "spike simulator: preset = default|ideal|noisy plus SpikeSimConfig overrides")


@dataclasses.dataclass(frozen=True)
class ResolvedGroup:
    """A group ready to build: plain-data resolved scene and simulator config.

    Attributes:
        name, split, tier, seed, duration_s, keyframe_fps: as in the manifest.
        scene: resolved SceneConfig as a plain dict (:func:`polinfra.config.to_dict`).
        spike_sim: resolved SpikeSimConfig as a plain dict.
        spec_sha256: hash of everything that determines the group's content
            (not the split or description).
    """

    name: str
    split: str
    tier: str
    seed: int
    duration_s: float
    keyframe_fps: float
    scene: dict
    spike_sim: dict
    spec_sha256: str
    tier_plan: dict | None = None
    """``tier = auto``: the planner's choice, predictions and reasons (:mod:`generator.planner`)."""

    def build_spec(self) -> dict:
        """Plain data sent to a build worker (and stored as GROUP/group_spec.json)."""
        return {
            "format": "polspike-group-spec/1",
            "name": self.name,
            "tier": self.tier,
            "seed": self.seed,
            "duration_s": self.duration_s,
            "keyframe_fps": self.keyframe_fps,
            "scene": self.scene,
            "spike_sim": self.spike_sim,
            "spec_sha256": self.spec_sha256,
            **({"tier_plan": self.tier_plan} if self.tier_plan is not None else {}),
        }


@dataclasses.dataclass(frozen=True)
class Manifest:
    """A loaded manifest.

    Attributes:
        name, description: dataset name and text.
        groups: resolved groups in manifest order.
        source_text: the manifest file's bytes (copied into the built dataset).
        sha256: hash of ``source_text``.
        path: where it was read from ("" when parsed from text).
    """

    name: str
    description: str
    groups: tuple[ResolvedGroup, ...]
    source_text: bytes
    sha256: str
    path: str = ""

    def group(self, name: str) -> ResolvedGroup:
        """The group called ``name`` (ConfigError listing the names when absent)."""
        for g in self.groups:
            if g.name == name:
                return g
        raise ConfigError(f"manifest {self.name!r} has no group {name!r}; groups: {', '.join(g.name for g in self.groups)}")


@dataclasses.dataclass(frozen=True)
class _ManifestHead:
    name: str = opt(doc="dataset name")
    format: str = opt(MANIFEST_FORMAT, "manifest format tag", choices=(MANIFEST_FORMAT,))
    description: str = opt("", "free text")
    allow_shared_content: bool = opt(False, "allow the same layer content in train and test groups")
    defaults: Any = opt(None, "group keys applied to every group (groups overlay them)")
    groups: Any = opt(None, "the [[groups]] list")


def _deep_merge(base: dict, over: dict) -> dict:
    """``over`` overlaid on ``base`` (tables merge recursively; other values replace)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _canon(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _find_scene(ref: str, base_dir: Path | None, where: str) -> Path:
    cands = []
    p = Path(ref)
    if p.is_absolute():
        cands.append(p)
    else:
        if base_dir is not None:
            cands.append(base_dir / p)
        cands.append(REPO_ROOT / p)
        cands.append(REPO_ROOT / "scenes" / (p.name if p.suffix else f"{p.name}.toml"))
    for c in cands:
        if c.is_file():
            return c
    raise ConfigError(f"{where}: scene {ref!r} not found (looked in the manifest folder, {REPO_ROOT} and scenes/); give a scenes/*.toml path")


def _resolve_group(raw: dict, defaults: dict, base_dir: Path | None, where: str) -> ResolvedGroup:
    from generator.scene import SceneConfig, check_scene_geometry, scene_from_dict
    from spike_sim.config import SpikeSimConfig, preset

    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: every [[groups]] entry must be a table, got {type(raw).__name__}")
    label = f"{where} group {raw.get('name', '?')!r}"
    for k in ("name", "split"):
        if k in defaults:
            raise ConfigError(f"{where}: [defaults] may not set {k!r}; set it in each [[groups]] entry")
    merged = _deep_merge(defaults, raw)
    spec = from_dict(GroupSpec, merged, where=label)
    if not _NAME_RE.match(spec.name):
        raise ConfigError(f"{label}: name {spec.name!r} must be 1-100 letters, digits, '_', '-' or '.', starting with a letter or digit")
    base = to_dict(SceneConfig())
    if spec.scene:
        base = _deep_merge(base, load_toml(_find_scene(spec.scene, base_dir, label)))
    for sec in _SCENE_SECTIONS:
        ov = getattr(spec, sec)
        if ov is None:
            continue
        if not isinstance(ov, dict):
            raise ConfigError(f"{label}: [{sec}] must be a table, got {ov!r}")
        base = _deep_merge(base, {sec: ov})
    base["name"] = spec.name
    base.setdefault("render", {})
    fps = spec.keyframe_fps if spec.keyframe_fps is not None else float(base["render"].get("fps", 100.0))
    base["render"] = {**base["render"], "duration_s": spec.duration_s, "seed": spec.seed, "fps": fps}
    try:
        scene = scene_from_dict(base, where=label)
        check_scene_geometry(_coarse(scene))
    except PolspikeError as exc:
        msg = str(exc)
        raise type(exc)(msg if msg.startswith(label) else f"{label}: {msg}") from None
    ss = spec.spike_sim if spec.spike_sim is not None else {}
    if isinstance(ss, str):  # spike_sim = "ideal": a bare preset name
        ss = {"preset": ss}
    if not isinstance(ss, dict):
        raise ConfigError(f"{label}: spike_sim = {ss!r} must be a preset name or a table (preset = ..., plus SpikeSimConfig keys)")
    ss = dict(ss)
    pname = ss.pop("preset", "default")
    if not isinstance(pname, str):
        raise ConfigError(f"{label}: spike_sim.preset = {pname!r} must be a preset name")
    try:
        sim_base = to_dict(preset(pname))
    except ConfigError as exc:
        raise ConfigError(f"{label}: {exc}") from None
    sim_base.update(ss)
    sim_base["width"], sim_base["height"] = scene.camera.width, scene.camera.height
    sim = from_dict(SpikeSimConfig, sim_base, where=f"{label} [spike_sim]")
    tier, plan = spec.tier, None
    if spec.tier == "auto":
        scene, tier, plan = _auto_tier(scene, spec.tolerance, label)
    elif spec.tolerance is not None:
        raise ConfigError(f"{label}: tolerance is for tier = 'auto' (tier is {spec.tier!r})")
    scene_d, sim_d = to_dict(scene), to_dict(sim)
    key = {"tier": tier, "seed": spec.seed, "duration_s": spec.duration_s, "keyframe_fps": fps, "scene": scene_d, "spike_sim": sim_d}
    h = hashlib.sha256(_canon(key).encode()).hexdigest()
    return ResolvedGroup(spec.name, spec.split, tier, spec.seed, spec.duration_s, float(fps), scene_d, sim_d, h, plan)


def _auto_tier(scene, tolerance: float | None, label: str):
    """(scene with the planned spp / spectral, tier, plan dict) of a ``tier = auto`` group."""
    from generator.planner import plan_tier

    if tolerance is None:
        raise ConfigError(f"{label}: tier = 'auto' needs tolerance = EPS (largest acceptable p99 radiance error)")
    try:
        plan = plan_tier(scene, tolerance, analytic_spectral=False)  # the dataset builder's analytic source is mono
    except PolspikeError as exc:
        raise type(exc)(f"{label}: {exc}") from None
    c = plan.choice
    if c.tier == "full":
        scene = dataclasses.replace(scene, render=dataclasses.replace(scene.render, spp=int(c.spp), spectral=bool(c.spectral)))
    elif c.tier == "analytic":  # the plan's pixel sampling (point or area), whatever the group's [render] said
        scene = dataclasses.replace(scene, render=dataclasses.replace(scene.render, supersample=int(c.supersample)))
    return scene, c.tier, plan.to_dict()


def _coarse(scene):
    """The scene seen by a camera of at most 80 pixels across (same field of view): a fast
    coverage / edge-on check at load time; the build checks again at full resolution.
    """
    w, h = scene.camera.width, scene.camera.height
    if w <= 80:
        return scene
    w2 = 80
    h2 = max(2, int(round(h * w2 / w)))
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=w2, height=h2))


def parse_manifest(data: dict, where: str = "manifest", base_dir: Path | None = None, source_text: bytes | None = None) -> Manifest:
    """Validate plain manifest data (see the module docstring) into a :class:`Manifest`."""
    head = from_dict(_ManifestHead, data, where=where)
    defaults = head.defaults or {}
    if not isinstance(defaults, dict):
        raise ConfigError(f"{where}: [defaults] must be a table")
    groups_raw = head.groups
    if not isinstance(groups_raw, list) or not groups_raw:
        raise ConfigError(f"{where}: no [[groups]] entries; add at least one group")
    groups = tuple(_resolve_group(g, defaults, base_dir, where) for g in groups_raw)
    seen: set[str] = set()
    for g in groups:
        if g.name in seen:
            raise ConfigError(f"{where}: group name {g.name!r} appears twice; group names must be unique")
        seen.add(g.name)
    if not head.allow_shared_content:
        check_split(groups, where)
    text = source_text if source_text is not None else _canon(data).encode()
    return Manifest(head.name, head.description, groups, text, hashlib.sha256(text).hexdigest())


def load_manifest(path: str | os.PathLike) -> Manifest:
    """Load ``path`` (or a shipped manifest name such as ``small``) strictly."""
    p = Path(path)
    if not p.exists() and not p.suffix and (MANIFESTS_DIR / f"{p.name}.toml").is_file():
        p = MANIFESTS_DIR / f"{p.name}.toml"
    if not p.is_file():
        shipped = sorted(q.stem for q in MANIFESTS_DIR.glob("*.toml"))
        raise ConfigError(f"manifest not found: {path}; give a .toml path or one of {shipped}")
    data = load_toml(p)
    m = parse_manifest(data, where=str(p), base_dir=p.resolve().parent, source_text=p.read_bytes())
    return dataclasses.replace(m, path=str(p))


def content_keys(scene: dict) -> set[str]:
    """Identities of the layer content a resolved scene uses (T, R and sprites).

    ``procedural:noise`` is seeded, so its key carries the seed; other procedural
    kinds are the same image whatever the seed.  Content-free shapes
    (``procedural:flat``, ``procedural:disk``: a constant or a uniform disc, e.g. a
    specular highlight) carry no texture to learn and are not keys.
    """
    keys: set[str] = set()
    for lname in ("transmission", "reflection"):
        lay = scene["layers"][lname]
        srcs = [(lay["source"], int(lay.get("seed", 0)))]
        srcs += [(sp["source"], int(lay.get("seed", 0)) + 1 + i) for i, sp in enumerate(lay.get("sprites", ()))]
        for src, seed in srcs:
            k = _CONTENT_ALIASES.get(src, src)
            if k in _CONTENT_FREE:
                continue
            if k == "procedural:noise":
                k = f"{k}#seed={seed}"
            keys.add(k)
    return keys


def check_split(groups: tuple[ResolvedGroup, ...] | list[ResolvedGroup], where: str = "manifest") -> None:
    """ConfigError when a layer content key is used by a train and a test group."""
    owner: dict[str, dict[str, str]] = {"train": {}, "test": {}}
    for g in groups:
        for k in content_keys(g.scene):
            owner[g.split].setdefault(k, g.name)
    shared = sorted(set(owner["train"]) & set(owner["test"]))
    if shared:
        k = shared[0]
        raise ConfigError(
            f"{where}: layer content {k!r} is used by train group {owner['train'][k]!r} and test group {owner['test'][k]!r}"
            f" ({len(shared)} shared in all); use different content per split or set allow_shared_content = true"
        )


# ---- TOML writing (for the sampler) --------------------------------------------------------------

def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        r = repr(v)
        return r if ("." in r or "e" in r or "inf" in r or "nan" in r) else r + ".0"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_table(lines: list[str], prefix: str, d: dict, array_item: bool = False) -> None:
    scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and not (isinstance(v, list) and v and isinstance(v[0], dict))}
    tables = {k: v for k, v in d.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in d.items() if isinstance(v, list) and v and isinstance(v[0], dict)}
    if prefix:
        lines.append(f"[[{prefix}]]" if array_item else f"[{prefix}]")
    for k, v in scalars.items():
        if v is None:
            continue
        lines.append(f"{k} = {_toml_value(v)}")
    for k, v in tables.items():
        _toml_table(lines, f"{prefix}.{k}" if prefix else k, v)
    for k, items in arrays.items():
        for it in items:
            _toml_table(lines, f"{prefix}.{k}" if prefix else k, it, array_item=True)


def dump_manifest(data: dict, header: str = "") -> str:
    """TOML text of a plain manifest dict (tables, arrays of tables, scalars, lists of scalars)."""
    lines = [f"# {ln}" if ln else "#" for ln in header.splitlines()] if header else []
    top = {k: v for k, v in data.items() if k != "groups"}
    _toml_table(lines, "", top)
    for g in data.get("groups", []):
        lines.append("")
        _toml_table(lines, "groups", g, array_item=True)
    return "\n".join(lines) + "\n"


def checked_manifest_text(data: dict, header: str, where: str) -> str:
    """:func:`dump_manifest` of ``data``, parsed back as a manifest (errors name ``where``) before it is returned."""
    import tomllib

    text = dump_manifest(data, header=header)
    parse_manifest(tomllib.loads(text), where=where, source_text=text.encode())
    return text
