"""Differentiable maps tier of a planar pane, and a Gauss-Newton fit of its parameters.

The maps tier (:mod:`generator.mitsuba_integrator`) follows both lobes (reflected and
transmitted) at every glass interface with Mitsuba's Fresnel Mueller matrices and sums the
slab's interreflections.  For a planar pane seen by a pinhole camera the per-pixel response
depends only on the viewing ray d(p) and the pane normal N (not on where the pane is), so this
module evaluates the same physics as one Dr.Jit kernel whose inputs are Dr.Jit *differentiable*
variables (``*_ad_*`` variant: llvm here, cuda where present):

    x = (tilt, azimuth, fov, n)

* camera: the reference pinhole of :func:`reconstruct.pane.camera.camera_for` (origin, forward +z,
  up +y, so image right = -x), pixel rays through sub-pixel centres, horizontal field of view ``fov``;
* N = sin(tilt) (cos(az) right + sin(az) up) + cos(tilt) forward;
* theta = angle(d, N); the s-direction d x N expressed in the ray's Stokes frame
  (x_ref = d x up normalised, y_ref = x_ref x d: Mitsuba's ``stokes`` frame) gives phi_perp;
* Fresnel amplitudes from ``mi.fresnel_polarized(cos theta, n)`` (Mitsuba's own, differentiable
  in both arguments; the scene ``dielectric`` BSDF takes its index as a non-differentiable scalar,
  which is why the fit does not go through ``scene.ray_intersect``);
* ``single``: R = R1, T = 1 - R1 (the maps tier undoes Mitsuba's 1/n^2 radiance scaling);
  slabs: the two-lobe branch sum R = R1 + sum_k (1-R1)^2 R1^(2k-1) a^(2k),
  T = sum_k (1-R1)^2 R1^(2k) a^(2k+1), per polarization, to branch weight < 1e-7
  (a = exp(-alpha thickness / cos theta_t): absorption along the internal segment);
* per pixel, unit unpolarized R and T layers give the camera-frame Stokes vectors
  S_R = ((R_perp + R_par)/2, (R_perp - R_par)/2 cos 2phi_perp, ... sin 2phi_perp), S_T likewise,
  averaged over the sub-pixel rays and inverted for the maps exactly as the maps tier does.

``tests/generator/test_pane_fit.py`` pins the kernel to the scene-intersection tracer
(:func:`generator.mitsuba_integrator.pane_coefficients`) and its gradients to finite differences
and to torch autograd through the numpy formulas of :mod:`polphysics`.

:func:`gauss_newton` is a small bounded Levenberg-Marquardt solver on residuals whose Jacobian
comes from Dr.Jit forward-mode AD (one pass per parameter); its Gauss-Newton Hessian J^T J gives
the parameter covariance.
"""

from __future__ import annotations

import math

import numpy as np

from polinfra.errors import BackendUnavailableError, ConfigError

__all__ = ["PARAM_NAMES", "PaneModelAD", "ad_variant", "slab_terms"]

PARAM_NAMES = ("tilt", "azimuth", "fov", "n")
"""Order of the parameter vector x: tilt, azimuth, fov (radians), n."""

FIELDS = ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")

MIN_WEIGHT = 1e-7
"""Slab interreflection branches are summed until their weight falls below this (as the maps tier)."""


def ad_variant() -> str:
    """Set and return a JIT *differentiable* mono polarized Mitsuba variant (cuda where it works, else llvm)."""
    import mitsuba as mi

    from generator.mitsuba_backend import resolve_backend

    cur = mi.variant()
    if cur is not None and "_ad_" in cur and "mono_polarized" in cur:
        return cur
    be = resolve_backend("auto", spectral=False)
    if not be.vectorized or "_ad_" not in be.variant:
        raise BackendUnavailableError(f"the differentiable pane model needs an llvm_ad_* or cuda_ad_* mono polarized variant; {be.variant} was selected (install libllvm19)")
    return be.variant


def slab_terms(R1_max: float, a_max: float = 1.0) -> int:
    """Number of interreflection branches k until R1^(2k) a^(2k) < MIN_WEIGHT."""
    q = min(0.999999, float(R1_max) * float(a_max))
    if q <= 0:
        return 1
    return int(min(2000, max(1, math.ceil(math.log(MIN_WEIGHT) / (2.0 * math.log(q))))))


