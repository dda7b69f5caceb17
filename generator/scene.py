"""Scene schema: ``scenes/*.toml`` → :class:`SceneConfig` (frozen dataclasses).

A scene is a pinhole camera looking through a glass pane at a transmission (T)
layer behind it, while the pane reflects a reflection (R) layer on the camera
side into view; a polarizer spins in front of the camera.  Both layers are
textured planes: the T plane is perpendicular to the camera axis at
``layers.transmission.distance_m`` from the camera; the R plane is
perpendicular to the mirrored camera's axis, ``layers.reflection.distance_m``
beyond the pane along the reflected optical axis.  Each plane is sized to fill
its camera's view with a margin, so the layer texture maps onto the image.

Every field documents its unit and range; unknown keys and out-of-range values
raise :class:`~polinfra.errors.ConfigError` naming the key (see
:mod:`polinfra.config`).  Degrees appear only here (``*_deg``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np

from generator.objects_config import ObjectsConfig
from polinfra.config import from_dict, load_toml, opt, to_dict
from polinfra.errors import ConfigError, SceneError
from polphysics.fresnel import GLASSES, PANE_MODELS, glass_index
from polphysics.geometry import PinholeCamera, Plane, normalize
from polphysics.polarizer import PolarizerConfig

__all__ = [
    "CameraConfig",
    "PaneConfig",
    "MotionConfig",
    "SpriteConfig",
    "LayerConfig",
    "LayersConfig",
    "RenderSettings",
    "SceneConfig",
    "load_scene",
    "scene_from_dict",
    "scene_hash",
    "default_scenes",
    "SCENES_DIR",
]

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"
"""Folder of the shipped default scenes."""

Vec3 = tuple[float, float, float]


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera (the spike camera's lens), world frame in metres."""

    width: int = opt(400, "image width in pixels", lo=2, hi=8192)
    height: int = opt(250, "image height in pixels", lo=2, hi=8192)
    fov_deg: float = opt(50.0, "horizontal field of view in degrees", lo=1.0, hi=150.0)
    position: Vec3 = opt((0.0, 0.0, 0.0), "camera centre (m)")
    look_at: Vec3 = opt((0.0, 0.0, -1.0), "a point the optical axis passes through (m)")
    up: Vec3 = opt((0.0, 1.0, 0.0), "world direction that appears up in the image")
    roll_deg: float = opt(0.0, "roll of the image about the optical axis, degrees counter-clockwise", lo=-180.0, hi=180.0)


@dataclasses.dataclass(frozen=True)
class PaneConfig:
    """The glass pane between camera and T layer."""

    model: str = opt("thin_slab", "pane model: single (one interface), thin_slab (two interfaces, incoherent), thick_slab (plus displaced ghost)", choices=PANE_MODELS)
    n: float | None = opt(1.5, "relative refractive index (used when glass is not given)", lo=0.0, hi=4.0, lo_open=True)
    glass: str | None = opt(None, f"named dispersive glass, one of {sorted(GLASSES)} (overrides n; n at 550 nm in mono)")
    distance_m: float = opt(1.0, "distance from the camera to the pane centre along the optical axis (m)", lo=0.01, hi=1000.0)
    tilt_deg: float = opt(0.0, "angle between the pane normal and the optical axis, degrees", lo=0.0, hi=89.0)
    tilt_axis_deg: float = opt(90.0, "image-plane direction of the tilt axis, degrees from image +x toward up (90 = tilt about the vertical axis)", lo=-360.0, hi=360.0)
    normal: Vec3 | None = opt(None, "explicit pane normal in world coordinates (overrides tilt)")
    size_m: tuple[float, float] = opt((4.0, 3.0), "pane width and height (m)", lo=0.001, hi=1000.0)
    thickness_mm: float = opt(5.0, "slab thickness (mm); ignored for single", lo=0.0, hi=1000.0)
    absorption_per_mm: float = opt(0.0, "absorption coefficient inside the glass (1/mm)", lo=0.0, hi=100.0)

    def __post_init__(self) -> None:
        if self.glass is not None and self.glass.upper() not in GLASSES:
            raise ConfigError(f"pane.glass = {self.glass!r} is unknown; choose one of {sorted(GLASSES)} or give pane.n")
        if self.glass is None and self.n is None:
            raise ConfigError("pane needs n (refractive index) or glass")
        if self.model != "single" and self.index() < 1.0:
            raise ConfigError(f"pane.n = {self.index()} < 1 is only meaningful for model = 'single' (light leaving glass); slabs need n >= 1")

    def index(self, wavelength_nm: float = 550.0) -> float:
        """Refractive index at ``wavelength_nm`` (named glass) or the fixed n."""
        if self.glass is not None:
            return float(glass_index(self.glass, wavelength_nm))
        return float(self.n)

    @property
    def thickness_m(self) -> float:
        return self.thickness_mm * 1e-3

    @property
    def absorption_per_m(self) -> float:
        return self.absorption_per_mm * 1e3


