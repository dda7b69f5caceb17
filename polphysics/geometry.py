"""Per-pixel pane geometry: pinhole camera, pane plane, theta(p), phi_perp(p), mirrored camera.

World frame: right-handed, metres.  A pinhole camera at ``position`` looks along
``forward``; ``right`` = normalize(forward x up), true ``up`` = right x forward.
Pixel (x, y) (x right, y down, centres at +0.5) has direction

    d = forward + u_x tan(fov_x/2) right - v_y tan(fov_x/2) (H/W) up,
    u_x = 2 (x + 0.5)/W - 1,  v_y = 2 (y + 0.5)/H - 1.

Per-ray Stokes reference frame (Mitsuba's ``stokes`` integrator):
x_ref = normalize(d x up), y_ref = x_ref x d: on the optical axis these are
image +x and image up.  phi_perp(p) is the angle, in that frame, of the
s-direction e_s = normalize(d x n) of the ray's plane of incidence on the pane,
wrapped to [0, pi).  At normal incidence e_s is undefined; phi_perp = 0 there
(harmless: R_perp = R_par).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polinfra.errors import SceneError

__all__ = [
    "PinholeCamera",
    "Plane",
    "normalize",
    "reflect_dir",
    "mirror_point",
    "incidence_geometry",
    "intersect_plane",
    "refract_dir",
]


def normalize(v, axis: int = -1):
    """Unit vectors along ``axis`` (zero vectors stay zero)."""
    v = np.asarray(v, dtype=np.float64)
    nrm = np.linalg.norm(v, axis=axis, keepdims=True)
    return np.divide(v, nrm, out=np.zeros_like(v), where=nrm > 0)


def reflect_dir(d, n):
    """Mirror direction(s) d about a plane with unit normal n: d - 2 (d.n) n."""
    d = np.asarray(d, dtype=np.float64)
    return d - 2.0 * np.sum(d * n, axis=-1, keepdims=True) * n


def mirror_point(p, plane_point, n):
    """Mirror point(s) p across the plane (plane_point, unit normal n)."""
    p = np.asarray(p, dtype=np.float64)
    return p - 2.0 * np.sum((p - plane_point) * n, axis=-1, keepdims=True) * n


def refract_dir(d, n_unit, eta):
    """Refracted unit direction for incident unit d entering a medium of relative index eta.

    ``n_unit`` faces the incident side (d . n < 0).  Total internal reflection
    returns the reflected direction (the whole energy goes there).
    """
    cos_i = -np.sum(d * n_unit, axis=-1, keepdims=True)
    k = 1.0 - (1.0 - cos_i**2) / eta**2
    t = d / eta + (cos_i / eta - np.sqrt(np.maximum(k, 0.0))) * n_unit
    return np.where(k >= 0, normalize(t), reflect_dir(d, n_unit))


@dataclasses.dataclass(frozen=True)
class Plane:
    """An oriented plane: a point and a unit normal (world frame)."""

    point: np.ndarray
    normal: np.ndarray


def intersect_plane(origin, direction, plane: Plane):
    """Ray-plane intersection.

    Args:
        origin: (..., 3) ray origins.
        direction: (..., 3) ray directions.
        plane: the plane.

    Returns:
        (t, points): t (...,) ray parameters (inf where parallel), points (..., 3).
    """
    denom = np.sum(direction * plane.normal, axis=-1)
    num = np.sum((plane.point - origin) * plane.normal, axis=-1)
    ok = np.abs(denom) > 1e-12
    t = np.where(ok, num / np.where(ok, denom, 1.0), np.inf)
    pts = origin + np.where(np.isfinite(t), t, 0.0)[..., None] * direction
    return t, pts


@dataclasses.dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera with square pixels.

    Attributes:
        position: (3,) camera centre, metres.
        forward, right, up: (3,) orthonormal axes (up = right x forward for a
            real camera; a mirrored camera keeps the mirrored right and up, so
            its image is the reflection as the real camera sees it).
        fov_x_rad: horizontal field of view.
        width, height: image size in pixels.
    """

    position: np.ndarray
    forward: np.ndarray
    right: np.ndarray
    up: np.ndarray
    fov_x_rad: float
    width: int
    height: int

    @classmethod
    def look_at(cls, position, look_at, up, fov_x_deg: float, width: int, height: int, roll_deg: float = 0.0) -> "PinholeCamera":
        """Build a camera from a look-at triple (degrees only here, at the edge)."""
        pos = np.asarray(position, dtype=np.float64)
        f = normalize(np.asarray(look_at, dtype=np.float64) - pos)
        if not np.any(f):
            raise SceneError("camera.look_at equals camera.position; give a look_at point away from the camera")
        r = np.cross(f, np.asarray(up, dtype=np.float64))
        if np.linalg.norm(r) < 1e-9:
            raise SceneError("camera.up is parallel to the viewing direction; choose an up vector not along look_at - position")
        r = normalize(r)
        u = np.cross(r, f)
        if roll_deg:
            a = np.deg2rad(roll_deg)  # roll: rotate the image axes counter-clockwise (as seen in the image)
            r, u = np.cos(a) * r + np.sin(a) * u, -np.sin(a) * r + np.cos(a) * u
        return cls(pos, f, r, u, float(np.deg2rad(fov_x_deg)), int(width), int(height))

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.width / np.tan(0.5 * self.fov_x_rad)

    def pixel_grid(self, subpixel: tuple[float, float] = (0.5, 0.5)):
        """Normalised image coordinates (u, v) in [-1, 1], each (H, W); v grows downward."""
        x = (np.arange(self.width) + subpixel[0]) / self.width * 2.0 - 1.0
        y = (np.arange(self.height) + subpixel[1]) / self.height * 2.0 - 1.0
        return np.meshgrid(x, y)

    def ray_directions(self, subpixel: tuple[float, float] = (0.5, 0.5)):
        """Unit ray directions (H, W, 3) through pixel positions (centre by default)."""
        return normalize(self.directions_at(*self.pixel_grid(subpixel)))

    def directions_at(self, u, v):
        """Ray directions (..., 3), not normalised, through normalised image coordinates (u, v) in [-1, 1]
        (v grows downward, as :meth:`pixel_grid`): forward + u tan(fov_x / 2) right - v tan(fov_y / 2) up.
        """
        u, v = np.asarray(u, np.float64), np.asarray(v, np.float64)
        tx = np.tan(0.5 * self.fov_x_rad)
        ty = tx * self.height / self.width
        return self.forward + (u * tx)[..., None] * self.right - (v * ty)[..., None] * self.up

    def stokes_frame(self, d):
        """Per-ray Stokes reference axes (x_ref, y_ref), each (..., 3) (Mitsuba's frame)."""
        x_ref = normalize(np.cross(d, self.up))
        y_ref = np.cross(x_ref, d)
        return x_ref, y_ref

    def project(self, points):
        """Pixel coordinates (x, y) (float, centres at +0.5) of world points (..., 3)."""
        rel = np.asarray(points, dtype=np.float64) - self.position
        z = np.sum(rel * self.forward, axis=-1)
        tx = np.tan(0.5 * self.fov_x_rad)
        ty = tx * self.height / self.width
        u = np.sum(rel * self.right, axis=-1) / (z * tx)
        v = -np.sum(rel * self.up, axis=-1) / (z * ty)
        return (u + 1.0) * 0.5 * self.width, (v + 1.0) * 0.5 * self.height

    def mirrored(self, plane: Plane) -> "PinholeCamera":
        """The virtual camera that sees the reflection layer directly.

        Its rays for pixel p start at the mirrored centre and travel along the
        reflected directions, so they pass through the pane point the real ray
        hits and continue to whatever the pane reflects into p.
        """
        n = plane.normal
        return dataclasses.replace(
            self,
            position=mirror_point(self.position, plane.point, n),
            forward=reflect_dir(self.forward, n),
            right=reflect_dir(self.right, n),
            up=reflect_dir(self.up, n),
        )


