"""Training windows sampled densely from stored spike groups (paper Sec. 3.5, supp. "Dense temporal sampling").

Each group is a 20 kHz spike stream (``spike_sim.store``, ``GROUP/spikes.h5``)
rather than a single image, so every simulator step can be the centre of a
training window.  :class:`StoreWindows` is a map-style ``torch`` dataset whose
item ``j`` is

* a window centre step ``c`` in a group (dense: every ``centre_every`` steps;
  or ``centres="output"``: only the stored output frames);
* the aligned stack ``{I(i+k), phi(i+k)}``, k = -K..K (N = 2K + 1 =
  ``cfg.n_obs``): observation k is centred on the step ``c_k`` where the
  calibrated (nominal) polarizer angle has turned by ``k * stride`` from its
  angle at step ``c`` (rounded to the nearest step, as
  :func:`spike_sim.aggregate.frame_centres` does for the output cadence), and

  ``I(i+k) = (1/dt) sum_{|n - c_k| <= h} S(n) / exposure``       paper Eq. (3)

  in radiance units (spikes per step divided by the group's exposure in
  thresholds per step per unit radiance; noise-free, ``I = L_M`` behind the
  polarizer); ``phi(i+k)`` is the window mean of the nominal angle, shifted by
  a whole number of pi so that the centre angle lies in [0, pi) (every
  quantity has period pi in phi);
* centre-frame ground truth ``T``, ``R``: the stored GT frames exist at the
  output cadence only (``/output/step_index``); at any other step they are
  **interpolated linearly in time** between the two stored frames around it
  (held at the ends), then rounded to float16 like the stored frames.  The
  stored frames are themselves linear between the source's keyframes, so
  this is exact whenever keyframes are no denser than the output cadence
  (343 FPS), and otherwise a linear approximation over at most 2.9 ms;
* ``zeta`` (N, H, W): paper Eq. (2) averaged over each observation's window
  at the *true* per-step angles (``/polarizer/phi_true_rad``), including the
  polarizer's rotation inside each step (sinc factor), i.e. the zeta that the
  spikes actually saw; and the coefficient maps ``R_perp``, ``R_par``,
  ``phi_perp``, ``T_perp``, ``T_par`` (H, W), from which zeta follows at any
  phi.  Groups without T maps get the lossless ``T = 1 - R``.

Items are built by :func:`reconstruct.net.onthefly.item_from_stream`, the code
that builds on-the-fly items, from the crop of the windows read here: the same
keys (``I``, ``phi``, ``T``, ``R``, ``zeta``, ``R_perp``, ``R_par``,
``phi_perp``, ``T_perp``, ``T_par``, ``exposure``), shapes and float32 dtypes,
so :func:`reconstruct.net.train.train` consumes either.  This module owns the
I/O: indexing, dense centres, crops, order, GT interpolation, lazy files.

Random crops (``cfg.crop`` square) and the order are seeded: item ``j`` is a
pure function of (seed, j) through ``np.random.default_rng([seed, j])``, and
with ``shuffle=True`` the index space is permuted by ``seed``.  Memory is
bounded: only the spike rows of the 2K + 1 windows (and, of those, the bytes
of the crop's image rows) and two GT frames are read per item; the HDF5 files
are opened lazily in each process (safe with ``DataLoader(num_workers > 0)``:
a forked worker reopens its own handles).  Reading a window inflates the
HDF5 chunk(s) holding it (``chunk_steps`` rows of whole frames), so each
handle keeps a chunk cache of ``cache_mb``.

This module reads stores only: it imports ``spike_sim`` (data layer) and never
``generator``.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import numpy as np
import torch

from polinfra.errors import ConfigError, DataFormatError
from reconstruct.net.onthefly import ITEM_KEYS, WindowConfig, item_from_stream, window_centres  # noqa: F401  (re-exported)
from reconstruct.stream.groups import list_groups

__all__ = ["StoreWindows", "GroupIndex", "window_centres", "open_window_datasets", "ITEM_KEYS"]

log = logging.getLogger(__name__)



class GroupIndex:
    """Per-group metadata read once (small arrays); spikes and GT stay on disk.

    Attributes:
        name, path (directory), h5 (spikes.h5 path), height, width, rate_hz,
        n_steps, exposure, window_steps, phi_nom, phi_true (T,), out_steps (M,),
        maps (dict of (H, W) float32), centres (valid dense centre steps).
    """

    def __init__(self, name: str, path: Path, cfg: WindowConfig, centres: str, centre_every: int):
        from spike_sim.store import open_group

        self.name, self.path = name, Path(path)
        with open_group(path) as g:
            self.h5 = Path(g.f.filename)
            self.height, self.width, self.rate_hz, self.n_steps = g.height, g.width, g.rate_hz, g.n_steps
            sim = g.json_attr("config_json") or {}
            self.exposure = float(sim.get("exposure", 1.0))
            self.phi_nom = np.asarray(g.phi_nominal_rad, dtype=np.float64)
            self.phi_true = np.asarray(g.phi_true_rad, dtype=np.float64)
            if not (g.has("gt/T") and g.has("gt/R") and g.has("output/step_index")):
                raise DataFormatError(f"{path}: no ground truth (gt/T, gt/R, output/step_index); training needs groups simulated from a source with layers")
            self.out_steps = np.asarray(g.array("output/step_index"), dtype=np.int64)
            self.maps = {k: np.asarray(v, dtype=np.float32) for k, v in g.maps().items()}
        missing = {"R_perp", "R_par", "phi_perp"} - set(self.maps)
        if missing:
            raise DataFormatError(f"{path}: coefficient maps {sorted(missing)} missing under /maps; zeta ground truth needs R_perp, R_par, phi_perp")
        self.maps.setdefault("T_perp", 1.0 - self.maps["R_perp"])
        self.maps.setdefault("T_par", 1.0 - self.maps["R_par"])
        if cfg.crop > min(self.height, self.width):
            raise ConfigError(f"crop = {cfg.crop} exceeds the {self.width}x{self.height} frames of group {name}; choose window.crop <= {min(self.height, self.width)}")
        self.window_steps = int(cfg.window_steps)
        h = self.window_steps // 2
        K = cfg.n_obs // 2
        stride = math.radians(cfg.stride_deg)
        self.mode = centres
        if centres == "output":
            # observation k of output frame i is the stored output frame i + k (the evaluation cadence)
            M = self.out_steps.size
            i = np.arange(K, max(K, M - K))
            fits = (self.out_steps[i - K] - h >= 0) & (self.out_steps[np.minimum(i + K, M - 1)] + h <= self.n_steps - 1)
            self.centres = self.out_steps[i[fits]]
            return
        else:
            cand = np.arange(0, self.n_steps, int(centre_every), dtype=np.int64)
        # a centre is valid when all 2K+1 windows lie inside the stream (angles inside the recorded range)
        ar = np.arange(self.n_steps, dtype=np.float64)
        ok = np.ones(cand.size, bool)
        for k in (-K, K):
            tgt = self.phi_nom[cand] + k * stride
            ok &= (tgt >= self.phi_nom[0]) & (tgt <= self.phi_nom[-1])
            c_k = np.rint(np.interp(tgt, self.phi_nom, ar)).astype(np.int64)
            ok &= (c_k - h >= 0) & (c_k + h <= self.n_steps - 1)
        cand = cand[ok & (cand - h >= 0) & (cand + h <= self.n_steps - 1)]
        self.centres = cand


def _resolve_groups(source, split: str | None) -> list[tuple[str, Path]]:
    if isinstance(source, (str, os.PathLike)):
        if split is None:
            root = Path(source)
            if (root / "spikes.h5").is_file():
                return [(root.name, root)]
            raise ConfigError(f"{root} is a dataset directory; choose a split (train/test)")
        return list_groups(source, split)
    out = []
    for s in source:
        p = Path(s)
        out.append((p.name, p))
    if not out:
        raise ConfigError("StoreWindows got an empty list of groups")
    return out


class StoreWindows(torch.utils.data.Dataset):
    """Dense sliding windows over stored spike groups (module docstring).

    Args:
        source: a dataset directory (``dataset.json`` as read by
            :func:`reconstruct.stream.groups.list_groups`), a group directory, or a
            sequence of group directories.
        cfg: window geometry (:class:`reconstruct.net.onthefly.WindowConfig`):
            ``n_obs`` (N = 2K + 1), ``crop`` (square side), ``window_steps``
            (Eq. (3) window dt in steps, odd), ``stride_deg`` (angle between
            observations).  The on-the-fly simulation fields are not
            used: stored spikes carry their own noise.
        split: split of a dataset directory ("train", "test", ...); None for a
            group directory or a list of groups.
        seed: seeds the crops and, with ``shuffle``, the order.
        centres: "dense" (every ``centre_every``-th step; observation centres
            from :func:`window_centres`) or "output" (the stored output
            frames only, observation k = stored frame i + k: the evaluation
            cadence of :func:`reconstruct.stream.groups.load_store_group`).
        centre_every: spacing of dense centres, steps (1 = every 50 us step).
        max_items: keep a seeded subset of this many windows (None = all).
        shuffle: permute the index space by ``seed``.
        crop: "random" (seeded per item) or "centre".
        cache_mb: HDF5 chunk cache per open group file, MiB.
    """

    def __init__(
        self,
        source: str | os.PathLike | Sequence[str | os.PathLike],
        cfg: WindowConfig = WindowConfig(),
        *,
        split: str | None = "train",
        seed: int = 0,
        centres: str = "dense",
        centre_every: int = 1,
        max_items: int | None = None,
        shuffle: bool = False,
        crop: str = "random",
        cache_mb: float = 64.0,
    ):
        if cfg.mean_steps:
            raise ConfigError("window.mean_steps (the long spike mean of a use_mean network) needs on-the-fly windows; stored windows read only the Eq. (3) steps; drop --data")
        if centres not in ("dense", "output"):
            raise ConfigError(f"centres = {centres!r}; choose 'dense' or 'output'")
        if crop not in ("random", "centre"):
            raise ConfigError(f"crop = {crop!r}; choose 'random' or 'centre'")
        if centre_every < 1:
            raise ConfigError(f"centre_every = {centre_every} must be >= 1 step")
        if cfg.n_obs % 2 == 0:
            raise ConfigError(f"n_obs = {cfg.n_obs} must be odd (N = 2K + 1)")
        if isinstance(source, (str, os.PathLike)) and (Path(source) / "spikes.h5").is_file():
            split = None
        self.cfg, self.seed, self.crop_mode, self.cache_mb = cfg, int(seed), crop, float(cache_mb)
        self.groups = [GroupIndex(n, p, cfg, centres, centre_every) for n, p in _resolve_groups(source, split)]
        counts = np.array([g.centres.size for g in self.groups], dtype=np.int64)
        if counts.sum() == 0:
            raise DataFormatError(f"no group holds a complete window of {cfg.n_obs} observations at {cfg.stride_deg} deg stride; use longer groups or fewer observations")
        self._offsets = np.concatenate([[0], np.cumsum(counts)])
        n = int(self._offsets[-1])
        order = np.arange(n, dtype=np.int64)
        if shuffle or (max_items is not None and max_items < n):
            order = np.random.default_rng([self.seed, 0x5EED]).permutation(n)
        if max_items is not None:
            if max_items < 1:
                raise ConfigError(f"max_items = {max_items} must be >= 1")
            order = order[: int(max_items)]
            if not shuffle:
                order = np.sort(order)
        self._order = order
        self._files: dict[int, h5py.File] = {}
        self._pid = None

    # -- index ----------------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self._order.size)

    def locate(self, index: int) -> tuple[int, int]:
        """(group number, centre step) of item ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(index)
        j = int(self._order[index])
        gi = int(np.searchsorted(self._offsets, j, side="right") - 1)
        return gi, int(self.groups[gi].centres[j - self._offsets[gi]])

    # -- lazy per-process files -----------------------------------------------------------------
    def _file(self, gi: int) -> dict[str, h5py.Dataset]:
        """Open handles of group ``gi`` in this process: the spike and GT datasets.

        The dataset objects are kept open: HDF5's chunk cache lives with an
        open dataset, so reopening per item would inflate a chunk every time.
        """
        if self._pid != os.getpid():  # new process (DataLoader worker): never reuse a parent's handles
            self._files = {}
            self._pid = os.getpid()
        h = self._files.get(gi)
        if h is None:
            f = h5py.File(self.groups[gi].h5, "r", rdcc_nbytes=int(self.cache_mb * 2**20), rdcc_nslots=10007)
            h = {"file": f, "spikes": f["spikes"], "T": f["gt/T"], "R": f["gt/R"]}
            self._files[gi] = h
        return h

    def close(self) -> None:
        """Close the open HDF5 handles of this process."""
        for h in self._files.values():
            h["file"].close()
        self._files = {}

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_files"], d["_pid"] = {}, None
        return d

    # -- items ----------------------------------------------------------------------------------
    def _crop_box(self, g: GroupIndex, rng: np.random.Generator) -> tuple[int, int]:
        S = self.cfg.crop
        if self.crop_mode == "centre":
            return (g.height - S) // 2, (g.width - S) // 2
        return int(rng.integers(0, g.height - S + 1)), int(rng.integers(0, g.width - S + 1))

    def _read_windows(self, f: dict[str, h5py.Dataset], g: GroupIndex, ck: np.ndarray, y0: int, x0: int) -> tuple[np.ndarray, int]:
        """The crop of the stream over the windows' span, (n, S, S) uint8, and its first step.

        Only the rows of the N windows [c_k - h, c_k + h] are read (and of each
        row only the bytes of the crop's image rows); the steps between windows
        stay zero (:func:`reconstruct.net.onthefly.item_from_stream` never reads them).
        """
        S, W, h = self.cfg.crop, g.width, g.window_steps // 2
        b0 = (y0 * W) // 8
        b1 = ((y0 + S) * W + 7) // 8
        off = y0 * W - 8 * b0
        ds = f["spikes"]
        r0, r1 = int(ck.min()) - h, int(ck.max()) + h + 1
        out = np.zeros((r1 - r0, S, S), np.uint8)
        for c in ck:
            raw = ds[c - h : c + h + 1, b0:b1]
            bits = np.unpackbits(raw, axis=1, bitorder="little")[:, off : off + S * W]
            out[c - h - r0 : c + h + 1 - r0] = bits.reshape(-1, S, W)[:, :, x0 : x0 + S]
        return out, r0

    def _gt(self, f: dict[str, h5py.Dataset], g: GroupIndex, c: int, sl) -> tuple[np.ndarray, np.ndarray]:
        """GT T, R at step c: linear in time between the stored output frames (held at the ends)."""
        s = g.out_steps
        j = int(np.searchsorted(s, c, side="right") - 1)
        if j < 0 or (j == s.size - 1) or s[j] == c:
            j = min(max(j, 0), s.size - 1)
            return tuple(f[n][j][sl].astype(np.float64) for n in ("T", "R"))
        w = (c - s[j]) / (s[j + 1] - s[j])
        return tuple((1 - w) * f[n][j][sl].astype(np.float64) + w * f[n][j + 1][sl].astype(np.float64) for n in ("T", "R"))

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        gi, c = self.locate(int(index))
        g = self.groups[gi]
        rng = np.random.default_rng([self.seed, int(index)])
        y0, x0 = self._crop_box(g, rng)
        S = self.cfg.crop
        sl = (slice(y0, y0 + S), slice(x0, x0 + S))
        f = self._file(gi)
        if g.mode == "output":
            i = int(np.searchsorted(g.out_steps, c))
            K = self.cfg.n_obs // 2
            ck = g.out_steps[i - K : i + K + 1]
        else:
            ck = window_centres(g.phi_nom, c, self.cfg.n_obs, math.radians(self.cfg.stride_deg))
        sub, r0 = self._read_windows(f, g, ck, y0, x0)
        r1 = r0 + sub.shape[0]
        maps = {k: g.maps[k][sl] for k in ("R_perp", "R_par", "phi_perp", "T_perp", "T_par")}
        # the item itself (Eq. (3) frames, angles, window-averaged Eq. (2) zeta, float16 GT) is built by the
        # code that builds on-the-fly items, so stored and on-the-fly items agree by construction
        return item_from_stream(sub, ck - r0, g.phi_nom[r0:r1], g.phi_true[r0:r1], self._gt(f, g, c, sl), maps, g.exposure, self.cfg)

    def describe(self) -> dict:
        """Plain-data summary (groups, windows per group, window steps)."""
        return {
            "groups": [{"name": g.name, "path": str(g.path), "windows": int(g.centres.size), "window_steps": g.window_steps} for g in self.groups],
            "items": len(self),
            "n_obs": self.cfg.n_obs,
            "crop": self.cfg.crop,
            "stride_deg": self.cfg.stride_deg,
        }


