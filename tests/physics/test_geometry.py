"""Pinhole camera, pane plane, theta(p), phi_perp(p) and the mirrored camera."""

from __future__ import annotations

import numpy as np
import pytest

from polphysics.geometry import PinholeCamera, Plane, incidence_geometry, intersect_plane, normalize, reflect_dir


def _pane(tilt_deg: float, axis=(0.0, 1.0, 0.0), dist=1.0) -> Plane:
    t = np.deg2rad(tilt_deg)
    axis = np.asarray(axis, float)
    back = np.array([0.0, 0.0, 1.0])
    n = back * np.cos(t) + np.cross(axis, back) * np.sin(t) + axis * axis.dot(back) * (1 - np.cos(t))
    return Plane(np.array([0.0, 0.0, -dist]), n)


def _cam(roll=0.0, w=41, h=25):
    return PinholeCamera.look_at([0, 0, 0], [0, 0, -1], [0, 1, 0], 50.0, w, h, roll)


def test_camera_axes_right_handed():
    cam = _cam()
    np.testing.assert_allclose(cam.right, [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(cam.up, [0, 1, 0], atol=1e-15)
    x_ref, y_ref = cam.stokes_frame(cam.forward)
    np.testing.assert_allclose(x_ref, cam.right, atol=1e-15)
    np.testing.assert_allclose(y_ref, cam.up, atol=1e-15)


@pytest.mark.parametrize("tilt", [0.0, 10.0, 56.31, 80.0])
def test_theta_at_principal_point_equals_tilt(tilt):
    cam = _cam()
    g = incidence_geometry(cam, _pane(tilt))
    assert np.rad2deg(g["theta"][12, 20]) == pytest.approx(tilt, abs=1e-9)


def test_phi_perp_for_vertical_and_horizontal_tilt_axes():
    """Tilt about the vertical axis: plane of incidence horizontal, s vertical (90 deg); about x: s horizontal (0)."""
    cam = _cam()
    g_v = incidence_geometry(cam, _pane(30.0, axis=(0, 1, 0)))
    g_h = incidence_geometry(cam, _pane(30.0, axis=(1, 0, 0)))
    assert np.rad2deg(g_v["phi_perp"][12, 20]) == pytest.approx(90.0, abs=1e-9)
    c = g_h["phi_perp"][12, 20]
    assert min(c, np.pi - c) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("roll", [15.0, -40.0, 90.0])
def test_phi_perp_rotates_with_camera_roll(roll):
    """Rolling the camera by +a (counter-clockwise) turns every image angle by -a."""
    plane = _pane(35.0, axis=normalize(np.array([1.0, 2.0, 0.0])))
    p0 = incidence_geometry(_cam(0.0), plane)["phi_perp"][12, 20]
    p1 = incidence_geometry(_cam(roll), plane)["phi_perp"][12, 20]
    diff = np.mod(p0 - p1 - np.deg2rad(roll) + np.pi / 2, np.pi) - np.pi / 2
    assert diff == pytest.approx(0.0, abs=1e-9)


def test_normal_incidence_has_finite_phi_perp():
    g = incidence_geometry(_cam(), _pane(0.0))
    assert np.all(np.isfinite(g["phi_perp"])) and np.all(np.isfinite(g["theta"]))
    assert g["theta"][12, 20] == pytest.approx(0.0, abs=1e-12)


def test_mirrored_camera_reproduces_reflection():
    """A world point Q on the camera side, projected by the mirrored camera to pixel p: the real ray
    through p, reflected at the pane, passes through Q.
    """
    cam = PinholeCamera.look_at([0, 0, 0], [0, 0, -1], [0, 1, 0], 60.0, 200, 120)
    plane = _pane(40.0, axis=normalize(np.array([0.3, 1.0, 0.0])))
    vcam = cam.mirrored(plane)
    rng = np.random.default_rng(0)
    # points on the camera side, in front of the mirrored camera
    Q = vcam.position + vcam.forward * 3.0 + (rng.random((20, 3)) - 0.5) * 0.8
    px, py = vcam.project(Q)
    for (x, y, q) in zip(px, py, Q):
        u = x / cam.width * 2 - 1
        v = y / cam.height * 2 - 1
        tx = np.tan(cam.fov_x_rad / 2)
        d = normalize(cam.forward + u * tx * cam.right - v * tx * cam.height / cam.width * cam.up)
        _, hit = intersect_plane(cam.position, d, plane)
        dr = reflect_dir(d, plane.normal)
        w = q - hit
        dist = np.linalg.norm(w - w.dot(dr) * dr)
        assert dist < 1e-9
        assert w.dot(dr) > 0  # Q lies ahead on the reflected ray