class PaneModelAD:
    """Per-pixel pane response of a ``width`` x ``height`` pinhole view as a differentiable function of x.

    Args:
        width, height: image (or block-grid) size; rays through pixel centres (``sub`` = 1) or a
            ``sub`` x ``sub`` grid per pixel (maps averaged in Stokes form, as the maps tier).
        model: ``single``, ``thin_slab`` or ``thick_slab`` (coefficient maps of thin and thick are equal;
            the thick slab's ghost displacement is not part of the maps).
        block: > 0: one ray per ``block`` x ``block`` pixel block (through the block's centre), maps on the
            (height // block, width // block) grid of :func:`reconstruct.pane.orientation.orientation_field`'s blocks.
        thickness_m, absorption_per_m: slab absorption along the internal path.
    """

    def __init__(self, width: int, height: int, model: str = "single", *, sub: int = 1, block: int = 0, thickness_m: float = 0.0, absorption_per_m: float = 0.0):
        if model not in ("single", "thin_slab", "thick_slab"):
            raise ConfigError(f"unknown pane model {model!r}; use single, thin_slab or thick_slab")
        self.W, self.H, self.K = int(width), int(height), int(sub)
        self.block = int(block)
        if self.block > 0:
            self.K = 1
            self.gw, self.gh = self.W // self.block, self.H // self.block
        else:
            self.gw, self.gh = self.W, self.H
        self.model = model
        self.thickness_m = float(thickness_m)
        self.absorption_per_m = float(absorption_per_m)
        self.variant = ad_variant()
        n = self.gw * self.gh * self.K * self.K
        idx = np.arange(n)
        pix, sb = np.divmod(idx, self.K * self.K)
        py, px = np.divmod(pix, self.gw)
        sy, sx = np.divmod(sb, self.K)
        if self.block > 0:  # block centres in image pixel coordinates
            xp, yp = px * self.block + 0.5 * self.block, py * self.block + 0.5 * self.block
        else:
            xp, yp = px + (sx + 0.5) / self.K, py + (sy + 0.5) / self.K
        self._u = (xp / self.W * 2.0 - 1.0).astype(np.float32)
        self._v = (yp / self.H * 2.0 - 1.0).astype(np.float32)

    # ------------------------------------------------------------------ kernel
    def _eval(self, x, grad_index: int | None = None):
        """Evaluate the ray-level outputs; with ``grad_index`` also their forward derivative along x[grad_index]."""
        import drjit as dr
        import mitsuba as mi

        mi.set_variant(self.variant)
        Float = mi.Float
        p = [dr.opaque(Float, float(v)) for v in x]  # opaque: one compiled kernel for every parameter value
        if grad_index is not None:
            dr.enable_grad(p[grad_index])
        tilt, az, fov, n = p
        u, v = Float(self._u), Float(self._v)
        tx = dr.tan(0.5 * fov)
        ty = tx * (self.H / self.W)
        # camera frame: forward +z, up +y, right = forward x up = -x
        right, up, fwd = mi.Vector3f(-1.0, 0.0, 0.0), mi.Vector3f(0.0, 1.0, 0.0), mi.Vector3f(0.0, 0.0, 1.0)
        d = dr.normalize(fwd + (u * tx) * right - (v * ty) * up)
        st = dr.sin(tilt)
        N = st * dr.cos(az) * right + st * dr.sin(az) * up + dr.cos(tilt) * fwd
        cos_i = dr.clip(dr.abs(dr.dot(d, N)), 1e-6, 1.0 - 1e-7)
        theta = dr.acos(cos_i)
        e_s = dr.cross(d, N)
        x_ref = dr.normalize(dr.cross(d, up))
        y_ref = dr.cross(x_ref, d)
        phi = dr.atan2(dr.dot(e_s, y_ref), dr.dot(e_s, x_ref))
        a_s, a_p, cos_t, _, _ = mi.fresnel_polarized(cos_i, n)
        Rs, Rp = dr.squared_norm(a_s), dr.squared_norm(a_p)
        if self.model == "single":
            R_s, R_p, T_s, T_p = Rs, Rp, 1.0 - Rs, 1.0 - Rp
        else:
            a = Float(1.0)
            if self.absorption_per_m > 0 and self.thickness_m > 0:
                a = dr.exp(-self.absorption_per_m * self.thickness_m / dr.maximum(dr.abs(cos_t), 1e-6))
            kmax = slab_terms(float(np.max(np.asarray(dr.detach(Rs)))))
            R_s, R_p = Float(Rs), Float(Rp)
            T_s, T_p = dr.zeros(Float, dr.width(Rs)), dr.zeros(Float, dr.width(Rs))
            # two-lobe branch sum through the slab: the branch transmitted into the glass bounces
            # between the faces; every bounce sends a reflected (R) and a transmitted (T) child out
            ts, tp = (1.0 - Rs) * (1.0 - Rs) * a, (1.0 - Rp) * (1.0 - Rp) * a
            for k in range(kmax + 1):
                T_s += ts
                T_p += tp
                ts_r, tp_r = ts * Rs * a, tp * Rp * a  # reflected at the back face, heading back
                R_s += ts_r
                R_p += tp_r
                ts, tp = ts_r * Rs * a, tp_r * Rp * a  # reflected again at the front face
        out = {"theta": theta, "phi": phi, "R_s": R_s, "R_p": R_p, "T_s": T_s, "T_p": T_p}
        if grad_index is not None:
            dr.forward_from(p[grad_index], flags=dr.ADFlag.ClearNone)  # keep interior gradients (outputs used by others)
            return {k: np.asarray(dr.grad(v), np.float64) for k, v in out.items()}
        return {k: np.asarray(v, np.float64) for k, v in out.items()}

    def _to_maps(self, r: dict, dr_: dict | None = None) -> dict[str, np.ndarray]:
        """Ray outputs -> per-pixel maps (Stokes-averaged over sub-pixel rays, as the maps tier);
        with ``dr_`` (the forward derivatives of the ray outputs) the derivatives of the maps.
        """
        K2, H, W = self.K * self.K, self.gh, self.gw
        c2, s2 = np.cos(2 * r["phi"]), np.sin(2 * r["phi"])

        def stokes(A, B, dA=None, dB=None):
            S = np.stack([0.5 * (A + B), 0.5 * (A - B) * c2, 0.5 * (A - B) * s2])
            if dA is None:
                return S.reshape(3, H, W, K2).mean(-1)
            dphi = dr_["phi"]
            dS = np.stack([0.5 * (dA + dB), 0.5 * (dA - dB) * c2 - (A - B) * s2 * dphi, 0.5 * (dA - dB) * s2 + (A - B) * c2 * dphi])
            return dS.reshape(3, H, W, K2).mean(-1)

        S_R = stokes(r["R_s"], r["R_p"])
        S_T = stokes(r["T_s"], r["T_p"])
        th = r["theta"].reshape(H, W, K2).mean(-1)
        P = np.hypot(S_R[1], S_R[2])
        # phi_perp from the reflected Stokes vector where it is polarized, else from geometry
        ph_geo = np.mod(r["phi"], np.pi).reshape(H, W, K2)[..., 0]
        phi = np.where(P > 1e-9, np.mod(0.5 * np.arctan2(S_R[2], S_R[1]), np.pi), ph_geo)
        c, s = np.cos(2 * phi), np.sin(2 * phi)

        def inv(S):
            q = S[1] * c + S[2] * s
            return S[0] + q, S[0] - q

        if dr_ is None:
            Rp_, Rl_ = inv(S_R)
            Tp_, Tl_ = inv(S_T)
            return {"theta": th, "phi_perp": phi, "R_perp": Rp_, "R_par": Rl_, "T_perp": Tp_, "T_par": Tl_}
        dS_R = stokes(r["R_s"], r["R_p"], dr_["R_s"], dr_["R_p"])
        dS_T = stokes(r["T_s"], r["T_p"], dr_["T_s"], dr_["T_p"])
        P2 = np.maximum(S_R[1] ** 2 + S_R[2] ** 2, 1e-30)
        dphi = 0.5 * (S_R[1] * dS_R[2] - S_R[2] * dS_R[1]) / P2
        dphi = np.where(P > 1e-9, dphi, dr_["phi"].reshape(H, W, K2)[..., 0])

        def dinv(S, dS):
            dq = dS[1] * c + dS[2] * s + 2.0 * (-S[1] * s + S[2] * c) * dphi
            return dS[0] + dq, dS[0] - dq

        dRp, dRl = dinv(S_R, dS_R)
        dTp, dTl = dinv(S_T, dS_T)
        return {"theta": dr_["theta"].reshape(H, W, K2).mean(-1), "phi_perp": dphi, "R_perp": dRp, "R_par": dRl, "T_perp": dTp, "T_par": dTl}

    # ------------------------------------------------------------------ public
    def maps(self, x) -> dict[str, np.ndarray]:
        """Per-pixel maps (H, W) float64: theta, phi_perp in [0, pi), R_perp, R_par, T_perp, T_par."""
        return self._to_maps(self._eval(x))

    def maps_and_jacobian(self, x, wrt: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Maps and their derivatives: J[field] is (len(wrt), H, W), Dr.Jit forward-mode AD, one pass per parameter."""
        r = self._eval(x)
        m = self._to_maps(r)
        J = {k: np.zeros((len(wrt), self.gh, self.gw)) for k in FIELDS}
        for j, i in enumerate(wrt):
            dm = self._to_maps(r, self._eval(x, grad_index=i))
            for k in FIELDS:
                J[k][j] = dm[k]
        return m, J