def _split_names(root: Path) -> set[str]:
    meta = root / "dataset.json"
    if not meta.is_file():
        return set()
    data = json.loads(meta.read_text())
    names = {str(g.get("split")) for g in data.get("groups", []) if isinstance(g, dict)}
    return names | set(data.get("splits", {}))


def open_window_datasets(data: str | os.PathLike, cfg, *, val_split: str | None = None) -> tuple[StoreWindows, StoreWindows]:
    """(train, validation) window sets of a built dataset for :func:`reconstruct.net.train.train`.

    Args:
        data: dataset directory with ``dataset.json``.
        cfg: a :class:`reconstruct.net.train.TrainConfig` (uses ``window``, ``seed``,
            ``train_items``, ``val_items``).
        val_split: split used for validation (default "val" when the dataset has
            one, else "test").

    Returns:
        Train windows: dense centres of the "train" split, at most ``train_items``
        (seeded subset); validation windows: ``val_items`` fixed windows with
        centre crops from ``val_split``.
    """
    root = Path(data)
    if val_split is None:
        val_split = "val" if "val" in _split_names(root) else "test"
    train_set = StoreWindows(root, cfg.window, split="train", seed=cfg.seed, max_items=cfg.train_items)
    val_set = StoreWindows(root, cfg.window, split=val_split, seed=cfg.seed + 10_000, max_items=cfg.val_items, crop="centre")
    return train_set, val_set
