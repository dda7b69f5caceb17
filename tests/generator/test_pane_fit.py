"""The differentiable maps tier (generator.pane_fit): values and gradients against independent oracles.

* values vs polphysics (numpy Fresnel + pinhole geometry) and vs the scene-intersection two-lobe
  tracer of the maps tier (generator.mitsuba_integrator.pane_coefficients);
* Dr.Jit forward-mode gradients vs central finite differences of the same kernel;
* Dr.Jit gradients vs torch autograd through the numpy-equivalent formulas (written here in torch,
  their values first checked against polphysics).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _mitsuba_common import require_mitsuba

from polphysics.fresnel import pane_coefficients
from polphysics.geometry import PinholeCamera, Plane, incidence_geometry


@pytest.fixture(autouse=True)
def _mitsuba_works():
    """The one skip policy (_mitsuba_common.require_mitsuba): skip only when mitsuba is not installed; under CI
    an installed Mitsuba whose import or backend fails is a failure, not a skip.
    """
    require_mitsuba()

W, H = 24, 16
X = np.array([math.radians(52.0), math.radians(35.0), math.radians(58.0), 1.53])
FIELDS = ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")


def _cam(fov_deg=math.degrees(X[2])):
    return PinholeCamera.look_at([0, 0, 0], [0, 0, 1], [0, 1, 0], fov_x_deg=fov_deg, width=W, height=H)


def _normal(x, cam):
    t, a = x[0], x[1]
    return math.sin(t) * math.cos(a) * cam.right + math.sin(t) * math.sin(a) * cam.up + math.cos(t) * cam.forward


def _dphi(a, b):
    return np.abs(np.mod(a - b + np.pi / 2, np.pi) - np.pi / 2)


@pytest.fixture(scope="module")
def ad():
    from generator.pane_fit import PaneModelAD

    return {m: PaneModelAD(W, H, m) for m in ("single", "thin_slab")}


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_values_match_polphysics(ad, model):
    m = ad[model].maps(X)
    cam = _cam()
    geo = incidence_geometry(cam, Plane(cam.position + cam.forward, _normal(X, cam)))
    co = pane_coefficients(geo["theta"], X[3], model=model)
    assert np.max(np.abs(m["theta"] - geo["theta"])) < 1e-5
    assert np.max(_dphi(m["phi_perp"], geo["phi_perp"])) < 1e-5
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        assert np.max(np.abs(m[k] - co[k])) < 2e-6, k


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_values_match_the_scene_intersection_tracer(model):
    """Same maps as the maps tier's tracer (Mitsuba scene, rectangle interfaces, dielectric BSDF, both lobes)."""
    import mitsuba as mi

    from generator.mitsuba_integrator import pane_coefficients as traced
    from generator.mitsuba_scene import CameraSpec, PaneSpec, build_scene_dict
    from generator.pane_fit import PaneModelAD

    x = X.copy()
    cam = _cam()
    N = _normal(x, cam)
    m_ad = PaneModelAD(W, H, model, sub=2, thickness_m=0.004).maps(x)
    camspec = CameraSpec(W, H, float(x[2]), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0))
    pane = PaneSpec(model, float(x[3]), (0.0, 0.0, 1.0), tuple(-N), (50.0, 50.0), 0.004 if model != "single" else 0.0)
    scene = mi.load_dict(build_scene_dict(mi, camspec, pane, []))
    m_tr = traced(mi, scene, -N, (0.0, 1.0, 0.0), W, H, model=model, n=float(x[3]), sub=2)
    assert np.max(np.abs(m_ad["theta"] - m_tr["theta"])) < 2e-4
    assert np.max(_dphi(m_ad["phi_perp"], m_tr["phi_perp"])) < 2e-4
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        assert np.max(np.abs(m_ad[k] - m_tr[k])) < 2e-4, k


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_gradients_match_finite_differences(ad, model):
    pm = ad[model]
    m, J = pm.maps_and_jacobian(X)
    steps = (2e-3, 2e-3, 2e-3, 2e-3)
    for i, h in enumerate(steps):
        xp, xm = X.copy(), X.copy()
        xp[i] += h
        xm[i] -= h
        mp, mm = pm.maps(xp), pm.maps(xm)
        for k in FIELDS:
            diff = mp[k] - mm[k]
            if k == "phi_perp":
                diff = np.mod(diff + np.pi / 2, np.pi) - np.pi / 2
            fd = diff / (2 * h)
            scale = max(1e-3, float(np.max(np.abs(fd))))
            err = float(np.max(np.abs(fd - J[k][i])))
            # float32 kernel: FD noise ~ 1e-7 / h; curvature error ~ h^2
            assert err <= 2e-3 * scale + 3e-4, (model, i, k, err, scale)


