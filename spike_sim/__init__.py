"""spike_sim: a 20 kHz integrate-and-fire spike camera behind a rotating polarizer.

Second floor: imports :mod:`polinfra` and :mod:`polphysics` only.

Input: Stokes keyframes (S0, S1, S2) over time (a render directory or arrays).
Output: bit-packed spike streams in a chunked HDF5 group (:mod:`.store`) and/or
raw Vidar ``.dat`` files (:mod:`.vidar_dat`), with phi(t), timestamps and
ground truth; paper Eq. (3) aggregation in :mod:`.aggregate`; polarizer
calibration from spikes in :mod:`.calibrate`.  See spike_sim/README.md.
"""

from spike_sim.aggregate import AggregateConfig, aggregate_group, aggregate_stream, frame_centres, observation_stack, output_fps
from spike_sim.calibrate import PolarizerCalibration, calibrate_flat_target, calibrate_from_modulation, calibrate_group, darkest_phase, estimate_rate, phase_error
from spike_sim.config import DEFAULT, IDEAL, NOISY, PRESETS, SpikeSimConfig, preset
from spike_sim.integrate_fire import make_pixel_params, run_numba, run_numpy, simulate_constant, simulate_currents
from spike_sim.simulate import KeyframeSource, SimulationSummary, keyframes_from_arrays, keyframes_from_render, simulate
from spike_sim.store import GroupWriter, SpikeGroup, open_group
from spike_sim.vidar_dat import DatWriter, dat_frame_count, iter_dat, read_dat, write_dat

__all__ = [
    "AggregateConfig",
    "aggregate_group",
    "aggregate_stream",
    "frame_centres",
    "observation_stack",
    "output_fps",
    "PolarizerCalibration",
    "calibrate_flat_target",
    "calibrate_group",
    "calibrate_from_modulation",
    "darkest_phase",
    "estimate_rate",
    "phase_error",
    "DEFAULT",
    "IDEAL",
    "NOISY",
    "PRESETS",
    "SpikeSimConfig",
    "preset",
    "make_pixel_params",
    "run_numba",
    "run_numpy",
    "simulate_constant",
    "simulate_currents",
    "KeyframeSource",
    "SimulationSummary",
    "keyframes_from_arrays",
    "keyframes_from_render",
    "simulate",
    "GroupWriter",
    "SpikeGroup",
    "open_group",
    "DatWriter",
    "dat_frame_count",
    "iter_dat",
    "read_dat",
    "write_dat",
]
