"""Chunked group store: one simulated spike group with its ground truth, in HDF5.

Why HDF5 (h5py) rather than zarr: one self-describing file per group (easy to
copy, checksum and list in a dataset manifest, atomic to publish by a single
rename), chunked and compressed datasets with lazy slicing, a standard deflate
filter readable from any language (C, MATLAB, Julia) without our code, and
h5py is already a dependency.  zarr's many small files are a better fit for
concurrent writers to ONE array, which we never need: a group is written by one
process, start to end.

Layout of ``GROUP/spikes.h5`` (format ``polspike-spikes/1``)::

    /spikes                (T, ceil(H W / 8)) uint8   bit-packed upright frames, LSB first per frame
                                                      (np.packbits(frame.ravel(), bitorder="little")),
                                                      chunked (chunk_steps, bytes), deflate level 1
    /polarizer/phi_true_rad     (T,) float64   true mid-step polarizer angle (offset, wobble, jitter)
    /polarizer/phi_nominal_rad  (T,) float64   calibrated angle a reconstructor assumes
    /time/step_mid_s            (T,) float64   mid-step timestamps
    /output/step_index          (M,) int64     centre step of each Eq. (3) output frame
    /output/times_s             (M,) float64   its time
    /output/phi_nominal_rad     (M,) float64   centre angle phi(i) (nominal), /output/phi_true_rad the true one
    /gt/T, /gt/R                (M, H, W) float16   GT layers at output times, linear in time between
                                                    keyframes (when the source has them; float16 keeps
                                                    3 significant digits and halves the largest part)
    /gt/zeta                    (M, H, W) float16   optional: paper Eq. (2) zeta at the true centre angle
    /maps/<name>                (H, W) float32       coefficient maps (theta, phi_perp, R_perp, R_par, T_perp, T_par)
    attrs: format, width, height, rate_hz, n_steps, seed, scene_hash, config_json, polarizer_json, aggregate_json

Byte layout.  The file is written the same way every time: no object timestamps
(``track_times=False`` on every dataset and group), a pinned file-format range
(:data:`LIBVER`, so a newer HDF5 library does not silently switch to newer object
headers), attributes in the order the writer sets them, chunks written in order.
The same inputs therefore give the same bytes; wall-clock timings do not belong in
the file (``simulate(..., store_timings=False)`` leaves them out of ``summary_json``).

Everything is written to a temporary file beside the final one and renamed when
complete (:class:`GroupWriter`), then ``GROUP/group.json`` (plain-data summary)
is written atomically: a group without group.json is incomplete.
Spike chunks are deflated on a thread pool (zlib releases the GIL) and stored
with HDF5 direct chunk writes, so compression overlaps the simulation.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
import zlib
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from polinfra.atomic import atomic_path, ensure_dir, finish_atomic, write_json
from polinfra.errors import DataFormatError, OutputError, ShapeError

__all__ = ["GroupWriter", "SpikeGroup", "open_group", "FORMAT", "SPIKES_FILE", "SUMMARY_FILE"]

FORMAT = "polspike-spikes/1"
SPIKES_FILE = "spikes.h5"
SUMMARY_FILE = "group.json"
_DEFLATE = 1  # zlib level: 30 % smaller than raw bits at ~100 MB/s per thread
LIBVER = ("earliest", "v110")
"""HDF5 file-format bounds (pinned: part of the byte layout)."""


class GroupWriter:
    """Write one group sequentially; publish it atomically on :meth:`close`.

    Args:
        group_dir: output folder (created); refuses an existing complete group
            unless ``overwrite``.
        height, width, rate_hz, n_steps: stream geometry.
        chunk_steps: HDF5 chunk length in steps.
        compression: "gzip" (deflate level 1, default), or "none".
        attrs: extra root attributes (plain data; dicts are stored as JSON).
        overwrite: replace an existing group.
    """

    def __init__(
        self,
        group_dir: str | os.PathLike,
        height: int,
        width: int,
        rate_hz: float,
        n_steps: int,
        chunk_steps: int = 1000,
        compression: str = "gzip",
        attrs: dict[str, Any] | None = None,
        overwrite: bool = False,
    ):
        self.dir = Path(group_dir)
        if (self.dir / SUMMARY_FILE).exists() and not overwrite:
            raise OutputError(f"{self.dir} already holds a spike group; pass --overwrite to replace it or choose another --out")
        if compression not in ("gzip", "none"):
            raise OutputError(f"unknown compression {compression!r}; choose 'gzip' or 'none'")
        ensure_dir(self.dir)
        (self.dir / SUMMARY_FILE).unlink(missing_ok=True)
        self.height, self.width, self.n_steps = int(height), int(width), int(n_steps)
        self.nbytes = (self.height * self.width + 7) // 8
        self.chunk_steps = max(1, min(int(chunk_steps), max(1, self.n_steps)))
        self.compression = compression
        self._ctx = atomic_path(self.dir / SPIKES_FILE, suffix=".h5")
        self._tmp = self._ctx.__enter__()
        self.f = h5py.File(self._tmp, "w", libver=LIBVER, track_order=False)
        kw: dict[str, Any] = {"compression": "gzip", "compression_opts": _DEFLATE} if compression == "gzip" else {}
        self.spikes = self.f.create_dataset("spikes", shape=(self.n_steps, self.nbytes), dtype="u1", chunks=(self.chunk_steps, self.nbytes), track_times=False, **kw)
        a = self.f.attrs
        a["format"] = FORMAT
        a["width"], a["height"], a["rate_hz"], a["n_steps"] = self.width, self.height, float(rate_hz), self.n_steps
        a["bit_order"] = "little"
        a["orientation"] = "upright (row 0 = top); .dat files store rows flipped"
        for k, v in (attrs or {}).items():
            self.set_attr(k, v)
        self._buf = np.zeros((self.chunk_steps, self.nbytes), np.uint8)
        self._fill = 0
        self._next_chunk = 0
        self.written = 0
        self._pool = cf.ThreadPoolExecutor(max_workers=2) if compression == "gzip" else None
        self._pending: deque = deque()

    def set_attr(self, key: str, value: Any) -> None:
        """Store a root attribute; dicts/lists as JSON text."""
        self.f.attrs[key] = json.dumps(value) if isinstance(value, (dict, list, tuple)) else value

    def write_spikes(self, packed: np.ndarray) -> None:
        """Append packed frames (t, ceil(H W / 8)) uint8, in order."""
        if packed.ndim != 2 or packed.shape[1] != self.nbytes:
            raise ShapeError(f"packed frames must be (t, {self.nbytes}), got {packed.shape}", packed.shape, f"(t, {self.nbytes})")
        if self.written + len(packed) > self.n_steps:
            raise OutputError(f"too many frames: {self.written + len(packed)} > declared {self.n_steps}")
        i = 0
        while i < len(packed):
            m = min(self.chunk_steps - self._fill, len(packed) - i)
            self._buf[self._fill : self._fill + m] = packed[i : i + m]
            self._fill += m
            i += m
            if self._fill == self.chunk_steps:
                self._flush_chunk()
        self.written += len(packed)

    def _flush_chunk(self) -> None:
        c = self._next_chunk
        data = self._buf.copy()
        if self._pool is None:
            n = min(self.chunk_steps, self.n_steps - c * self.chunk_steps)
            self.spikes[c * self.chunk_steps : c * self.chunk_steps + n] = data[:n]
        else:
            self._submit(self.spikes, (c * self.chunk_steps, 0), data)
        self._next_chunk += 1
        self._fill = 0
        self._buf[:] = 0

    def _submit(self, dset: h5py.Dataset, offset: tuple, chunk: np.ndarray) -> None:
        """Deflate one whole chunk on the pool; write it (in order) once done."""
        self._pending.append((dset, offset, self._pool.submit(zlib.compress, np.ascontiguousarray(chunk).tobytes(), _DEFLATE)))
        while len(self._pending) > 4:
            self._drain_one()

    def _drain_one(self) -> None:
        dset, offset, fut = self._pending.popleft()
        dset.id.write_direct_chunk(offset, fut.result())

    def write_frame(self, dset: h5py.Dataset, i: int, frame: np.ndarray) -> None:
        """Write frame ``i`` of a dataset made by :meth:`create_frames` (compressed on the pool)."""
        arr = np.asarray(frame, dtype=dset.dtype).reshape(1, self.height, self.width)
        if self._pool is None:
            dset[i] = arr[0]
        else:
            self._submit(dset, (i, 0, 0), arr)

    def write_array(self, name: str, data: np.ndarray, compress: bool = False, chunks: tuple | None = None) -> h5py.Dataset:
        """Write a whole dataset ``name`` (paths with '/' create groups)."""
        kw: dict[str, Any] = {"compression": "gzip", "compression_opts": _DEFLATE} if compress else {}
        if chunks is not None:
            kw["chunks"] = chunks
        return self._parent(name).create_dataset(name.rsplit("/", 1)[-1], data=np.asarray(data), track_times=False, **kw)

    def _parent(self, name: str) -> h5py.Group:
        """The group holding dataset ``name``, its missing ancestors created without timestamps."""
        g = self.f
        for part in name.strip("/").split("/")[:-1]:
            if part not in g:
                gcpl = h5py.h5p.create(h5py.h5p.GROUP_CREATE)
                gcpl.set_obj_track_times(False)
                h5py.h5g.create(g.id, part.encode(), gcpl=gcpl)
            g = g[part]
        return g

    def create_frames(self, name: str, n: int, dtype="f4") -> h5py.Dataset:
        """Create an (n, H, W) dataset chunked per frame, compressed (fill it by index)."""
        return self._parent(name).create_dataset(
            name.rsplit("/", 1)[-1], shape=(n, self.height, self.width), dtype=dtype, chunks=(1, self.height, self.width),
            compression="gzip", compression_opts=_DEFLATE, track_times=False,
        )

    def flush_pending(self) -> None:
        """Wait for every compressed chunk and write it."""
        while self._pending:
            self._drain_one()

    def close(self, summary: dict[str, Any] | None = None, ok: bool = True) -> Path:
        """Finish: flush, rename spikes.h5 into place, write group.json (or discard on failure)."""
        try:
            if ok:
                if self.written != self.n_steps:
                    raise OutputError(f"group incomplete: wrote {self.written} of {self.n_steps} steps")
                if self._fill:
                    self._flush_chunk()
                while self._pending:
                    self._drain_one()
        except BaseException:
            ok = False
            raise
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=not ok)
            self.f.close()
            finish_atomic(self._ctx, ok)
        write_json(self.dir / SUMMARY_FILE, {"format": FORMAT, "complete": True, **(summary or {})})
        return self.dir


class SpikeGroup:
    """Read-only access to a group; spikes are read lazily by time range.

    Attributes:
        path, n_steps, height, width, rate_hz, dt_s, seed, scene_hash, attrs, summary.
    """

    def __init__(self, group_dir: str | os.PathLike):
        p = Path(group_dir)
        h5 = p / SPIKES_FILE if p.is_dir() else p
        if not h5.is_file():
            raise DataFormatError(f"{p} is not a spike group (no {SPIKES_FILE}); run `polspike simulate` first")
        self.path = p
        try:
            self.f = h5py.File(h5, "r")
        except OSError as exc:
            raise DataFormatError(f"{h5} is not a readable HDF5 file ({exc})") from None
        a = self.f.attrs
        if a.get("format") != FORMAT:
            raise DataFormatError(f"{h5}: unknown format {a.get('format')!r}; expected {FORMAT!r}")
        self.attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in a.items()}
        self.n_steps = int(a["n_steps"])
        self.height, self.width = int(a["height"]), int(a["width"])
        self.rate_hz = float(a["rate_hz"])
        self.dt_s = 1.0 / self.rate_hz
        self.seed = int(a.get("seed", -1))
        self.scene_hash = str(a.get("scene_hash", ""))
        sp = p / SUMMARY_FILE if p.is_dir() else p.parent / SUMMARY_FILE
        self.summary = json.loads(sp.read_text()) if sp.is_file() else {}

    def json_attr(self, key: str) -> Any:
        """A root attribute stored as JSON (config_json, polarizer_json, aggregate_json)."""
        v = self.f.attrs.get(key)
        return None if v is None else json.loads(v)

    def read_packed(self, n0: int, n1: int) -> np.ndarray:
        """Packed frames of steps [n0, n1), (n, ceil(H W / 8)) uint8."""
        n0, n1 = max(0, int(n0)), min(self.n_steps, int(n1))
        return self.f["spikes"][n0:n1]

    def read(self, n0: int = 0, n1: int | None = None) -> np.ndarray:
        """Spikes of steps [n0, n1) as (n, H, W) uint8 0/1 (upright)."""
        n1 = self.n_steps if n1 is None else n1
        pk = self.read_packed(n0, n1)
        P = self.height * self.width
        return np.unpackbits(pk, axis=1, bitorder="little", count=P).reshape(-1, self.height, self.width)

    def read_time(self, t0_s: float, t1_s: float) -> np.ndarray:
        """Spikes of the steps whose start lies in [t0_s, t1_s)."""
        return self.read(int(np.ceil(t0_s * self.rate_hz - 1e-9)), int(np.ceil(t1_s * self.rate_hz - 1e-9)))

    def iter_chunks(self, chunk_steps: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        """Yield (first step, (n, H, W) spikes) over the whole stream, lazily."""
        c = chunk_steps or self.f["spikes"].chunks[0]
        for n0 in range(0, self.n_steps, c):
            yield n0, self.read(n0, n0 + c)

    def array(self, name: str) -> np.ndarray:
        """A whole small dataset, e.g. 'polarizer/phi_true_rad'."""
        if name not in self.f:
            raise DataFormatError(f"{self.path}: no dataset {name!r} in this group")
        return self.f[name][()]

    @property
    def phi_true_rad(self) -> np.ndarray:
        """(T,) true mid-step angles."""
        return self.array("polarizer/phi_true_rad")

    @property
    def phi_nominal_rad(self) -> np.ndarray:
        """(T,) calibrated (nominal) mid-step angles."""
        return self.array("polarizer/phi_nominal_rad")

    def has(self, name: str) -> bool:
        """Whether dataset ``name`` exists."""
        return name in self.f

    def gt_frame(self, name: str, i: int) -> np.ndarray:
        """GT frame ``i`` of 'gt/T', 'gt/R' or 'gt/zeta', (H, W) float32."""
        if f"gt/{name}" not in self.f:
            raise DataFormatError(f"{self.path}: no ground truth 'gt/{name}' in this group")
        return self.f[f"gt/{name}"][i].astype(np.float32)

    def maps(self) -> dict[str, np.ndarray]:
        """Coefficient maps stored with the group ({} when the source had none)."""
        if "maps" not in self.f:
            return {}
        return {k: v[()] for k, v in self.f["maps"].items()}

    def close(self) -> None:
        """Close the file."""
        self.f.close()

    def __enter__(self) -> SpikeGroup:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_group(group_dir: str | os.PathLike) -> SpikeGroup:
    """Open a finished group for reading (DataFormatError if it is not one)."""
    return SpikeGroup(group_dir)