@dataclasses.dataclass(frozen=True)
class MotionConfig:
    """Rigid 2-D motion of a layer's content (in the layer's own texture coordinates)."""

    translate_per_s: tuple[float, float] = opt((0.0, 0.0), "translation in fractions of the view width/height per second (x right, y down)", lo=-100.0, hi=100.0)
    rotate_deg_per_s: float = opt(0.0, "rotation about the view centre, degrees per second counter-clockwise", lo=-36000.0, hi=36000.0)
    zoom_per_s: float = opt(0.0, "log zoom rate (1/s): scale = exp(zoom_per_s * t)", lo=-10.0, hi=10.0)
    shake_per_s: float = opt(0.0, "hand-held shake: rms speed (view widths per second) of a random-walk translation added to the motion", lo=0.0, hi=100.0, omit_if_default=True)
    shake_seed: int = opt(0, "seed of the shake's random walk (one camera: the same seed and rms on both layers)", lo=0, hi=2**31 - 1, omit_if_default=True)


@dataclasses.dataclass(frozen=True)
class SpriteConfig:
    """A small moving object composited over a layer."""

    source: str = opt("procedural:disk", "content source (see LayerConfig.source)")
    size: float = opt(0.2, "sprite size as a fraction of the view height", lo=0.001, hi=2.0)
    start: tuple[float, float] = opt((0.5, 0.5), "centre at t = 0 in view fractions (x right, y down)", lo=-10.0, hi=10.0)
    velocity_per_s: tuple[float, float] = opt((0.2, 0.0), "velocity in view fractions per second", lo=-100.0, hi=100.0)
    brightness: float = opt(1.0, "multiplier on the sprite content", lo=0.0, hi=1.0)


@dataclasses.dataclass(frozen=True)
class LayerConfig:
    """One layer (T or R): content on a textured plane, with motion."""

    source: str = opt("skimage:camera", "content: skimage:NAME | procedural:checker|stripes|noise|gradient|disk|rings | folder:PATH | video:PATH | image:PATH")
    distance_m: float = opt(3.0, "T: camera-to-plane distance along the axis; R: pane-to-plane distance along the reflected axis (m)", lo=0.01, hi=1e5)
    brightness: float = opt(1.0, "radiance of content value 1.0 (linear; 1.0 = brightest)", lo=0.0, hi=1.0)
    offset: float = opt(0.0, "radiance added everywhere (linear)", lo=0.0, hi=1.0)
    margin: float = opt(0.15, "extra texture beyond the view on each side, as a fraction of the view", lo=0.0, hi=2.0)
    texture_scale: float = opt(1.0, "texture resolution relative to the camera resolution", lo=0.1, hi=8.0)
    gamma: float = opt(2.2, "decode 8-bit content to linear radiance with this gamma (1 = already linear)", lo=0.1, hi=5.0)
    seed: int = opt(0, "seed for procedural content", lo=0, hi=2**31 - 1)
    content_fps: float = opt(30.0, "frame rate of folder:/video: content (frames per second of scene time)", lo=0.001, hi=100000.0)
    motion: MotionConfig = opt(doc="content motion", factory=MotionConfig)
    sprites: tuple[SpriteConfig, ...] = opt((), "moving sprites composited over the content")


