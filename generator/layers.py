"""Layer content: offline textures with motion, placed on the T and R planes.

Sources (``LayerConfig.source``):
    ``skimage:NAME``   a scikit-image bundled image (grey; works offline),
    ``procedural:KIND``  checker | stripes | noise | gradient | disk | rings | flat (1.0),
    ``image:PATH``     one image file,
    ``folder:PATH``    a folder of frames (sorted by name) at ``content_fps``,
    ``video:PATH``     a video file (imageio/ffmpeg) at ``content_fps``.
8-bit content is decoded to linear radiance with ``gamma``; then
radiance = offset + brightness * content, in [0, 1].

A layer plane is perpendicular to its camera's optical axis (the real camera
for T, the mirrored camera for R) and spans the view plus ``margin`` on each
side.  Texture coordinates (s, t) in [0, 1]^2 run along the camera's right and
down axes, so with no pane offsets a layer image is the texture's central crop.
Motion is rigid in "view coordinates" (X, Y) = view fractions centred on the
axis: translation, counter-clockwise rotation and exponential zoom.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
from scipy import ndimage

from generator.scene import LayerConfig
from polinfra.errors import ConfigError, DataFormatError
from polphysics.geometry import PinholeCamera, Plane, intersect_plane

__all__ = ["LayerPlane", "LayerContent", "load_source", "shake_offset", "SHAKE_KNOT_S", "SHAKE_TAU_S", "PROCEDURAL_KINDS", "SKIMAGE_NAMES"]

SHAKE_KNOT_S = 0.002
"""Knot spacing (s) of the shake's velocity random walk."""
SHAKE_TAU_S = 0.05
"""Correlation time (s) of the shake's velocity (an Ornstein-Uhlenbeck walk)."""

log = logging.getLogger(__name__)

PROCEDURAL_KINDS = ("checker", "stripes", "noise", "gradient", "disk", "rings", "flat")
SKIMAGE_NAMES = (
    "astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins", "colorwheel", "grass", "gravel",
    "horse", "hubble_deep_field", "immunohistochemistry", "moon", "page", "retina", "rocket", "text",
)


def _to_gray01(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img)
    if a.dtype == bool:
        a = a.astype(np.float64)
    elif np.issubdtype(a.dtype, np.integer):
        a = a.astype(np.float64) / float(np.iinfo(a.dtype).max)
    else:
        a = a.astype(np.float64)
    if a.ndim == 3:
        a = a[..., :3] @ np.array([0.2126, 0.7152, 0.0722])[: a.shape[-1]] if a.shape[-1] >= 3 else a[..., 0]
    return np.clip(a, 0.0, 1.0)


def _procedural(kind: str, shape: tuple[int, int], seed: int) -> np.ndarray:
    h, w = shape
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    if kind == "flat":
        return np.ones((h, w))
    if kind == "checker":
        return ((np.floor(x * 12) + np.floor(y * 12)) % 2).astype(np.float64) * 0.8 + 0.1
    if kind == "stripes":
        return 0.5 + 0.4 * np.sin(2 * np.pi * 10 * x)
    if kind == "gradient":
        return 0.1 + 0.8 * x / max(x.max(), 1e-9)
    if kind == "noise":
        rng = np.random.default_rng(seed)
        return np.clip(ndimage.gaussian_filter(rng.random((h, w)), sigma=max(h, w) / 60) * 3 - 1, 0, 1) * 0.8 + 0.1
    if kind == "disk":
        r = np.hypot(x - x.mean(), y - y.mean())
        return (r < 0.45 * min(h, w) / max(h, w)).astype(np.float64)
    if kind == "rings":
        r = np.hypot(x - x.mean(), y - y.mean())
        return 0.5 + 0.4 * np.cos(2 * np.pi * 8 * r)
    raise ConfigError(f"unknown procedural content {kind!r}; choose one of {list(PROCEDURAL_KINDS)}")


