"""Configuration of a scene's 3-D objects (``[objects]`` of a scene TOML): shapes, materials, lights.

The schema only; :mod:`generator.objects3d` builds the Mitsuba scene from it and measures the
departure from paper Eq. (1)-(2).  Kept apart so the scene schema (:mod:`generator.scene`) can
hold it without importing the renderer.
"""

from __future__ import annotations

import dataclasses

from polinfra.config import opt
from polinfra.errors import ConfigError

__all__ = ["ShapeConfig", "LightConfig", "ObjectsConfig", "SHAPES", "MATERIALS", "METALS", "require_full_tier"]

Vec3 = tuple[float, float, float]

SHAPES = ("sphere", "cube", "rectangle")
MATERIALS = ("diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric")
METALS = (
    "a-C", "Ag", "Al", "AlAs", "AlSb", "Au", "Be", "Cr", "CsI", "Cu", "Cu2O", "CuO", "d-C", "Hg", "HgTe", "Ir", "K", "Li",
    "MgO", "Mo", "Na_palik", "Nb", "Ni_palik", "Rh", "Se", "SiC", "SnTe", "Ta", "Te", "ThF4", "TiC", "TiN", "TiO2", "VC",
    "V_palik", "VN", "W", "none",
)
"""Metal names of Mitsuba's conductor BSDFs (measured complex indices; "none" = an ideal mirror)."""


@dataclasses.dataclass(frozen=True)
class ShapeConfig:
    """One 3-D object (world frame, metres)."""

    type: str = opt("sphere", "sphere | cube | rectangle", choices=SHAPES)
    center: Vec3 = opt((0.0, 0.0, -3.0), "centre (m)")
    radius: float = opt(0.3, "sphere radius (m)", lo=1e-4, hi=1e4)
    size: Vec3 = opt((0.5, 0.5, 0.5), "cube edge lengths x, y, z; rectangle width x, height y (z unused) (m)", lo=1e-4, hi=1e4)
    rotate_deg: Vec3 = opt((0.0, 0.0, 0.0), "rotation about world x, then y, then z (degrees); a rectangle's front is its local +z", lo=-360.0, hi=360.0)
    material: str = opt("diffuse", "diffuse | plastic | roughplastic | conductor | roughconductor | dielectric", choices=MATERIALS)
    reflectance: float = opt(0.5, "diffuse albedo (diffuse; base of plastic)", lo=0.0, hi=1.0)
    ior: float = opt(1.5, "refractive index (dielectric; plastic coat)", lo=1.0, hi=4.0, lo_open=True)
    metal: str = opt("Al", "conductor: Mitsuba material name (Al, Ag, Au, Cu, Cr, ...; none = ideal mirror)", choices=METALS)
    alpha: float = opt(0.1, "roughness of the rough materials (GGX alpha)", lo=0.001, hi=1.0)
    velocity_m_per_s: Vec3 = opt((0.0, 0.0, 0.0), "constant velocity of the centre (m/s); the object must stay on its side of the pane", lo=-100.0, hi=100.0)
    spin_deg_per_s: Vec3 = opt((0.0, 0.0, 0.0), "rotation rate about world x, y, z added to rotate_deg (degrees/s)", lo=-3600.0, hi=3600.0)

    @property
    def moving(self) -> bool:
        return any(v != 0.0 for v in self.velocity_m_per_s) or any(v != 0.0 for v in self.spin_deg_per_s)

    def at(self, t_s: float) -> "ShapeConfig":
        """This shape at scene time ``t_s`` (s): centre moved, rotation advanced."""
        if not self.moving:
            return self
        c = tuple(float(a + v * t_s) for a, v in zip(self.center, self.velocity_m_per_s))
        r = tuple(float(a + w * t_s) for a, w in zip(self.rotate_deg, self.spin_deg_per_s))
        return dataclasses.replace(self, center=c, rotate_deg=r)


@dataclasses.dataclass(frozen=True)
class LightConfig:
    """A one-sided rectangular area light."""

    center: Vec3 = opt((0.0, 2.0, -3.0), "centre (m)")
    size: tuple[float, float] = opt((1.0, 1.0), "width, height (m)", lo=1e-4, hi=1e4)
    target: Vec3 = opt((0.0, 0.0, -3.0), "a point the light faces (m)")
    radiance: float = opt(5.0, "emitted radiance (linear)", lo=0.0, hi=1e6)


@dataclasses.dataclass(frozen=True)
class ObjectsConfig:
    """3-D content on both sides of the pane (replaces the layer planes; full tier only)."""

    shapes: tuple[ShapeConfig, ...] = opt((), "objects; each lies wholly behind the pane (T) or in front of it (R)")
    lights: tuple[LightConfig, ...] = opt((), "area lights; each lies wholly on one side of the pane")
    environment: float = opt(0.0, "radiance of a constant environment around everything (0 = none)", lo=0.0, hi=1e6)
    max_depth: int = opt(24, "path depth of the renders", lo=2, hi=256)

    def __post_init__(self) -> None:
        if not self.shapes:
            raise ConfigError("objects.shapes is empty; add at least one [[objects.shapes]] (or remove [objects] for a layer scene)")
        if not self.lights and self.environment <= 0:
            raise ConfigError("objects: no [[objects.lights]] and environment = 0: the scene would be black; add a light or an environment")

    @property
    def is_static(self) -> bool:
        return not any(s.moving for s in self.shapes)

    def at(self, t_s: float) -> "ObjectsConfig":
        """The objects at scene time ``t_s`` (lights and environment do not move)."""
        if self.is_static:
            return self
        return dataclasses.replace(self, shapes=tuple(s.at(t_s) for s in self.shapes))


def require_full_tier(scene, tier: str) -> None:
    """ConfigError unless ``tier`` can render ``scene`` (object scenes: full only)."""
    if getattr(scene, "objects", None) is not None and tier != "full":
        raise ConfigError(f"scene {scene.name!r} holds 3-D objects: only --tier full renders it (got {tier!r})")


# ---------------------------------------------------------------------------- geometry
