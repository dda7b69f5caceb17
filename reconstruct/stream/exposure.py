"""Exposure of a raw spike stream of unknown scale (``polspike reconstruct FILE.dat`` without ``--exposure``).

Units.  The reconstructors work in radiance units, paper Eq. (3): I = counts / (window_steps x
exposure), with exposure in thresholds per step per unit radiance (:mod:`spike_sim.config`).
The radiance unit is a convention of the training data ("1.0 = the brightest layer value"), not
a physical quantity the stream carries: a scene twice as bright at half the exposure fires the
same spikes.  So no statistic of the spikes alone can recover "the true" exposure; what can be
done, and what the models need, is to put I in the range they were trained on.

Why not the noise statistics.  For an integrate-and-fire pixel the spike count in a window is
close to deterministic (rate x steps, +-1 spike of phase), and the photon shot noise that remains
reveals the photoelectrons per threshold (``photons_per_threshold``), i.e. the sensor's gain in
photons, never the radiance unit of the training scenes.  The variance-to-mean relation therefore
cannot fix the scale the networks and solvers depend on.

Method (:func:`estimate_exposure`).  The time-averaged firing rate r(p) (spikes per step) over the
first ``max_steps`` steps (0.2 s at 20 kHz: several polarizer half-turns, so the polarizer
modulation averages out) is computed per pixel; its ``QUANTILE`` (99.9th percentile: the
bright end of the scene, robust to a few hot pixels) is mapped to :data:`REFERENCE_RADIANCE`,
the same quantile of the time-averaged I of the training groups:

    exposure = quantile_99.9(r) / REFERENCE_RADIANCE.

:data:`REFERENCE_RADIANCE` is the geometric mean, over the 40 train groups of
``datasets/manifests/paper.toml`` (built as ``out/datasets/fit_paper``, each group's stored true
exposure), of the 99.9th percentile of r / exposure.  Measured spread (log of estimated / true
exposure, the irreducible scene-brightness ambiguity above): standard deviation 0.42 on those
train groups, 0.30 on the 10 test groups (``eval_paper``, bias +0.21), 0.22 on the stress set
(bias +0.33); worst case a factor 3.1 (a nearly dark train scene).  Other statistics spread more
(the mean rate: 0.84 on train; the 99th percentile: 0.48).  The estimate is exactly
proportional to the true exposure for a given scene (tested), so reconstructions in radiance
units agree with those at the true exposure up to that one factor, which the networks' own
brightness normalisation (:func:`reconstruct.net.network.window_scale`) removes.

A pixel fires at most once per step: when the quantile rate is above :data:`SATURATION_RATE` the
stream is saturated at its bright end and the estimate is a lower bound (``saturated`` in the
result; a warning is logged).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from polinfra.errors import ConfigError

__all__ = ["REFERENCE_RADIANCE", "QUANTILE", "SATURATION_RATE", "ExposureEstimate", "estimate_exposure", "estimate_source_exposure", "exposure_errors"]

log = logging.getLogger(__name__)

REFERENCE_RADIANCE = 0.2418
"""99.9th percentile of the time-averaged I (radiance units) of the paper.toml train groups (geometric mean over the 40 groups; module docstring)."""

QUANTILE = 99.9
"""Percentile of the per-pixel mean firing rate mapped to :data:`REFERENCE_RADIANCE`."""

SATURATION_RATE = 0.9
"""Spikes per step above which the quantile is treated as saturated (a pixel fires at most once per step)."""

MIN_SPIKES = 8
"""Fewest spikes the quantile pixel must have fired for an estimate (below: ConfigError, pass --exposure); 8 spikes quantise the estimate to within 1/8, well inside its scene-brightness ambiguity."""


@dataclasses.dataclass(frozen=True)
class ExposureEstimate:
    """Result of :func:`estimate_exposure` (plain data, JSON-ready via :meth:`summary`)."""

    exposure: float
    rate_quantile: float
    mean_rate: float
    steps: int
    saturated: bool
    reference_radiance: float = REFERENCE_RADIANCE
    quantile: float = QUANTILE

    def summary(self) -> dict[str, Any]:
        return {"method": f"percentile {self.quantile:g} of the per-pixel mean firing rate -> radiance {self.reference_radiance:g}", **dataclasses.asdict(self)}


def estimate_exposure(spikes: np.ndarray, reference_radiance: float = REFERENCE_RADIANCE, quantile: float = QUANTILE) -> ExposureEstimate:
    """Exposure (thresholds per step per unit radiance) of a (T, H, W) 0/1 spike array (module docstring).

    Raises:
        ConfigError: too few spikes to estimate (an empty or almost dark stream).
    """
    sp = np.asarray(spikes)
    if sp.ndim != 3 or sp.shape[0] < 1:
        raise ConfigError(f"exposure estimation needs a (T, H, W) spike array; got shape {sp.shape}")
    counts = sp.sum(0, dtype=np.int64)
    return _from_counts(counts, sp.shape[0], reference_radiance, quantile)


def _from_counts(counts: np.ndarray, steps: int, reference_radiance: float, quantile: float) -> ExposureEstimate:
    rate = counts.astype(np.float64) / steps
    q = float(np.percentile(rate, quantile))
    if q * steps < MIN_SPIKES:
        raise ConfigError(
            f"cannot estimate the exposure: the brightest pixels fired {q * steps:.0f} spikes in {steps} steps (need {MIN_SPIKES}); "
            "use a longer recording or pass --exposure"
        )
    sat = q > SATURATION_RATE
    if sat:
        log.warning("the stream is saturated at its bright end (%.2f spikes per step): the estimated exposure is a lower bound", q)
    return ExposureEstimate(exposure=q / reference_radiance, rate_quantile=q, mean_rate=float(rate.mean()), steps=int(steps), saturated=bool(sat),
                            reference_radiance=float(reference_radiance), quantile=float(quantile))


def estimate_source_exposure(source, max_steps: int = 4000, reference_radiance: float = REFERENCE_RADIANCE, quantile: float = QUANTILE) -> ExposureEstimate:
    """:func:`estimate_exposure` on the first ``max_steps`` steps of a :class:`reconstruct.stream.sources.SpikeSource` (read chunk by chunk)."""
    counts = np.zeros((source.height, source.width), np.int64)
    have = 0
    for _, chunk in source.chunks():
        c = np.asarray(chunk)[: max_steps - have]
        counts += c.sum(0, dtype=np.int64)
        have += c.shape[0]
        if have >= max_steps:
            break
    if have == 0:
        raise ConfigError(f"{source.name}: the stream has no steps to estimate the exposure from")
    return _from_counts(counts, have, reference_radiance, quantile)


def exposure_errors(group_dirs, max_steps: int = 4000) -> list[dict[str, Any]]:
    """Estimated vs stored exposure of spike groups (``polspike bench exposure``): one row per group with
    ``exposure``, ``estimate``, ``log_error`` = ln(estimate / exposure), ``quantile_radiance`` (the
    group's 99.9th percentile of I at its true exposure: what :data:`REFERENCE_RADIANCE` is the mean of).
    """
    from spike_sim.store import open_group

    rows = []
    for gd in group_dirs:
        with open_group(gd) as g:
            e = (g.json_attr("config_json") or {}).get("exposure")
            n = min(int(max_steps), int(g.n_steps))
            sp = g.read(0, n)
        if e is None:
            continue
        est = estimate_exposure(sp)
        rows.append({"group": str(gd), "exposure": float(e), "estimate": est.exposure, "log_error": float(np.log(est.exposure / float(e))),
                     "quantile_radiance": est.rate_quantile / float(e), "saturated": est.saturated, "steps": n})
    return rows