@dataclasses.dataclass(frozen=True)
class LayersConfig:
    """The two layers."""

    transmission: LayerConfig = opt(doc="the scene behind the pane (T)", factory=LayerConfig)
    reflection: LayerConfig = opt(doc="the scene on the camera side reflected by the pane (R)", factory=lambda: LayerConfig(source="skimage:astronaut", distance_m=2.0))


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """Timing and sampling defaults of ``polspike render`` (CLI options override)."""

    duration_s: float = opt(0.1, "length of the rendered clip (s)", lo=0.0, hi=3600.0, lo_open=True)
    fps: float = opt(100.0, "keyframes per second written by the render (Stokes are interpolated between them)", lo=0.01, hi=20000.0)
    spp: int = opt(16, "samples per pixel (maps: sub-pixel rays; full: path samples)", lo=1, hi=1 << 16)
    spectral: bool = opt(False, "integrate over wavelength with the sensor response (needed only for dispersive glass)")
    seed: int = opt(0, "render seed", lo=0, hi=2**31 - 1)
    supersample: int = opt(
        0, "analytic tier: 0 = the pixel centre's point sample; K >= 1 = the pixel's area, K x K stratified rays each the box mean of the full tier's texels over its cell",
        lo=0, hi=64, omit_if_default=True,
    )


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """A whole scene (one ``scenes/*.toml`` file)."""

    name: str = opt("scene", "short scene name")
    description: str = opt("", "what this scene is for")
    camera: CameraConfig = opt(doc="camera", factory=CameraConfig)
    pane: PaneConfig = opt(doc="glass pane", factory=PaneConfig)
    layers: LayersConfig = opt(doc="T and R layers", factory=LayersConfig)
    polarizer: PolarizerConfig = opt(doc="rotating polarizer", factory=PolarizerConfig)
    render: RenderSettings = opt(doc="render defaults", factory=RenderSettings)
    objects: ObjectsConfig | None = opt(
        None, "3-D objects behind and in front of the pane instead of the layer planes (full tier only; see generator.objects3d)", omit_if_default=True
    )

    # ---- derived geometry -------------------------------------------------
    def camera_model(self) -> PinholeCamera:
        c = self.camera
        return PinholeCamera.look_at(c.position, c.look_at, c.up, c.fov_deg, c.width, c.height, c.roll_deg)

    def pane_plane(self) -> Plane:
        """Front surface of the pane; normal faces the camera."""
        cam = self.camera_model()
        center = cam.position + self.pane.distance_m * cam.forward
        if self.pane.normal is not None:
            n = normalize(np.asarray(self.pane.normal, dtype=np.float64))
            if not np.any(n):
                raise ConfigError("pane.normal is the zero vector; give a direction")
        else:
            a = np.deg2rad(self.pane.tilt_axis_deg)
            axis = np.cos(a) * cam.right + np.sin(a) * cam.up
            t = np.deg2rad(self.pane.tilt_deg)
            back = -cam.forward
            # Rodrigues rotation of -forward about the in-image axis by the tilt.
            n = back * np.cos(t) + np.cross(axis, back) * np.sin(t) + axis * np.dot(axis, back) * (1 - np.cos(t))
        if np.dot(n, cam.position - center) < 0:
            n = -n
        return Plane(center, n)

    def pane_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """In-plane unit axes (e_w, e_h) of the pane rectangle (width along camera right, projected)."""
        cam = self.camera_model()
        n = self.pane_plane().normal
        e_w = normalize(cam.right - np.dot(cam.right, n) * n)
        if not np.any(e_w):
            e_w = normalize(np.cross(cam.up, n))
        return e_w, np.cross(n, e_w)


def scene_from_dict(data: dict, where: str = "scene") -> SceneConfig:
    """Validate plain data into a SceneConfig (strict; see :mod:`polinfra.config`)."""
    return from_dict(SceneConfig, data, where=where)


def load_scene(path: str | os.PathLike) -> SceneConfig:
    """Load and validate ``scenes/NAME.toml`` (or a bare default name like ``brewster``)."""
    p = Path(path)
    if not p.exists() and not p.suffix and (SCENES_DIR / f"{p.name}.toml").is_file():
        p = SCENES_DIR / f"{p.name}.toml"
    if not p.is_file():
        raise ConfigError(f"scene file not found: {path}; give a .toml path or one of {default_scenes()}")
    return scene_from_dict(load_toml(p), where=str(p))


def scene_hash(scene: SceneConfig) -> str:
    """Stable content hash (sha256 hex, 16 chars) of the resolved scene."""
    blob = json.dumps(to_dict(scene), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def default_scenes() -> list[str]:
    """Names of the shipped scenes."""
    return sorted(p.stem for p in SCENES_DIR.glob("*.toml"))


def check_scene_geometry(scene: SceneConfig) -> None:
    """Raise SceneError when the pane does not cover the view or faces away."""
    from polphysics.geometry import incidence_geometry

    cam = scene.camera_model()
    plane = scene.pane_plane()
    geo = incidence_geometry(cam, plane)
    t = geo["t"]
    if not np.all(np.isfinite(t) & (t > 0)):
        raise SceneError("the pane is edge-on or behind the camera for part of the view; reduce pane.tilt_deg or the field of view")
    e_w, e_h = scene.pane_axes()
    rel = geo["hit"] - plane.point
    half_w, half_h = 0.5 * scene.pane.size_m[0], 0.5 * scene.pane.size_m[1]
    need_w = float(np.max(np.abs(rel @ e_w)))
    need_h = float(np.max(np.abs(rel @ e_h)))
    if need_w > half_w or need_h > half_h:
        raise SceneError(
            f"the pane ({scene.pane.size_m[0]:.3g} x {scene.pane.size_m[1]:.3g} m) does not cover the view; "
            f"set pane.size_m to at least [{2 * need_w:.3g}, {2 * need_h:.3g}] or reduce camera.fov_deg"
        )