def incidence_geometry(camera: PinholeCamera, plane: Plane, subpixel: tuple[float, float] = (0.5, 0.5)):
    """Incidence angle theta(p) and s-direction angle phi_perp(p) for each pixel.

    Args:
        camera: the real camera.
        plane: the pane's front surface; its normal may face either side.
        subpixel: position inside each pixel (0.5, 0.5 = centre).

    Returns:
        dict with ``theta`` (H, W) in [0, pi/2] radians, ``phi_perp`` (H, W) in
        [0, pi) radians, ``t`` (H, W) distance along each ray to the pane
        (inf or negative where the ray misses it), ``d`` (H, W, 3) unit rays,
        ``hit`` (H, W, 3) hit points.
    """
    d = camera.ray_directions(subpixel)
    n = normalize(plane.normal)
    cos_i = np.clip(np.abs(np.sum(d * n, axis=-1)), 0.0, 1.0)
    theta = np.arccos(cos_i)
    e_s = np.cross(d, n)
    s_norm = np.linalg.norm(e_s, axis=-1)
    x_ref, y_ref = camera.stokes_frame(d)
    ang = np.arctan2(np.sum(e_s * y_ref, axis=-1), np.sum(e_s * x_ref, axis=-1))
    phi_perp = np.where(s_norm > 1e-12, np.mod(ang, np.pi), 0.0)
    phi_perp = np.where(phi_perp >= np.pi, 0.0, phi_perp)  # float rounding at the wrap
    t, hit = intersect_plane(camera.position, d, Plane(plane.point, n))
    return {"theta": theta, "phi_perp": phi_perp, "t": t, "d": d, "hit": hit}
