"""Deterministic two-lobe polarized evaluation of a glass pane with Mitsuba 3.

Path tracing a smooth ``dielectric`` picks reflection OR transmission at random
per sample, so per-pixel coefficients from a plain ``stokes``+``path`` render
carry Monte Carlo noise that falls only as spp^-1/2.  This module instead
follows BOTH lobes at every glass hit:

1. Mitsuba generates the camera rays (``sensor.sample_ray``) through a fixed
   ``sub x sub`` grid of sub-pixel positions (deterministic anti-aliasing).
2. Each ray is intersected with the pane geometry of
   :func:`generator.mitsuba_scene.pane_interfaces` (``scene.ray_intersect``).
3. At every hit the pane's ``dielectric`` BSDF is sampled twice with the BSDF
   context restricted to one component (0 = delta reflection, 1 = delta
   transmission): with one lobe enabled the returned weight IS that lobe's
   Mueller matrix (pdf 1), converted to world Stokes bases with
   ``si.to_world_mueller``.  Both children are traced on.
4. A branch that leaves the pane is classified by its direction: back toward
   the camera side -> reflected light (it sees the R layer); away -> transmitted
   (it sees the T layer).  Its accumulated Mueller product ``M_1 M_2 ... M_k``
   applied to unpolarized unit radiance (first column) is the Stokes vector
   it delivers to the camera.  Slabs sum all interreflections until the
   branch weight falls below ``min_weight`` (default 1e-7; incoherent sum, the
   ``2R/(1+R)`` law for a lossless slab; bulk absorption multiplies each
   internal segment by ``exp(-alpha * length)``).
5. The summed Stokes vectors are rotated into the camera frame of the
   ``stokes`` integrator (reference axis ``cross(d, up)``, image right) and
   averaged per pixel.

Per pixel, with unpolarized layers of unit radiance, the reflected Stokes
vector is ``((R_perp + R_par)/2, (R_perp - R_par)/2 cos 2phi_perp,
(R_perp - R_par)/2 sin 2phi_perp)`` (paper Eq. (2) in Stokes form), which is
inverted here for ``R_perp, R_par, phi_perp`` and likewise ``T_perp, T_par``.

``single`` (one interface) transmits into glass: Mitsuba scales radiance by
``1/n^2`` across it; :func:`pane_coefficients` undoes that scaling so that
``T = 1 - R`` (the convention of paper Eq. (1)), and says so.

Everything per branch runs in Mitsuba / Dr.Jit (a JIT variant: ``llvm_*`` or
``cuda_*`` ``mono_polarized``; float32): ray generation, intersection, the BSDF,
the Mueller products, compaction of live branches (``dr.compress`` /
``dr.gather``) and the per-lane sums (``dr.scatter_reduce``).  The final frame
rotation and per-pixel averages are float64 NumPy.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from polinfra.errors import BackendUnavailableError, SceneError

__all__ = ["pane_coefficients", "stokes_to_coefficients"]

log = logging.getLogger(__name__)


def _np(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


def _mueller_np(M) -> np.ndarray:
    """Dr.Jit Mueller matrix (Matrix4f or mono polarized Spectrum) -> (N, 4, 4) float64."""
    a = np.array(M, dtype=np.float64)
    return np.moveaxis(a.reshape(4, 4, -1), -1, 0)


def stokes_to_coefficients(s: np.ndarray, phi_perp_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Invert the Stokes form of paper Eq. (2) given the s-direction angle.

    Args:
        s: (3, ...) Stokes (S0, S1, S2) of unit unpolarized radiance after the pane.
        phi_perp_rad: (...) angle of the s-direction in the image plane.

    Returns:
        (C_perp, C_par) = (S0 + P, S0 - P) with P = S1 cos 2phi_perp + S2 sin 2phi_perp.
    """
    p = s[1] * np.cos(2 * phi_perp_rad) + s[2] * np.sin(2 * phi_perp_rad)
    return s[0] + p, s[0] - p


