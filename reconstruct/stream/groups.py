"""Evaluation inputs: a group's observation frames, angles, ground truth and pane maps.

Sources:

* a simulated group store (``spike_sim.store``, ``GROUP/spikes.h5``), aggregated
  here by paper Eq. (3) with any window / stride (:func:`load_store_group`);
* a dataset directory listing groups and their split (:func:`list_groups`);
* the in-process closed-form set of :mod:`reconstruct.stream.synthetic`.

Dataset layout accepted by :func:`list_groups` (paths relative to DATASET)::

    DATASET/dataset.json   {"groups": [{"name": "g000", "path": "groups/g000", "split": "test"}, ...]}
                       or  {"splits": {"train": ["groups/g000", ...], "test": [...]}}
    DATASET/<group>/spikes.h5 + group.json     (one spike_sim group store each)

A DATASET that is itself a group directory, or a directory of group
directories without dataset.json, is accepted too (every group is then used,
whatever the split).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
from pathlib import Path

import numpy as np

from polinfra.errors import ConfigError, DataFormatError
from reconstruct.physics.zeta import PaneMaps
from reconstruct.stream.window_inputs import WindowInputs, inputs_of

__all__ = ["EvalGroup", "list_groups", "load_store_group", "window_steps_from_ms", "spike_mean_frames", "SpikeMeanSums", "SPIKE_MEAN_MS", "spike_mean_steps", "spike_mean_span", "span_harmonic", "HARMONIC_RIDGE", "wide_window_steps", "window_means", "harmonic_design", "network_inputs"]

log = logging.getLogger(__name__)

@dataclasses.dataclass
class EvalGroup:
    """One group ready for evaluation; frame arrays are (M, H, W) float32 in radiance units.

    Attributes:
        name: group name.
        I: observations I(i) (radiance behind the polarizer).
        phi_nominal: (M,) calibrated window-mean polarizer angles, radians.
        phi_true: (M,) true window-mean angles, radians.
        span_rad: polarizer rotation during one aggregation window.
        T, R: GT layers at frame centres, or None.
        maps: pane maps (R_perp, R_par, phi_perp) or None; theta map in ``theta``.
        has_gt: (M,) bool, frames with ground truth.
    """

    name: str
    I: np.ndarray
    phi_nominal: np.ndarray
    phi_true: np.ndarray
    span_rad: float
    T: np.ndarray | None
    R: np.ndarray | None
    maps: PaneMaps | None
    theta: np.ndarray | None = None
    has_gt: np.ndarray | None = None
    gt_zeta: np.ndarray | None = None
    fov_deg: float | None = None
    """horizontal field of view of the camera (degrees) when known (a dataset group's scene), for ``--zeta self``"""
    source_dir: str | None = None
    """the stored group this was aggregated from (``--zeta self`` calibrates on all of its spikes), or None"""
    I_mean: np.ndarray | None = None
    """(M, H, W) the plain spike mean: spikes per step / exposure over :data:`SPIKE_MEAN_MS` centred on each
    frame (clipped to the stream), the "doing nothing" baseline of issue 16 (2 x it estimates T + zbar (R - T))"""
    I_wide: np.ndarray | None = None
    """(M, H, W) Eq. (3) frames at the same centres over the wide window (:func:`wide_window_steps`: the whole
    stride, so the N windows of an output tile its span), radiance units; read by a network with ``NetConfig.wide_input``"""
    I_harm: np.ndarray | None = None
    """(M, 2, H, W) the first harmonic (cos 2 phi, sin 2 phi) of the spikes over the same spans, radiance units
    (:func:`span_harmonic`; a ``use_harm`` network's input)"""
    exposure: float | None = None
    """the stream's exposure (spikes per step per unit radiance; I x exposure = spikes per step), when known"""
    span_steps: int | None = None
    """steps of I_mean's span (:func:`spike_mean_steps`), when known; with ``exposure``, the span's noise and
    saturation a ``span_level`` network weighs"""


def network_inputs(group: EvalGroup, model, I, phi, centres, K: int, crop: tuple[slice, slice] = (slice(None), slice(None))) -> WindowInputs:
    """Windows ``I`` (B, N, H, W), ``phi`` (B, N) of the output frames at ``centres`` of a group, with the long span that
    ``model`` reads beside them (``model.cfg.inputs``: I_mean, I_harm, I_wide, exposure, span_steps), each window's
    N = 2K + 1 frames around its centre, cropped to ``crop`` (rows, columns); ConfigError naming what the
    group lacks (only stored groups and the synthetic set carry the long span).
    """
    need = inputs_of(model)
    for name, have, what in (("I_mean", group.I_mean, "the long spike mean"), ("I_harm", group.I_harm, "the long span's first harmonic"),
                             ("I_wide", group.I_wide, "the observations over the wide window"), ("exposure", group.exposure, "the stream's exposure"),
                             ("span_steps", group.span_steps, "the long span's length")):
        if name in need and have is None:
            raise ConfigError(f"group {group.name}: the network takes {what}, which only stored groups (spikes.h5) and synthetic groups give; evaluate it on a built dataset")
    ys, xs = crop
    kw: dict = {}
    if "I_mean" in need:
        kw["I_mean"] = np.stack([group.I_mean[i][ys, xs] for i in centres])
    if "I_harm" in need:
        kw["I_harm"] = np.stack([group.I_harm[i][:, ys, xs] for i in centres])
    if "I_wide" in need:
        kw["I_wide"] = np.stack([group.I_wide[i - K : i + K + 1][:, ys, xs] for i in centres])
    if "exposure" in need:
        kw["exposure"] = group.exposure
    if "span_steps" in need:
        kw["span_steps"] = group.span_steps
    return WindowInputs(I, phi, **kw)


SPIKE_MEAN_MS = 17.5
"""Span of the plain spike-mean baseline (about half a polarizer turn at 30 rev/s: the modulation averages out)."""


def wide_window_steps(rate_hz: float, rev_per_s: float, stride_deg: float) -> int:
    """Steps of the wide window: the largest odd count within one stride between output frames (57 at 20 kHz,
    30 rev/s, 31.5 deg), so the N wide windows of an output use every spike between their centres without overlap
    (1 for a still polarizer or a stride shorter than two steps).
    """
    if rev_per_s <= 0:
        return 1
    s = int(math.floor(stride_deg / 360.0 / rev_per_s * rate_hz))
    return max(1, s if s % 2 else s - 1)


def window_means(read, centres: np.ndarray, widths: tuple[int, ...], n_steps: int, exposure: float) -> tuple[np.ndarray, ...]:
    """For each odd width in ``widths``: spikes per step / exposure over that many steps centred on each of ``centres``,
    clipped to a stream of ``n_steps`` (the count divided by the clipped length): paper Eq. (3) frames at the 0.65 ms
    window and the wide window alike.  ``read(n0, n1)`` returns the (n1 - n0, H, W) spikes; each centre's widest
    span is read once and the narrower windows are its centre slices.
    """
    halves = [int(w) // 2 for w in widths]
    reach = max(halves)
    out: list[list[np.ndarray]] = [[] for _ in widths]
    for c in np.asarray(centres, np.int64):
        c = int(c)
        lo0 = max(0, c - reach)
        part = read(lo0, min(n_steps, c + reach + 1))
        for o, h in zip(out, halves):
            lo, hi = max(0, c - h), min(n_steps, c + h + 1)
            o.append(part[lo - lo0 : hi - lo0].sum(0, dtype=np.int32) / np.float32(max(hi - lo, 1) * exposure))
    return tuple(np.asarray(o, np.float32) for o in out)


def spike_mean_steps(rate_hz: float) -> int:
    """Steps of the :data:`SPIKE_MEAN_MS` span at ``rate_hz`` (350 at 20 kHz; at least 1)."""
    return max(1, int(round(SPIKE_MEAN_MS * 1e-3 * rate_hz)))


def span_part_edges(L: int, n_sub: int) -> list[tuple[int, int]]:
    """[lo, hi) step ranges of ``n_sub`` consecutive parts of a span of ``L`` steps (sizes differ by at most one)."""
    n = max(1, min(int(n_sub), int(L)))
    edges = np.linspace(0, L, n + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def spike_mean_span(centre, steps: int, n_steps: int):
    """Steps [lo, hi) of the long spike mean of ``steps`` steps centred on step ``centre`` (scalar or array), clipped
    to a stream of ``n_steps``: the one span of the stream reconstructor, the stored groups and the training items.
    """
    return np.clip(centre - steps // 2, 0, n_steps), np.clip(centre + steps // 2 + 1, 0, n_steps)


class SpikeMeanSums:
    """Spike counts of a stream up to the boundaries the long spike means need, kept only until used.

    The mean of frame j covers steps [centre_j - L // 2, centre_j + L // 2 + 1) clipped to the stream. Chunks are
    fed in order (from any step up to the first boundary; earlier steps are skipped) and each boundary's running
    count is snapshotted once: a stream reconstructor (:func:`reconstruct.video.stream.reconstruct_stream`) and a stored
    group (:func:`spike_mean_frames`) share this one count.

    Given the per-step polarizer angles ``phi_step`` (radians, the reconstructor's nominal ones), the sums weighted
    by cos 2 phi and sin 2 phi are kept too, and :meth:`harmonic` gives the first harmonic of each span's spikes
    (:func:`span_harmonic`; :func:`reconstruct.physics.span.long_span_separation` reads it).
    """

    def __init__(self, centres: np.ndarray, steps: int, n_steps: int, shape: tuple[int, int], phi_step: np.ndarray | None = None, n_sub: int = 1):
        self.lo, self.hi = spike_mean_span(np.asarray(centres, np.int64), steps, n_steps)
        self.n_sub = int(n_sub)
        if self.n_sub > 1 and phi_step is None:
            raise DataFormatError("SpikeMeanSums with parts (n_sub > 1) needs the per-step angles (phi_step)")
        edges = set(self.lo.tolist()) | set(self.hi.tolist())
        if self.n_sub > 1:  # each span's part boundaries too (span_part_edges)
            for lo, hi in zip(self.lo.tolist(), self.hi.tolist()):
                edges |= {lo + a for a, _ in span_part_edges(hi - lo, self.n_sub)}
        self.want = sorted(edges)
        self.snap: dict[int, np.ndarray] = {}
        self.phi = None if phi_step is None else np.asarray(phi_step, np.float64)
        if self.phi is not None and self.phi.size < n_steps:
            raise DataFormatError(f"phi_step has {self.phi.size} angles for a stream of {n_steps} steps")
        self.acc = np.zeros(shape if self.phi is None else (3, *shape), np.float64 if self.phi is not None else np.int64)
        self.pos = self.want[0] if self.want else 0  # acc = spikes of steps [first boundary, pos)
        self.wi = 0

    def _add(self, s0: int, part: np.ndarray) -> None:
        """Add the spikes of steps s0 .. s0 + len(part) to the running sums."""
        if self.phi is None:
            self.acc += part.sum(0, dtype=np.int64)
            return
        if not part.shape[0]:
            return
        p = 2.0 * self.phi[s0 : s0 + part.shape[0]]
        harmonic_accumulate(self.acc, part, np.cos(p), np.sin(p))

    def feed(self, s0: int, chunk: np.ndarray) -> None:
        """The next chunk of spikes (steps s0 .. s0 + len); chunks arrive in order without gaps."""
        if s0 + chunk.shape[0] <= self.pos:
            return
        if s0 > self.pos:
            raise DataFormatError(f"spike chunks must arrive without gaps: expected step {self.pos}, got {s0}")
        chunk = chunk[self.pos - s0 :]
        s0 = self.pos
        end = s0 + chunk.shape[0]
        while self.wi < len(self.want) and self.want[self.wi] <= end:
            b = self.want[self.wi]
            self._add(self.pos, chunk[self.pos - s0 : b - s0])
            self.pos = b
            self.snap[b] = self.acc.copy()
            self.wi += 1
        self._add(self.pos, chunk[self.pos - s0 :])
        self.pos = end

    def _span(self, j: int) -> tuple[int, int, np.ndarray]:
        lo, hi = int(self.lo[j]), int(self.hi[j])
        if hi not in self.snap:  # the stream ended early or is not fed that far yet: up to where it is
            hi = self.pos
            self.snap[hi] = self.acc.copy()
        return lo, hi, self.snap[hi] - self.snap[lo]

    def _free(self, lo: int) -> None:
        for k in [k for k in self.snap if k < lo]:
            del self.snap[k]

    def mean(self, j: int, exposure: float = 1.0) -> np.ndarray:
        """Spikes per step / exposure around frame j (frames taken in order); frees older snapshots."""
        lo, hi, d = self._span(j)
        m = (d if self.phi is None else d[0]) / np.float32(max(hi - lo, 1) * exposure)
        self._free(lo)
        return m.astype(np.float32)

    def part_sums(self, j: int) -> tuple[np.ndarray, list[tuple[int, int]]]:
        """The spike sums (weighted by 1, cos 2 phi, sin 2 phi) of the ``n_sub`` parts of frame j's span, (n, 3, H, W),
        and the parts' absolute [lo, hi) steps; call before :meth:`mean` of the same frame.
        """
        lo, hi, _ = self._span(j)
        parts = [(lo + a, lo + b) for a, b in span_part_edges(hi - lo, self.n_sub)]
        return np.stack([self.snap[b] - self.snap[a] for a, b in parts]), parts

    def release(self, j: int) -> None:
        """Free the snapshots frame j and later frames no longer need (frames taken in order; :meth:`mean` does it too)."""
        self._free(int(self.lo[j]))

    def harmonic(self, j: int, exposure: float = 1.0) -> np.ndarray:
        """(2, H, W) first-harmonic coefficients of the spikes around frame j (:func:`span_harmonic`); call before
        :meth:`mean` of the same frame (which frees older snapshots); needs ``phi_step``.
        """
        if self.phi is None:
            raise DataFormatError("SpikeMeanSums.harmonic needs the per-step angles (phi_step)")
        lo, hi, d = self._span(j)
        return span_harmonic(d, self.phi[lo:hi], exposure)


def _harmonic_accumulate_py(acc, part, c, s):  # pragma: no cover - compiled by numba below; kept plain for reading
    t, H, W = part.shape
    for y in range(H):
        a0, a1, a2 = acc[0, y], acc[1, y], acc[2, y]  # three float64 rows stay in the L1 cache over the steps
        for k in range(t):
            ck, sk, row = c[k], s[k], part[k, y]
            for x in range(W):
                v = np.float64(row[x])
                a0[x] += v
                a1[x] += ck * v
                a2[x] += sk * v


@functools.cache
def _harmonic_kernel():
    import numba

    return numba.njit(cache=True, nogil=True, error_model="numpy")(_harmonic_accumulate_py)


def harmonic_accumulate(acc: np.ndarray, part: np.ndarray, cos2: np.ndarray, sin2: np.ndarray) -> None:
    """``acc`` (3, H, W) float64 += the spikes ``part`` (t, H, W) summed over the steps with weights 1, ``cos2``,
    ``sin2`` (t,) (cos and sin of 2 phi per step): the sums :func:`span_harmonic` reads, in float64 and in step order
    per pixel, by one numba pass over the spikes as they come (no float copies of the chunk).
    """
    _harmonic_kernel()(acc, np.ascontiguousarray(part), np.ascontiguousarray(cos2, np.float64), np.ascontiguousarray(sin2, np.float64))


def harmonic_design(phi: np.ndarray) -> np.ndarray:
    """(3, t) rows 1, cos 2 phi, sin 2 phi of per-step angles ``phi`` (radians): the first-harmonic design whose
    products with a span's spikes :func:`span_harmonic` takes.
    """
    p = 2.0 * np.asarray(phi, np.float64)
    return np.stack([np.ones_like(p), np.cos(p), np.sin(p)])


HARMONIC_RIDGE = 1e-6
"""Ridge (relative to the span's steps) on the cos / sin coefficients of :func:`span_harmonic`: a span too short to
see the harmonic (a still polarizer) gets b = c = 0."""


def span_harmonic(sums: np.ndarray, phi: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """First harmonic of a span's spikes: the least-squares (b, c) of s_t ~ a + b cos 2 phi_t + c sin 2 phi_t per pixel.

    Args:
        sums: (3, H, W) the span's spike sums weighted by 1, cos 2 phi_t, sin 2 phi_t.
        phi: (t,) the span's per-step angles (radians).
        exposure: the stream's exposure (the result is in radiance units, as I_mean).

    Returns:
        (2, H, W) float32 (b, c).
    """
    X = harmonic_design(phi)
    if X.shape[1] == 0:
        return np.zeros((2, *sums.shape[1:]), np.float32)
    G = X @ X.T + HARMONIC_RIDGE * X.shape[1] * np.diag([0.0, 1.0, 1.0])
    coef = (np.linalg.solve(G, np.eye(3)) @ sums.reshape(3, -1)).reshape(sums.shape)  # one 3 x 3 inverse for every pixel
    return (coef[1:] / exposure).astype(np.float32)


def spike_mean_frames(g, centres: np.ndarray, span_steps: int, exposure: float, chunk_steps: int = 2048, harmonic: bool = False):
    """Spikes per step / exposure over ``span_steps`` steps centred on each of ``centres`` (ascending), clipped to
    the stream, of an open ``spike_sim.store`` group: :class:`SpikeMeanSums` fed with the steps from the first
    frame's span to the last's, each read once; a mean is taken as soon as its span is read.  ``harmonic``: also
    the spans' first harmonics at the group's nominal angles, returning (means (M, H, W), harmonics (M, 2, H, W)).
    """
    sums = SpikeMeanSums(centres, span_steps, g.n_steps, (g.height, g.width), g.phi_nominal_rad if harmonic else None)
    out = np.zeros((len(centres), g.height, g.width), np.float32)
    harm = np.zeros((len(centres), 2, g.height, g.width), np.float32) if harmonic else None
    j = 0

    def take(j):
        if harm is not None:
            harm[j] = sums.harmonic(j, exposure)
        out[j] = sums.mean(j, exposure)

    if sums.want:
        for n0 in range(sums.want[0], sums.want[-1], chunk_steps):
            sums.feed(n0, g.read(n0, min(sums.want[-1], n0 + chunk_steps)))
            while j < len(centres) and sums.hi[j] <= sums.pos:
                take(j)
                j += 1
    while j < len(centres):  # empty spans only (a frame at the stream's very edge)
        take(j)
        j += 1
    return (out, harm) if harmonic else out


def window_steps_from_ms(dt_ms: float, rate_hz: float) -> int:
    """Aggregation window in steps: the odd integer nearest to dt * rate (ties round up).

    Eq. (3) windows are centred on a step, so their length is odd: 0.65 ms at
    20 kHz -> 13, 0.30 ms -> 7 (6 rounded up to odd), 1.10 ms -> 23.
    """
    x = round(dt_ms * 1e-3 * rate_hz, 9)
    lo = int(np.floor((x - 1) / 2)) * 2 + 1
    lo = max(lo, 1)
    hi = lo + 2
    return lo if abs(x - lo) < abs(hi - x) else hi


def _is_group(p: Path) -> bool:
    return (p / "spikes.h5").is_file()


def list_groups(dataset: str | os.PathLike, split: str = "test") -> list[tuple[str, Path]]:
    """(name, group directory) of every group of ``split`` in a dataset (layout in the module docstring)."""
    root = Path(dataset)
    if not root.exists():
        raise DataFormatError(f"dataset {root} does not exist; give a dataset directory, a group directory, or 'synthetic'")
    if _is_group(root):
        return [(root.name, root)]
    meta = root / "dataset.json"
    if meta.is_file():
        data = json.loads(meta.read_text())
        out: list[tuple[str, Path]] = []
        if "groups" in data:
            for g in data["groups"]:
                if isinstance(g, dict) and g.get("split", split) == split:
                    p = root / g["path"]
                    out.append((str(g.get("name", p.name)), p))
        elif "splits" in data or split in data:
            for rel in (data.get("splits", data).get(split) or []):
                rel = rel["path"] if isinstance(rel, dict) else rel
                out.append((Path(rel).name, root / rel))
        else:
            raise DataFormatError(f"{meta}: expected a 'groups' list or a 'splits' table; found keys {sorted(data)}")
        if not out:
            raise DataFormatError(f"{meta} lists no groups in split {split!r}; choose another --split")
        return out
    groups = sorted(p for p in root.iterdir() if p.is_dir() and _is_group(p))
    if not groups:
        raise DataFormatError(f"{root} has no dataset.json and no group directories (GROUP/spikes.h5); build or simulate a dataset first")
    log.warning("%s has no dataset.json: using all %d groups regardless of split", root, len(groups))
    return [(p.name, p) for p in groups]


def load_store_group(
    path: str | os.PathLike,
    window_steps: int = 13,
    stride_deg: float = 31.5,
    n_obs: int = 7,
    max_frames: int = 0,
    name: str | None = None,
) -> EvalGroup:
    """Aggregate a stored spike group into Eq. (3) frames in radiance units, with its GT.

    Args:
        path: group directory (``spikes.h5`` inside).
        window_steps: aggregation window in steps (odd).
        stride_deg: polarizer rotation between output frames.
        n_obs: observations per output, only to validate the configuration.
        max_frames: keep only the first ``max_frames`` frames (0 = all).
        name: display name (default: the directory name).

    Returns:
        :class:`EvalGroup`.  I = spikes per step / exposure; GT frames exist where a
        frame centre coincides with a stored output step (the group's own cadence).
    """
    from reconstruct.stream.groups import fov_from_group_dir
    from spike_sim.aggregate import AggregateConfig, frame_centres
    from spike_sim.store import open_group

    cfg = AggregateConfig(window_steps=window_steps, stride_deg=stride_deg, n_obs=n_obs)
    with open_group(path) as g:
        sim = g.json_attr("config_json") or {}
        pol = g.json_attr("polarizer_json") or {}
        exposure = float(sim.get("exposure", 1.0))
        pol_rate = float(pol.get("rate_hz", 30.0))
        phi_nom = g.phi_nominal_rad
        phi_tr = g.phi_true_rad
        # the simulator places its centres (and stores the GT there) from its clock's angle at t = 0, the nominal
        # phase; the same start here gives the same centres to the bit (extrapolating it from the first two steps
        # differs by float noise, and every third centre sits on a half step at 30 rev/s and 20 kHz)
        phi_start = float(np.deg2rad(pol["phase_deg"])) if "phase_deg" in pol else None
        c, phi_i = frame_centres(phi_nom, cfg, phi_start_rad=phi_start)
        if max_frames:
            c, phi_i = c[:max_frames], phi_i[:max_frames]
        if c.size == 0:
            raise DataFormatError(f"{path}: the stream ({g.n_steps} steps) holds no complete {window_steps}-step window")
        h = cfg.half
        csum = np.concatenate([[0.0], np.cumsum(phi_tr)])
        phi_t = (csum[c + h + 1] - csum[c - h]) / window_steps
        # Eq. (3) frames and the wide windows at the same centres, each centre's spikes read once
        I, I_wide = window_means(g.read, c, (window_steps, wide_window_steps(g.rate_hz, pol_rate, stride_deg)), g.n_steps, exposure)
        has = np.zeros(c.size, bool)
        T = R = None
        if g.has("output/step_index") and g.has("gt/T"):
            idx = {int(s): j for j, s in enumerate(g.array("output/step_index"))}
            T = np.zeros_like(I)
            R = np.zeros_like(I)
            for m, cc in enumerate(c):
                j = idx.get(int(cc))
                if j is not None:
                    has[m] = True
                    T[m] = g.gt_frame("T", j)
                    if g.has("gt/R"):
                        R[m] = g.gt_frame("R", j)
            if not has.any():
                log.warning("%s: no frame centre matches a stored GT output step; choose the group's own stride/window", path)
        span_mean = spike_mean_steps(g.rate_hz)
        I_mean, I_harm = spike_mean_frames(g, c, span_mean, exposure, harmonic=True)
        mp = g.maps()
        maps = None
        if {"R_perp", "R_par", "phi_perp"} <= set(mp):
            maps = PaneMaps(R_perp=mp["R_perp"], R_par=mp["R_par"], phi_perp=mp["phi_perp"])
        span = 2 * np.pi * pol_rate * window_steps / g.rate_hz
        return EvalGroup(
            name=name or Path(path).name,
            I=I,
            phi_nominal=phi_i,
            phi_true=phi_t,
            span_rad=float(span),
            T=T,
            R=R,
            maps=maps,
            theta=mp.get("theta"),
            has_gt=has,
            fov_deg=fov_from_group_dir(path),
            source_dir=str(path),
            I_mean=I_mean,
            I_harm=I_harm,
            I_wide=I_wide,
            exposure=exposure,
            span_steps=span_mean,
        )


def fov_from_group_dir(path) -> float | None:
    """Horizontal field of view (degrees) recorded in a dataset group's ``group_spec.json`` (scene.camera.fov_deg), else None."""
    p = Path(path) / "group_spec.json"
    try:
        doc = json.loads(p.read_text())
        return float(doc["scene"]["camera"]["fov_deg"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