def _torch_maps(x, model):
    """The numpy formulas of polphysics (pinhole rays, plane normal, Fresnel power, incoherent slab) in torch."""
    tilt, az, fov, n = x
    u = (torch.arange(W, dtype=torch.float64) + 0.5) / W * 2 - 1
    v = (torch.arange(H, dtype=torch.float64) + 0.5) / H * 2 - 1
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    tx = torch.tan(0.5 * fov)
    ty = tx * H / W
    right = torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    fwd = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    d = fwd + (uu * tx)[..., None] * right - (vv * ty)[..., None] * up
    d = d / d.norm(dim=-1, keepdim=True)
    N = torch.sin(tilt) * torch.cos(az) * right + torch.sin(tilt) * torch.sin(az) * up + torch.cos(tilt) * fwd
    ci = (d * N).sum(-1).abs()
    theta = torch.acos(ci)
    es = torch.cross(d, N.expand_as(d), dim=-1)
    xr = torch.cross(d, up.expand_as(d), dim=-1)
    xr = xr / xr.norm(dim=-1, keepdim=True)
    yr = torch.cross(xr, d, dim=-1)
    phi = torch.atan2((es * yr).sum(-1), (es * xr).sum(-1))
    st = torch.sin(theta) / n
    ct = torch.sqrt(1 - st * st)
    rs = (ci - n * ct) / (ci + n * ct)
    rp = (n * ci - ct) / (n * ci + ct)
    Rs, Rp = rs * rs, rp * rp
    if model != "single":
        Rs, Rp = 2 * Rs / (1 + Rs), 2 * Rp / (1 + Rp)
    return {"theta": theta, "phi_perp": phi, "R_perp": Rs, "R_par": Rp, "T_perp": 1 - Rs, "T_par": 1 - Rp}


@pytest.mark.parametrize("model", ["single", "thin_slab"])
def test_gradients_match_torch_autograd_of_the_analytic_formulas(ad, model):
    xt = torch.tensor(X, dtype=torch.float64, requires_grad=True)
    tm = _torch_maps(xt, model)
    # the torch transcription is the analytic model: its values equal polphysics'
    cam = _cam()
    geo = incidence_geometry(cam, Plane(cam.position + cam.forward, _normal(X, cam)))
    co = pane_coefficients(geo["theta"], X[3], model=model)
    assert np.max(np.abs(tm["theta"].detach().numpy() - geo["theta"])) < 1e-12
    assert np.max(_dphi(tm["phi_perp"].detach().numpy(), geo["phi_perp"])) < 1e-12
    assert np.max(np.abs(tm["R_perp"].detach().numpy() - co["R_perp"])) < 1e-12
    _, J = ad[model].maps_and_jacobian(X)
    for k in FIELDS:
        # d(sum_p w_p f_p)/dx for random weights w: the full Jacobian contracted, one backward pass per field
        w = torch.from_numpy(np.random.default_rng(7).normal(size=(H, W)))
        (g,) = torch.autograd.grad((tm[k] * w).sum(), xt, retain_graph=True)
        mine = np.einsum("ihw,hw->i", J[k], w.numpy())
        scale = float(np.abs(J[k]).sum(axis=(1, 2)).max())
        assert np.allclose(mine, g.numpy(), atol=2e-5 * scale + 1e-6), (model, k, mine, g.numpy())
        # and pixel by pixel for the index and tilt derivatives
    for i in (0, 3):
        for k in ("R_perp", "R_par", "theta"):
            gi = torch.autograd.grad(tm[k][H // 2, W // 3], xt, retain_graph=True)[0][i].item()
            assert abs(J[k][i][H // 2, W // 3] - gi) <= 1e-4 * max(1.0, abs(gi)), (model, i, k)


def test_gauss_newton_recovers_a_known_optimum_and_its_covariance():
    """Linear least squares with known noise: GN's x and covariance equal the closed form."""
    from reconstruct.pane.levenberg import gauss_newton

    rng = np.random.default_rng(3)
    A = rng.normal(size=(200, 3))
    x_true = np.array([0.3, -1.0, 2.0])
    y = A @ x_true + rng.normal(size=200)
    res = gauss_newton(lambda x: (A @ x - y, A), np.zeros(3), [-10] * 3, [10] * 3)
    x_ls = np.linalg.lstsq(A, y, rcond=None)[0]
    assert np.allclose(res.x, x_ls, atol=1e-6)
    assert np.allclose(res.cov, np.linalg.inv(A.T @ A) * max(1.0, res.chi2 / res.dof), rtol=1e-6)
    assert res.converged
