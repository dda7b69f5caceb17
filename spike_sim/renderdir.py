"""Reader of a render directory (the generator's output, spike_sim's input).

This module knows the file format only; it never imports the generator, so
downstream stages (spike_sim, reconstruct) can read renders without Mitsuba.
See :mod:`generator.render` for the layout.
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path

import numpy as np

from polinfra.config import from_dict
from polinfra.errors import DataFormatError
from polinfra.exr import read_exr
from polphysics.polarizer import PolarizerConfig

__all__ = ["RenderDir", "open_render"]

MAP_CHANNELS = ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")
EXTRA_MAP_CHANNELS = ("dop_T", "dop_R", "eq12_err", "polT_model_err")
"""Optional maps of 3-D object scenes (their departure from paper Eq. (1)-(2)); kept when present."""


class RenderDir:
    """A render directory opened for reading.

    Attributes:
        path: the folder.
        meta: the parsed render.json.
        times_s: (K,) keyframe times in seconds.
        width, height: image size.
        scene_hash: content hash of the scene that made it.
        polarizer: the scene's rotating-polarizer parameters.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        mp = self.path / "render.json"
        if not mp.is_file():
            raise DataFormatError(f"{self.path} is not a render directory (no render.json); run `polspike render` first")
        try:
            self.meta = json.loads(mp.read_text())
        except json.JSONDecodeError as exc:
            raise DataFormatError(f"{mp} is not valid JSON ({exc})") from None
        if self.meta.get("format") != "polspike-render/1":
            raise DataFormatError(f"{mp}: unknown format {self.meta.get('format')!r}; expected 'polspike-render/1'")
        if not self.meta.get("complete", False):
            raise DataFormatError(f"render in {self.path} is incomplete; rerun `polspike render` with the same --out to finish it")
        self.times_s = np.asarray(self.meta["frame_times_s"], dtype=np.float64)
        self.width = int(self.meta["width"])
        self.height = int(self.meta["height"])
        self.scene_hash = str(self.meta["scene_hash"])
        self.polarizer = from_dict(PolarizerConfig, self.meta.get("scene", {}).get("polarizer", {}), where=str(mp))

    def __len__(self) -> int:
        return len(self.times_s)

    @functools.lru_cache(maxsize=8)
    def _frame(self, i: int) -> dict[str, np.ndarray]:
        return read_exr(self.path / self.meta["frames"][i], ["S0", "S1", "S2", "T", "R"])

    def stokes(self, i: int) -> np.ndarray:
        """Stokes (3, H, W) float32 of keyframe ``i``."""
        f = self._frame(i)
        return np.stack([f["S0"], f["S1"], f["S2"]])

    def layers(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Ground-truth layer radiances (T, R), each (H, W) float32, of keyframe ``i``."""
        f = self._frame(i)
        return f["T"], f["R"]

    def maps(self) -> dict[str, np.ndarray]:
        """Coefficient maps {theta, phi_perp, R_perp, R_par, T_perp, T_par} (plus the optional
        :data:`EXTRA_MAP_CHANNELS` of object scenes), each (H, W) float32.
        """
        allc = read_exr(self.path / "maps.exr")
        missing = [k for k in MAP_CHANNELS if k not in allc]
        if missing:
            raise DataFormatError(f"{self.path / 'maps.exr'}: channel(s) {missing} missing; re-render")
        return {k: allc[k] for k in (*MAP_CHANNELS, *EXTRA_MAP_CHANNELS) if k in allc}


def open_render(path: str | os.PathLike) -> RenderDir:
    """Open a finished render directory for reading (DataFormatError if it is not one)."""
    return RenderDir(path)