def pane_coefficients(
    mi,
    scene,
    pane_normal,
    camera_up,
    width: int,
    height: int,
    *,
    model: str = "single",
    n: float = 1.5,
    sub: int = 2,
    absorption_per_m: float = 0.0,
    max_depth: int = 64,
    min_weight: float = 1e-7,
    chunk_rays: int = 1 << 20,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, np.ndarray]:
    """Noise-free per-pixel pane response maps by two-lobe tracing (see module doc).

    Args:
        mi: mitsuba module with a JIT polarized mono variant set.
        scene: loaded Mitsuba scene holding the sensor and the pane interfaces
            only (no emitters needed).
        pane_normal: (3,) unit pane normal toward the camera side.
        camera_up: (3,) the camera's up vector (the ``stokes`` reference).
        width, height: image size W, H.
        model: pane model (``single`` gets the 1/n^2 radiance scaling undone).
        n: refractive index used in the scene (for that undo).
        sub: sub-pixel grid size per axis (sub*sub rays per pixel).
        absorption_per_m: bulk absorption coefficient inside the glass (1/m).
        max_depth: most glass interactions followed per branch.
        min_weight: branches whose throughput S0 falls below this are dropped.
        chunk_rays: rays per Mitsuba call (memory bound).
        progress: optional (done, total) callback over chunks.

    Returns:
        dict of (H, W) float64 maps: ``theta`` (incidence angle, rad, of the
        camera ray on the first interface), ``phi_perp`` (rad, [0, pi)),
        ``R_perp``, ``R_par``, ``T_perp``, ``T_par``, ``G_perp``, ``G_par``
        (the part of R after the first surface: the slab's ghost), ``coverage``
        (fraction of sub-pixel rays that hit the pane), plus ``S_R``, ``S_R1``
        (first-surface reflection only) and ``S_T``
        (3, H, W): camera-frame Stokes of unit unpolarized R / T layers.
    """
    import drjit as dr

    if mi.variant() is None or mi.variant().startswith("scalar") or "spectral" in mi.variant():
        raise BackendUnavailableError(f"the two-lobe pane integrator needs a JIT mono polarized variant, current {mi.variant()!r}")
    W, H, K = int(width), int(height), int(sub)
    n_pane = _np(pane_normal).reshape(3)
    up = _np(camera_up).reshape(3)
    sensor = scene.sensors()[0]
    N = W * H * K * K
    s_r = np.zeros((4, N))
    s_t = np.zeros((4, N))
    s_r1 = np.zeros((4, N))
    cos_i = np.zeros(N)
    hit0 = np.zeros(N, dtype=bool)
    phi_geo_xy = np.zeros((2, N))
    chunks = list(range(0, N, chunk_rays))
    # evaluated (non-symbolic) BSDF calls: far lower per-launch overhead here
    with dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
        for ci, start in enumerate(chunks):
            _trace_chunk(mi, dr, scene, sensor, start, min(N, start + chunk_rays), W, H, K, n_pane, up, absorption_per_m, max_depth, min_weight, s_r, s_t, s_r1, cos_i, hit0, phi_geo_xy)
            if progress is not None:
                progress(ci + 1, len(chunks))
    return _finish(s_r, s_t, s_r1, cos_i, hit0, phi_geo_xy, W, H, K, model, n)


