"""On-the-fly training windows from the generator and the spike simulator.

This module is the bridge ``reconstruct`` may not cross itself: it renders
crops with the generator's **analytic tier** (:func:`generator.analytic.analytic_maps`,
:func:`generator.analytic.sample_layers`, :func:`generator.analytic.frame_stokes`)
and simulates them with :func:`spike_sim.simulate` (integrate-and-fire with the
full noise model), the code that builds stores, then turns the stream into a
window item with :func:`reconstruct.net.onthefly.item_from_stream`.

One item (``(seed, index)`` -> item, a pure function):

1. ``rng = np.random.default_rng([seed, index])`` draws a scene of the pool,
   a start time t0 in the scene's clip, a crop (y0, x0) of the 400x250 camera,
   the exposure and the simulator seed;
2. the crop's pane maps are a slice of the full-frame analytic maps (cached per
   scene, so a crop sees exactly the geometry of the full camera);
3. Stokes keyframes of the crop at ``window.keyframe_hz`` from t0 over the
   window's steps only (about 21 ms: N = 7 frames at 31.5 deg stride, 13-step windows);
4. the crop is simulated as a small sensor (``spike_sim.simulate``, ``out=None``),
   the polarizer phase advanced to t0;
5. Eq. (3) frames, angles and GT as a stored group would give them.

Building the same *window group* as a store (``simulate(..., out=DIR)``, see
:meth:`GeneratorWindows.window_group`) and reading it back gives the same item
(tests/pipeline/test_train_windows.py).

Scene pool: :func:`sample_scene` draws scenes from the documented ranges of
:class:`SceneRanges` (pane model / index / tilt / tilt axis, camera field of
view and roll, layer content, brightness and motion), the settings a
``paper.toml``-like manifest varies; layer content is split between train and
test (:data:`TEST_CONTENT`), so no content is shared.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from polinfra.config import opt
from polinfra.errors import ConfigError, SceneError

log = logging.getLogger(__name__)

__all__ = ["SceneRanges", "TEST_CONTENT", "train_content", "sample_scene", "scene_pool", "manifest_scenes", "GeneratorWindows", "window_sets"]

TEST_CONTENT = ("skimage:chelsea", "skimage:coins", "skimage:grass", "skimage:text", "skimage:rocket", "procedural:rings")
"""Layer content used only by test scenes (never by training scenes)."""


def train_content() -> tuple[str, ...]:
    """Layer sources of training scenes: bundled images and procedural kinds minus :data:`TEST_CONTENT`."""
    from generator.layers import PROCEDURAL_KINDS, SKIMAGE_NAMES

    pool = [f"skimage:{n}" for n in SKIMAGE_NAMES] + [f"procedural:{k}" for k in PROCEDURAL_KINDS if k not in ("flat", "gradient")]
    return tuple(s for s in pool if s not in TEST_CONTENT)


@dataclasses.dataclass(frozen=True)
class SceneRanges:
    """Ranges the scene sampler draws from (uniform unless noted)."""

    fov_deg: tuple[float, float] = opt((40.0, 65.0), "camera horizontal field of view, deg")
    roll_deg: tuple[float, float] = opt((-15.0, 15.0), "camera roll, deg")
    pane_models: tuple[str, ...] = opt(("single", "thin_slab", "thick_slab"), "pane models (equally likely)")
    n: tuple[float, float] = opt((1.45, 1.65), "refractive index")
    pane_distance_m: tuple[float, float] = opt((0.4, 1.5), "camera-to-pane distance, m")
    tilt_deg: tuple[float, float] = opt((0.0, 55.0), "pane tilt from the optical axis, deg (sets the incidence angles)")
    thickness_mm: tuple[float, float] = opt((3.0, 10.0), "slab thickness, mm")
    t_distance_m: tuple[float, float] = opt((2.0, 6.0), "T plane distance, m")
    r_distance_m: tuple[float, float] = opt((0.5, 3.0), "R plane distance beyond the pane, m")
    t_brightness: tuple[float, float] = opt((0.5, 1.0), "T layer radiance of content 1.0")
    r_brightness: tuple[float, float] = opt((0.4, 1.0), "R layer radiance of content 1.0")
    offset: tuple[float, float] = opt((0.0, 0.1), "radiance added to each layer")
    translate_per_s: float = opt(0.15, "std of the layer translation speed, view fractions per second")
    rotate_deg_per_s: float = opt(8.0, "std of the layer rotation speed, deg/s")
    zoom_per_s: float = opt(0.1, "std of the layer log-zoom rate, 1/s")
    jitter_deg: tuple[float, float] = opt((0.0, 0.3), "polarizer per-step jitter, deg")
    calibration_offset_deg: tuple[float, float] = opt((-1.0, 1.0), "true minus calibrated polarizer phase, deg")


def sample_scene(rng: np.random.Generator, content: Sequence[str], ranges: SceneRanges = SceneRanges(), name: str = "scene", duration_s: float = 1.0):
    """Draw a valid :class:`generator.scene.SceneConfig` (redraws geometry the pane cannot cover)."""
    from generator.scene import check_scene_geometry, scene_from_dict

    u = lambda r: float(rng.uniform(*r))  # noqa: E731

    def motion() -> dict:
        return {
            "translate_per_s": [float(rng.normal(0, ranges.translate_per_s)), float(rng.normal(0, ranges.translate_per_s))],
            "rotate_deg_per_s": float(rng.normal(0, ranges.rotate_deg_per_s)),
            "zoom_per_s": float(rng.normal(0, ranges.zoom_per_s)),
        }

    for _ in range(100):
        i, j = rng.choice(len(content), size=2, replace=False)
        model = str(ranges.pane_models[int(rng.integers(len(ranges.pane_models)))])
        data = {
            "name": name,
            "description": "sampled by polspike.pipeline.train_windows.sample_scene",
            "camera": {"width": 400, "height": 250, "fov_deg": u(ranges.fov_deg), "roll_deg": u(ranges.roll_deg)},
            "pane": {
                "model": model, "n": u(ranges.n), "distance_m": u(ranges.pane_distance_m), "tilt_deg": u(ranges.tilt_deg),
                "tilt_axis_deg": float(rng.uniform(0, 360)), "size_m": [60.0, 60.0], "thickness_mm": u(ranges.thickness_mm),
            },
            "layers": {
                "transmission": {"source": content[i], "distance_m": u(ranges.t_distance_m), "brightness": u(ranges.t_brightness), "offset": u(ranges.offset), "seed": int(rng.integers(1 << 30)), "motion": motion()},
                "reflection": {"source": content[j], "distance_m": u(ranges.r_distance_m), "brightness": u(ranges.r_brightness), "offset": u(ranges.offset), "seed": int(rng.integers(1 << 30)), "motion": motion()},
            },
            "polarizer": {"rate_hz": 30.0, "phase_deg": float(rng.uniform(0, 360)), "jitter_deg": u(ranges.jitter_deg), "calibration_offset_deg": u(ranges.calibration_offset_deg)},
            "render": {"duration_s": duration_s, "fps": 2000.0},
        }
        scene = scene_from_dict(data, where=name)
        try:
            check_scene_geometry(scene)
        except SceneError:
            continue
        return scene
    raise SceneError("could not draw a scene whose pane covers the view in 100 tries; narrow SceneRanges.tilt_deg or fov_deg")


def scene_pool(n: int, seed: int, split: str = "train", ranges: SceneRanges = SceneRanges()) -> list:
    """``n`` scenes for ``split`` ("train" uses :func:`train_content`, "test" :data:`TEST_CONTENT`)."""
    content = train_content() if split == "train" else TEST_CONTENT
    rng = np.random.default_rng([seed, 0 if split == "train" else 1])
    return [sample_scene(rng, content, ranges, name=f"{split}{k:03d}") for k in range(n)]


class _SceneCache:
    """Full-frame analytic maps (float32) and layer content of one scene."""

    def __init__(self, scene):
        from generator.analytic import analytic_maps
        from generator.layers import LayerContent

        m = analytic_maps(scene)
        f = lambda a: None if a is None else np.asarray(a, np.float32)  # noqa: E731
        self.maps = dataclasses.replace(
            m, **{k: f(getattr(m, k)) for k in ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par", "G_perp", "G_par")},
            t_xy=tuple(f(a) for a in m.t_xy), r_xy=tuple(f(a) for a in m.r_xy), g_xy=None if m.g_xy is None else tuple(f(a) for a in m.g_xy),
        )
        shape = (scene.camera.height, scene.camera.width)
        self.tc = LayerContent(scene.layers.transmission, shape)
        self.rc = LayerContent(scene.layers.reflection, shape)

    def crop(self, y0: int, x0: int, S: int):
        sl = (slice(y0, y0 + S), slice(x0, x0 + S))
        m = self.maps
        c = lambda a: np.ascontiguousarray(a[sl], dtype=np.float64)  # noqa: E731
        return dataclasses.replace(
            m, **{k: c(getattr(m, k)) for k in ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par", "G_perp", "G_par")},
            t_xy=tuple(c(a) for a in m.t_xy), r_xy=tuple(c(a) for a in m.r_xy), g_xy=None if m.g_xy is None else tuple(c(a) for a in m.g_xy),
        )


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    """One log-uniform draw in [low, high]."""
    return math.exp(rng.uniform(math.log(bounds[0]), math.log(bounds[1])))


class GeneratorWindows:
    """A :data:`reconstruct.net.onthefly.WindowSource` over a scene pool (module docstring).

    Args:
        scenes: :class:`generator.scene.SceneConfig` list (all 400x250 or any size >= the crop).
        window: :class:`reconstruct.net.onthefly.WindowConfig`.
        cache_scenes: scenes whose maps and content stay in memory (about 7 MB each).
    """

    def __init__(self, scenes: Sequence, window, cache_scenes: int = 64, sims: Sequence | None = None):
        from spike_sim.config import preset

        if not scenes:
            raise SceneError("GeneratorWindows needs at least one scene")
        if window.exposure_source == "group" and (sims is None or len(sims) != len(scenes)):
            raise SceneError("window.exposure_source = 'group' needs each scene's manifest sensor (train with a manifest)")
        self.scenes = list(scenes)
        self.sims = None if sims is None else list(sims)
        self.window = window
        self.sim = preset("default" if window.sim_preset == "group" else window.sim_preset)
        self.cache: OrderedDict[int, _SceneCache] = OrderedDict()
        self.cache_scenes = cache_scenes
        self.rate_hz = self.sim.rate_hz
        stride_steps = window.stride_deg / 360.0 / 30.0 * self.rate_hz
        self.n_steps = int(math.ceil((window.n_obs + 1) * stride_steps + window.window_steps // 2 + 2))
        self.n_steps += window.mean_steps  # room for the long spike mean around the centre frame

    def _scene(self, j: int) -> _SceneCache:
        if j in self.cache:
            self.cache.move_to_end(j)
            return self.cache[j]
        sc = _SceneCache(self.scenes[j])
        self.cache[j] = sc
        if len(self.cache) > self.cache_scenes:
            self.cache.popitem(last=False)
        return sc

    def window_group(self, seed: int, index: int) -> dict:
        """The window group of item ``(seed, index)``: keyframe source, duration, sim seed and config, maps."""
        from generator.analytic import frame_stokes, sample_layers
        from spike_sim.simulate import KeyframeSource

        w = self.window
        rng = np.random.default_rng([int(seed), int(index)])
        j = int(rng.integers(len(self.scenes)))
        scene = self.scenes[j]
        S = w.crop
        H, W = scene.camera.height, scene.camera.width
        if S > min(H, W):
            raise SceneError(f"crop {S} does not fit the {W}x{H} camera of scene {scene.name}; reduce window.crop")
        dur = self.n_steps / self.rate_hz
        t0 = float(rng.uniform(0.0, max(scene.render.duration_s - dur, 0.0)))
        y0 = int(rng.integers(0, H - S + 1))
        x0 = int(rng.integers(0, W - S + 1))
        if w.exposure_source == "group":  # the group's light level, jittered log-uniformly
            base = self.sims[j]
            exposure = float(base.exposure * _log_uniform(rng, w.exposure_jitter))
            if w.bright_prob > 0 and rng.random() < w.bright_prob:  # bright light the manifest may lack (sampler's formula)
                from polspike.pipeline.sampler import exposure_for_rate

                exposure = exposure_for_rate(_log_uniform(rng, w.bright_rate), scene.layers.transmission.brightness)
        else:
            base = self.sim
            exposure = float(rng.uniform(*w.exposure_range))
        sim_seed = int(rng.integers(0, 2**31 - 1))
        sc = self._scene(j)
        maps = sc.crop(y0, x0, S)
        nk = int(math.ceil(dur * w.keyframe_hz)) + 2
        times = np.arange(nk) / w.keyframe_hz
        cache: dict[int, tuple] = {}

        def frame(i: int):
            if i not in cache:
                L_T, L_R, L_G = sample_layers(maps, sc.tc, sc.rc, t0 + float(times[i]))
                cache[i] = (frame_stokes(maps, L_T, L_R, L_G).astype(np.float32), np.asarray(L_T, np.float32), np.asarray(L_R, np.float32))
            return cache[i]

        pol = scene.polarizer
        pol = dataclasses.replace(pol, phase_deg=float((pol.phase_deg + 360.0 * pol.rate_hz * t0) % 360.0))
        chans = maps.channels()
        src = KeyframeSource(
            times_s=times, stokes=lambda i: frame(i)[0], height=S, width=S, layers=lambda i: frame(i)[1:],
            maps=lambda: {k: np.asarray(v, np.float32) for k, v in chans.items()}, polarizer=pol, scene_hash=f"window-{seed}-{index}",
        )
        sim = dataclasses.replace(base, width=S, height=S, exposure=exposure, rate_hz=self.rate_hz)
        return {"source": src, "duration_s": dur, "seed": sim_seed, "config": sim, "scene": j, "t0_s": t0, "crop": (y0, x0, S)}

    def __call__(self, seed: int, index: int):
        import numba

        from polphysics.polarizer import phi_nominal, step_phi_edges
        from reconstruct.net.onthefly import flip_item, item_from_stream
        from spike_sim.aggregate import AggregateConfig, frame_centres
        from spike_sim.simulate import _interp_layers, simulate

        g = self.window_group(seed, index)
        src, cfg, w = g["source"], g["config"], self.window
        chunks: list[np.ndarray] = []
        agg = AggregateConfig(window_steps=w.window_steps, stride_deg=w.stride_deg, n_obs=w.n_obs)
        nthreads = numba.get_num_threads()
        numba.set_num_threads(1)  # a window is ~0.4 M pixel-steps: thread start-up would dominate
        try:
            simulate(src, g["duration_s"], g["seed"], cfg, out=None, chunk_steps=self.n_steps, aggregate=agg, spikes_sink=lambda n0, pk: chunks.append(pk))
        finally:
            numba.set_num_threads(nthreads)
        P = cfg.height * cfg.width
        spikes = np.unpackbits(np.concatenate(chunks), axis=1, bitorder="little", count=P).reshape(-1, cfg.height, cfg.width)
        n = spikes.shape[0]
        dt = 1.0 / cfg.rate_hz
        pol = src.polarizer
        phi_nom = phi_nominal((np.arange(n) + 0.5) * dt, pol)
        pa, pb = step_phi_edges(0, n, dt, pol, g["seed"])
        centres, _ = frame_centres(phi_nom, agg, phi_start_rad=float(phi_nominal(0.0, pol)))
        m, K = len(centres) // 2, w.n_obs // 2
        ck = centres[m - K : m + K + 1]  # the N output frames around the middle one, as evaluation stacks them
        c = int(ck[K])
        item = item_from_stream(spikes, ck, phi_nom, 0.5 * (pa + pb), _interp_layers(src, (c + 0.5) * dt), src.maps(), cfg.exposure, w)
        if w.flips:  # drawn from its own stream so the unflipped item stays the same
            item = flip_item(item, int(np.random.default_rng([int(seed), int(index), 8]).integers(8)))
        return item


def manifest_scenes(path: str, split: str, with_sensor: bool = False) -> list:
    """Scenes of the ``split`` groups of a dataset manifest (``datasets/manifests/*.toml``), clip length = group duration.

    With ``with_sensor``: (scenes, sensors), the groups' resolved :class:`spike_sim.config.SpikeSimConfig` beside them.
    """
    from generator.scene import scene_from_dict
    from polinfra.config import from_dict
    from polspike.pipeline.manifest import load_manifest
    from spike_sim.config import SpikeSimConfig

    m = load_manifest(path)
    out, sims = [], []
    for g in m.groups:
        if g.split == split:
            sc = scene_from_dict(g.scene, where=f"{path} [{g.name}]")
            out.append(dataclasses.replace(sc, render=dataclasses.replace(sc.render, duration_s=g.duration_s)))
            sims.append(from_dict(SpikeSimConfig, g.spike_sim, where=f"{path} [{g.name}] spike_sim"))
    if not out:
        raise ConfigError(f"manifest {path} has no {split!r} groups; splits: {sorted({g.split for g in m.groups})}")
    return (out, sims) if with_sensor else out


def window_sets(window, train_items: int, val_items: int, seed: int, n_train_scenes: int = 40, n_test_scenes: int = 10, scene_seed: int = 0, manifest: str = "", val_manifest: str = "", val_split: str = "train", mix_manifests: Sequence[str] = ()):
    """(train, validation) :class:`reconstruct.net.onthefly.OnTheFlyWindows` on disjoint scenes and content.

    With ``manifest``: the scenes of its "train" and "test" groups (e.g. ``paper.toml``: 40 / 10).
    Else training windows come from ``n_train_scenes`` scenes drawn with seed ``scene_seed``
    (the paper's 40 training groups) and validation windows from ``n_test_scenes`` test scenes.
    With ``val_manifest``: validation windows from its ``val_split`` groups instead (a validation split
    apart from the test groups). ``mix_manifests``: their "train" groups join ``manifest``'s.
    """
    from reconstruct.net.onthefly import OnTheFlyWindows

    if manifest:
        sc_tr, si_tr = manifest_scenes(manifest, "train", with_sensor=True)
        for extra in mix_manifests:
            sc, si = manifest_scenes(extra, "train", with_sensor=True)
            sc_tr, si_tr = sc_tr + sc, si_tr + si
        tr = GeneratorWindows(sc_tr, window, sims=si_tr)
    else:
        if mix_manifests:
            raise ConfigError("mix_manifests joins the train groups of manifest: set manifest too")
        tr = GeneratorWindows(scene_pool(n_train_scenes, scene_seed, "train"), window)
    if val_manifest or manifest:
        sc_va, si_va = manifest_scenes(val_manifest, val_split, with_sensor=True) if val_manifest else manifest_scenes(manifest, "test", with_sensor=True)
        te = GeneratorWindows(sc_va, window, sims=si_va)
    else:
        te = GeneratorWindows(scene_pool(n_test_scenes, scene_seed, "test"), window)
    return OnTheFlyWindows(tr, length=train_items, seed=seed), OnTheFlyWindows(te, length=val_items, seed=seed + 10_000)
