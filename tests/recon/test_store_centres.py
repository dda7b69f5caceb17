"""The reader of a stored group finds the ground truth of every frame the simulator stored.

At 30 rev/s and 20 kHz a 31.5 deg stride is 58 1/3 steps: every third Eq. (3) centre falls on a half step, where
the rounding follows the last bit of the angles. The simulator places its centres from its clock's angle at t = 0;
the reader must start from the same angle, or it rounds some of those centres to the other step and the frame is
scored without ground truth (or not at all).
"""

from __future__ import annotations

import numpy as np
import pytest

from polphysics.polarizer import PolarizerConfig
from reconstruct.stream.groups import load_store_group
from spike_sim.simulate import keyframes_from_arrays, simulate
from spike_sim.store import open_group


@pytest.mark.parametrize("phase_deg", [10.0, 33.3, 100.0])
def test_every_stored_output_frame_is_found_with_its_ground_truth(tmp_path, phase_deg):
    H, W = 6, 8
    rng = np.random.default_rng(3)
    T, R = rng.uniform(0.2, 1.0, (2, 1, H, W)).astype(np.float32)
    st = np.zeros((1, 3, H, W), np.float32)
    st[:, 0] = 0.5 * (T + R)
    src = keyframes_from_arrays([0.0], st, (T, R), polarizer=PolarizerConfig(phase_deg=phase_deg))
    simulate(src, duration_s=0.1, seed=1, out=tmp_path / "g", compression="none")
    with open_group(tmp_path / "g") as g:
        stored = g.array("output/step_index")
    eg = load_store_group(tmp_path / "g")
    assert eg.has_gt.all(), f"frames without ground truth at phase {phase_deg}: {np.flatnonzero(~eg.has_gt)}"
    assert eg.I.shape[0] == stored.size  # one reader frame per stored output frame (34 in 0.1 s)