def _read_image(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    try:
        return _to_gray01(iio.imread(path))
    except Exception as exc:
        raise DataFormatError(f"cannot read image {path}: {exc}") from None


def load_source(source: str, shape: tuple[int, int], seed: int = 0, gamma: float = 2.2) -> list[np.ndarray]:
    """Decode a content source to a list of linear grey frames of ``shape`` (H, W) in [0, 1].

    Still sources return one frame; folders and videos return all their frames.
    """
    kind, _, arg = source.partition(":")
    if not arg:
        raise ConfigError(f"layer source {source!r} must look like KIND:VALUE (skimage:camera, procedural:checker, image:PATH, folder:PATH, video:PATH)")
    if kind == "skimage":
        if arg not in SKIMAGE_NAMES:
            raise ConfigError(f"skimage image {arg!r} is not bundled offline; choose one of {list(SKIMAGE_NAMES)}")
        import skimage.data

        frames = [_to_gray01(getattr(skimage.data, arg)()) ** gamma]
    elif kind == "procedural":
        return [_procedural(arg, shape, seed)]
    elif kind == "image":
        frames = [_read_image(Path(arg)) ** gamma]
    elif kind == "folder":
        files = sorted(p for p in Path(arg).glob("*") if p.suffix.lower() in {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".exr"})
        if not files:
            raise ConfigError(f"layer folder {arg!r} holds no image frames (png/jpg/tif/bmp)")
        frames = [_read_image(p) ** gamma for p in files]
    elif kind == "video":
        import imageio.v3 as iio

        if not Path(arg).is_file():
            raise ConfigError(f"layer video {arg!r} not found")
        try:
            frames = [_to_gray01(f) ** gamma for f in iio.imiter(arg)]
        except Exception as exc:
            raise DataFormatError(f"cannot decode video {arg}: {exc}") from None
        if not frames:
            raise DataFormatError(f"video {arg} has no frames")
    else:
        raise ConfigError(f"unknown layer source kind {kind!r} in {source!r}; use skimage:, procedural:, image:, folder: or video:")
    return [_fit(f, shape) for f in frames]


def _fit(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resize and centre-crop ``img`` to cover ``shape`` (aspect preserved)."""
    from skimage.transform import resize

    h, w = shape
    ih, iw = img.shape
    k = max(h / ih, w / iw)
    nh, nw = max(h, int(np.ceil(ih * k))), max(w, int(np.ceil(iw * k)))
    big = resize(img, (nh, nw), order=1, anti_aliasing=k < 1, preserve_range=True)
    y0, x0 = (nh - h) // 2, (nw - w) // 2
    return np.ascontiguousarray(big[y0 : y0 + h, x0 : x0 + w])


@dataclasses.dataclass(frozen=True)
class LayerPlane:
    """A textured plane perpendicular to a camera's axis, filling its view plus a margin.

    Attributes:
        center: (3,) plane centre on the camera axis.
        right, up: (3,) in-plane unit axes (texture s along right, t along -up).
        half_w, half_h: half extents of the textured area (m).
        view_half_w, view_half_h: half extents of the camera view at the plane (m).
    """

    center: np.ndarray
    right: np.ndarray
    up: np.ndarray
    half_w: float
    half_h: float
    view_half_w: float
    view_half_h: float

    @classmethod
    def facing(cls, camera: PinholeCamera, distance_m: float, margin: float) -> "LayerPlane":
        tx = np.tan(0.5 * camera.fov_x_rad)
        vw = distance_m * tx
        vh = vw * camera.height / camera.width
        k = 1.0 + 2.0 * margin
        return cls(camera.position + distance_m * camera.forward, camera.right, camera.up, vw * k, vh * k, vw, vh)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.right, self.up)

    def uv(self, origin, direction):
        """View coordinates (X, Y) (view fractions, centred; Y down) where rays hit the plane."""
        _, pts = intersect_plane(origin, direction, Plane(self.center, self.normal))
        rel = pts - self.center
        return rel @ self.right / (2 * self.view_half_w), -(rel @ self.up) / (2 * self.view_half_h)


def shake_offset(rms_per_s: float, seed: int, t_s, aspect: float):
    """Offset (view fractions x, y) at time ``t_s`` (a float or an array) of a hand-held shake: the integral
    of a stationary Ornstein-Uhlenbeck velocity (correlation time :data:`SHAKE_TAU_S`, knots every
    :data:`SHAKE_KNOT_S`), isotropic in pixels, whose speed has rms ``rms_per_s`` view widths per second;
    zero at t <= 0.  The walk is a function of ``seed`` alone, so two layers with equal (rms, seed) shake as
    one camera.
    """
    from scipy.signal import lfilter

    t = np.asarray(t_s, dtype=np.float64)
    if rms_per_s == 0.0 or not np.any(t > 0.0):
        return (np.zeros_like(t), np.zeros_like(t)) if t.ndim else (0.0, 0.0)
    n = int(np.ceil(float(np.max(t)) / SHAKE_KNOT_S)) + 1
    n = 1024 * int(np.ceil(n / 1024))  # whole blocks: the walk's prefix does not depend on t
    z = np.random.default_rng(int(seed)).standard_normal((n, 2))
    a = float(np.exp(-SHAKE_KNOT_S / SHAKE_TAU_S))
    # v[0] = z[0] (stationary start), v[k] = a v[k-1] + sqrt(1 - a^2) z[k]
    v = lfilter([1.0], [1.0, -a], np.concatenate([z[:1], np.sqrt(1.0 - a * a) * z[1:]]), axis=0)
    v *= rms_per_s / np.sqrt(2.0)  # per axis: the speed's rms is rms_per_s
    cum = np.concatenate([[[0.0, 0.0]], np.cumsum(0.5 * (v[1:] + v[:-1]) * SHAKE_KNOT_S, 0)])
    tk = np.arange(n) * SHAKE_KNOT_S
    tc = np.maximum(t, 0.0)
    dx, dy = np.interp(tc, tk, cum[:, 0]), np.interp(tc, tk, cum[:, 1]) * aspect  # view widths -> view heights
    return (dx, dy) if t.ndim else (float(dx), float(dy))


class LayerContent:
    """Time-varying content of one layer, sampled in view coordinates.

    Args:
        cfg: the layer's config.
        view_shape: camera (H, W); the texture is ``view_shape * (1 + 2 margin) * texture_scale``.
    """

    def __init__(self, cfg: LayerConfig, view_shape: tuple[int, int]):
        self.cfg = cfg
        k = (1.0 + 2.0 * cfg.margin) * cfg.texture_scale
        self.tex_shape = (max(2, int(round(view_shape[0] * k))), max(2, int(round(view_shape[1] * k))))
        self.frames = load_source(cfg.source, self.tex_shape, cfg.seed, cfg.gamma)
        self.sprites = [
            (sp, load_source(sp.source, (64, 64), cfg.seed + 1 + i, cfg.gamma)[0], sp.source.startswith("procedural:disk"))
            for i, sp in enumerate(cfg.sprites)
        ]
        self.aspect = view_shape[1] / view_shape[0]  # W / H of the view
        self.extent = 1.0 + 2.0 * cfg.margin

    @property
    def is_static(self) -> bool:
        m = self.cfg.motion
        return len(self.frames) == 1 and not self.sprites and m.translate_per_s == (0.0, 0.0) and m.rotate_deg_per_s == 0.0 and m.zoom_per_s == 0.0 and m.shake_per_s == 0.0

    def _frame_at(self, t_s: float) -> np.ndarray:
        i = int(np.floor(t_s * self.cfg.content_fps + 1e-9)) % len(self.frames)
        return self.frames[i]

    def sample(self, t_s: float, X, Y):
        """Radiance at view coordinates (X, Y) (arrays) at scene time ``t_s`` (s)."""
        m = self.cfg.motion
        sx, sy = shake_offset(m.shake_per_s, m.shake_seed, t_s, self.aspect)
        Xs = X - m.translate_per_s[0] * t_s - sx
        Ys = Y - m.translate_per_s[1] * t_s - sy
        a = -np.deg2rad(m.rotate_deg_per_s * t_s)
        # rotate in a metric frame (x right, y up), counter-clockwise as seen in the image
        xm, ym = Xs * self.aspect, -Ys
        xr, yr = np.cos(a) * xm - np.sin(a) * ym, np.sin(a) * xm + np.cos(a) * ym
        k = np.exp(-m.zoom_per_s * t_s)
        Xb, Yb = xr / self.aspect * k, -yr * k
        th, tw = self.tex_shape
        col = (Xb / self.extent + 0.5) * tw - 0.5
        row = (Yb / self.extent + 0.5) * th - 0.5
        val = ndimage.map_coordinates(self._frame_at(t_s), [row, col], order=1, mode="mirror")
        for sp, img, round_ in self.sprites:
            cx = sp.start[0] - 0.5 + sp.velocity_per_s[0] * t_s
            cy = sp.start[1] - 0.5 + sp.velocity_per_s[1] * t_s
            half_y = 0.5 * sp.size
            half_x = half_y / self.aspect
            lx = (X - cx) / (2 * half_x) + 0.5
            ly = (Y - cy) / (2 * half_y) + 0.5
            inside = (lx >= 0) & (lx <= 1) & (ly >= 0) & (ly <= 1)
            if round_:
                inside &= (lx - 0.5) ** 2 + (ly - 0.5) ** 2 <= 0.25
            if np.any(inside):
                sv = ndimage.map_coordinates(img, [ly[inside] * 63.0, lx[inside] * 63.0], order=1, mode="nearest")
                val = val.copy()
                val[inside] = sp.brightness * (sv if not round_ else 1.0)
        return np.clip(self.cfg.offset + self.cfg.brightness * val, 0.0, 1.0)