def _trace_chunk(mi, dr, scene, sensor, start, stop, W, H, K, n_pane, up, absorption_per_m, max_depth, min_weight, s_r, s_t, s_r1, cos_i, hit0, phi_geo_xy) -> None:
    """Trace rays start..stop (lane = pixel-major, sub-pixel minor) into the accumulators."""
    idx = np.arange(start, stop)
    pix, sb = np.divmod(idx, K * K)
    py, px = np.divmod(pix, W)
    sy, sx = np.divmod(sb, K)
    ux = (px + (sx + 0.5) / K) / W
    uy = (py + (sy + 0.5) / K) / H
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(mi.Float(ux.astype(np.float32)), mi.Float(uy.astype(np.float32))), mi.Point2f(0.5, 0.5))
    d0 = _np(ray.d).T  # (M, 3)
    # rotation from Mitsuba's implicit basis of -d to the stokes-integrator frame
    rot = _mueller_np(mi.mueller.rotate_stokes_basis(-ray.d, mi.mueller.stokes_basis(-ray.d), dr.cross(ray.d, mi.Vector3f(*[float(x) for x in up]))))
    x_ref = np.cross(d0, up)
    x_ref /= np.linalg.norm(x_ref, axis=1, keepdims=True)
    y_ref = np.cross(x_ref, d0)
    s_dir = np.cross(d0, n_pane)
    phi_geo_xy[0, start:stop] = np.einsum("ij,ij->i", s_dir, x_ref)
    phi_geo_xy[1, start:stop] = np.einsum("ij,ij->i", s_dir, y_ref)
    # branch state lives in Dr.Jit arrays (fused, multi-threaded kernels); lanes index this chunk
    n_lanes = stop - start
    nv = mi.Vector3f(*[float(x) for x in n_pane])
    acc = {key: [dr.zeros(mi.Float, n_lanes) for _ in range(4)] for key in ("r", "t", "r1")}
    sets = [{
        "lane": dr.arange(mi.UInt32, n_lanes), "ray": mi.Ray3f(ray.o, ray.d), "M": mi.Spectrum(mi.Matrix4f(1.0)),
        "inside": dr.full(mi.Bool, False, n_lanes), "primary": dr.full(mi.Bool, False, n_lanes),
        "p_prev": mi.Point3f(ray.o), "ok": dr.full(mi.Bool, True, n_lanes),
    }]
    for depth in range(max_depth + 1):
        new_sets = []
        for st in sets:
            si = scene.ray_intersect(st["ray"])
            if depth == 0:
                hit0[start:stop] = np.asarray(si.is_valid(), dtype=bool).reshape(-1)
                cos_i[start:stop] = np.abs(_np(si.wi.z).reshape(-1))
            valid = si.is_valid() & st["ok"]
            # branches that leave: classify by direction relative to the pane normal
            esc = ~si.is_valid() & st["ok"]
            toward = dr.dot(st["ray"].d, nv) > 0
            M = st["M"]
            for c in range(4):
                val = M[c][0][0]
                dr.scatter_reduce(dr.ReduceOp.Add, acc["r"][c], val, st["lane"], esc & toward)
                dr.scatter_reduce(dr.ReduceOp.Add, acc["t"][c], val, st["lane"], esc & ~toward)
                if depth == 1:
                    dr.scatter_reduce(dr.ReduceOp.Add, acc["r1"][c], val, st["lane"], esc & st["primary"])
            dr.eval(acc)
            if depth == max_depth:
                if dr.any(valid):
                    log.debug("two-lobe tracer: branches cut at max_depth %d", max_depth)
                continue
            idx = dr.compress(valid)
            if dr.width(idx) == 0:
                continue
            lane = dr.gather(mi.UInt32, st["lane"], idx)
            r = dr.gather(mi.Ray3f, st["ray"], idx)
            M = dr.gather(mi.Spectrum, M, idx)
            inside = dr.gather(mi.Bool, st["inside"], idx)
            p_prev = dr.gather(mi.Point3f, st["p_prev"], idx)
            si = scene.ray_intersect(r)
            # internal path length between the parallel faces: normal separation / |cos|.  Not si.t,
            # nor |p - p_prev|: spawn_ray offsets origins along the normal by Mitsuba's ray
            # epsilon (~0.18 mm at 1 m from the origin), which would shorten the path by ~3%.
            if absorption_per_m > 0:
                seg = dr.abs(dr.dot(si.p - p_prev, nv)) / dr.maximum(dr.abs(dr.dot(r.d, nv)), 1e-12)
                M = M * dr.select(inside, dr.exp(-absorption_per_m * seg), 1.0)
            for comp in (0, 1):
                ctx = mi.BSDFContext()
                ctx.component = comp
                bs, wt = si.bsdf().sample(ctx, si, 0.5, mi.Point2f(0.5, 0.5))
                Mk = M @ si.to_world_mueller(wt, -bs.wo, si.wi)
                w00 = Mk[0][0][0]
                kid = {
                    "lane": lane, "ray": si.spawn_ray(si.to_world(bs.wo)), "M": Mk,
                    "inside": inside ^ (comp == 1), "primary": dr.full(mi.Bool, comp == 0 and depth == 0, dr.width(lane)),
                    "p_prev": mi.Point3f(si.p), "ok": dr.isfinite(w00) & (w00 > min_weight),
                }
                dr.eval(kid)
                new_sets.append(kid)
        sets = new_sets
        if not sets:
            break
    acc_np = {k: np.stack([_np(a).reshape(-1) for a in v], axis=1) for k, v in acc.items()}  # (n, 4)
    s_r[:, start:stop] = (rot @ acc_np["r"][:, :, None])[:, :, 0].T
    s_t[:, start:stop] = (rot @ acc_np["t"][:, :, None])[:, :, 0].T
    s_r1[:, start:stop] = (rot @ acc_np["r1"][:, :, None])[:, :, 0].T


def _finish(s_r, s_t, s_r1, cos_i, hit0, phi_geo_xy, W, H, K, model, n) -> dict[str, np.ndarray]:
    def per_pixel(a: np.ndarray) -> np.ndarray:
        return a.reshape(*a.shape[:-1], H, W, K * K).mean(axis=-1)

    S_R = per_pixel(s_r[:3])
    S_T = per_pixel(s_t[:3])
    S_R1 = per_pixel(s_r1[:3])
    if model == "single":
        S_T = S_T * float(n) ** 2  # undo Mitsuba's 1/n^2 radiance scaling into glass: T = 1 - R
    cov = per_pixel(hit0.astype(np.float64))
    theta = per_pixel(np.arccos(np.clip(cos_i, 0.0, 1.0)))
    # phi_perp: from the reflected Stokes where it is polarized, else from geometry
    pol = np.hypot(S_R[1], S_R[2])
    phi_st = np.mod(0.5 * np.arctan2(S_R[2], S_R[1]), np.pi)
    gx, gy = per_pixel(phi_geo_xy[0]), per_pixel(phi_geo_xy[1])
    phi_geo = np.mod(np.arctan2(gy, gx), np.pi)
    phi_perp = np.where(pol > 1e-7, phi_st, phi_geo)
    R_perp, R_par = stokes_to_coefficients(S_R, phi_perp)
    T_perp, T_par = stokes_to_coefficients(S_T, phi_perp)
    R1_perp, R1_par = stokes_to_coefficients(S_R1, phi_perp)
    out = {"theta": theta, "phi_perp": phi_perp, "R_perp": R_perp, "R_par": R_par, "T_perp": T_perp, "T_par": T_par, "coverage": cov, "G_perp": R_perp - R1_perp, "G_par": R_par - R1_par, "S_R": S_R, "S_R1": S_R1, "S_T": S_T, "phi_perp_geometric": phi_geo}
    for k, v in out.items():
        if not np.all(np.isfinite(v)):
            raise SceneError(f"two-lobe tracer produced non-finite values in {k}; check the pane geometry")
    return out
