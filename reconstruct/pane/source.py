"""Self-calibration of a spike source: the first span of a stream as Eq. (3) frames, handed to the self-calibration."""

from __future__ import annotations

import dataclasses
import logging

from reconstruct.pane.selfcal import SelfCalConfig, SelfCalResult, self_calibrate
from reconstruct.stream.sources import frames_exposure, span_frames

log = logging.getLogger(__name__)


def calibrate_stream(source, group_dir=None, window_steps: int = 13, exposure: float | None = None, selfcal: SelfCalConfig | None = None,
                     pane_n: float | None = None, pane_model: str | None = None) -> SelfCalResult:
    """:func:`calibrate_source` with the settings a stream's caller has: the field of view from the stored group's
    scene when ``selfcal`` does not give one, and a known index / pane model (None: ``selfcal``'s, by default the
    index and model fitted where the data constrain them, else n 1.5 and a thin slab: what the evaluation measures,
    :func:`reconstruct.pane.selfcal.group_self_zeta`).
    """
    sc = selfcal or SelfCalConfig()
    if pane_n is not None:
        sc = dataclasses.replace(sc, n=float(pane_n))
    if pane_model is not None and pane_model != "auto":
        sc = dataclasses.replace(sc, model=pane_model)
    if not sc.fov_deg and group_dir is not None:
        from reconstruct.stream.groups import fov_from_group_dir

        fov = fov_from_group_dir(group_dir)
        if fov:
            sc = dataclasses.replace(sc, fov_deg=fov)
    return calibrate_source(source, window_steps, exposure, sc)


def calibrate_source(source, window_steps: int = 13, exposure: float | None = None, cfg: SelfCalConfig = SelfCalConfig()) -> SelfCalResult:
    """Self-calibrate the pane on the first ``cfg.span_s`` of a spike stream (:class:`reconstruct.stream.sources.SpikeSource`).

    Every spike of the span is used: back-to-back Eq. (3) windows of ``window_steps`` steps, each at
    its mean calibrated polarizer angle (denser than the output cadence: more data, same model); pixels that
    saturate are left out (:func:`reconstruct.pane.selfcal.leave_out_saturated`).
    """
    ex = frames_exposure(source, exposure)
    I, phi = span_frames(source, cfg.span_s, window_steps, ex)
    return self_calibrate(I, phi, cfg, name=source.name, exposure=ex)
