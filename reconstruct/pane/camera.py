"""The camera and pane-normal conventions of the self-calibration: pinhole camera, normal from (tilt, azimuth), phi_perp maps, fov bounds."""

from __future__ import annotations

import logging
import math

import numpy as np

log = logging.getLogger(__name__)


def camera_for(width: int, height: int, fov_deg: float):
    """The reference pinhole (origin, looking along +z, up +y) of ``width`` x ``height`` pixels."""
    from polphysics.geometry import PinholeCamera

    return PinholeCamera.look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], fov_x_deg=float(fov_deg), width=int(width), height=int(height))


def normal_from_angles(tilt_rad: float, azimuth_rad: float, camera) -> np.ndarray:
    """Unit normal at ``tilt`` from the camera's forward axis, its image projection at ``azimuth``
    counter-clockwise from image +x (camera.right) towards image up (camera.up).
    """
    st = math.sin(tilt_rad)
    return st * math.cos(azimuth_rad) * camera.right + st * math.sin(azimuth_rad) * camera.up + math.cos(tilt_rad) * camera.forward


def _angles_of(normal: np.ndarray, camera) -> tuple[float, float]:
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    if float(n @ camera.forward) < 0:
        n = -n
    tilt = math.acos(min(1.0, float(n @ camera.forward)))
    az = math.atan2(float(n @ camera.up), float(n @ camera.right)) % (2 * math.pi)
    return tilt, az


def _phi_perp_many(camera, normals: np.ndarray, batch: int = 128):
    """phi_perp grids for many normals (K, 3): incidence_geometry broadcast over a (k, 1, 1, 3) normal, in batches."""
    from polphysics.geometry import Plane, incidence_geometry

    for i in range(0, normals.shape[0], batch):
        yield incidence_geometry(camera, Plane(camera.position + camera.forward, normals[i : i + batch, None, None, :]))["phi_perp"]


def _phi_perp_grid(camera, normal: np.ndarray) -> np.ndarray:
    from polphysics.geometry import Plane, incidence_geometry

    return incidence_geometry(camera, Plane(camera.position + camera.forward, normal))["phi_perp"]


def _pane_phi_perp(width: int, height: int, tilt: float, az: float, fov_deg: float) -> np.ndarray:
    """phi_perp (height, width) of the pane with normal (tilt, az) on a width x height grid seen with horizontal fov fov_deg."""
    cam = camera_for(width, height, fov_deg)
    return _phi_perp_grid(cam, normal_from_angles(tilt, az, cam))


FOV_BOUNDS_DEG = (5.0, 150.0)
"""Search bounds (degrees) of a fitted field of view: :func:`fit_normal`, :func:`polish_geometry` and
:func:`valley_candidates`, which leaves out candidates that ran into them."""


FOV_INNER_DEG = (FOV_BOUNDS_DEG[0] + 0.5, FOV_BOUNDS_DEG[1] - 1.0)
"""A fitted fov strictly inside this range is off the search bounds (:data:`FOV_BOUNDS_DEG`); one outside it ran
into them: a degenerate view, not a fitted value."""

CHI2_1_MEDIAN = 0.4549364
"""The median of the chi-square distribution with one degree of freedom: a median of squared unit-variance
residuals over it estimates their variance."""
