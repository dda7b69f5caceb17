"""Options of polspike calibrate-pane."""

from __future__ import annotations

import dataclasses
import logging

from polinfra.config import opt

log = logging.getLogger(__name__)


PANE_CHOICES = ("auto", "single", "thin_slab", "thick_slab")


@dataclasses.dataclass(frozen=True)
class CalibratePaneConfig:
    """Options of ``polspike calibrate-pane``."""

    span_s: float = opt(0.1, "length of the stream used, seconds (stationary pane)", lo=0.005, hi=100.0)
    window_steps: int = opt(13, "Eq. (3) window in camera steps", lo=1, hi=10001)
    fov_deg: float = opt(0.0, "known horizontal field of view, degrees (0 = fit it)", lo=0.0, hi=170.0)
    n: float = opt(0.0, "known refractive index (0 = fit it where the data constrain it)", lo=0.0, hi=4.0)
    glass: str | None = opt(None, "known named glass (its index at 550 nm is used and kept fixed)")
    pane_model: str = opt("auto", "pane model: auto (fit single vs slab where the data constrain it) or single | thin_slab | thick_slab", choices=PANE_CHOICES)
    prior_n: float = opt(1.5, "index kept when the data do not constrain it", lo=1.01, hi=4.0)
    prior_model: str = opt("thin_slab", "pane model kept when the data do not tell single from slab", choices=("single", "thin_slab", "thick_slab"))
    block_px: int = opt(0, "block size of the orientation field (0 = about 48 blocks across)", lo=0, hi=1024)
    glass_block_px: int = opt(0, "block size of the glass statistics (0 = as block_px)", lo=0, hi=1024)
    max_n_sigma: float = opt(0.03, "n counts as identified only with a 1-sigma uncertainty at most this", lo=0.0, hi=1.0)
    min_edge_blocks: int = opt(8, "blocks on the cone's edge needed before n / the model count as identified", lo=1, hi=100000)
    min_edge_fraction: float = opt(0.1, "share of the precisely measured block extremes that must pile up on the fitted cone (a real edge: one layer black there) before n / the model are claimed", lo=0.0, hi=1.0)
    max_edge_noise: float = opt(0.03, "a block's extreme modulation ratio counts towards n / the model only when its noise is at most this", lo=0.0, hi=1.0)
    model_delta_chi2: float = opt(9.0, "the better pane model must win by this much chi^2 to be claimed", lo=0.0, hi=1e6)
    sub: int = opt(2, "rays per pixel axis of the written maps (as the maps tier)", lo=1, hi=4)
    dop_fov: bool = opt(False, "experimental (off: on eval_paper it moved test_004 0.4 deg off, see docs/calibrate_pane.md): where the modulation depths reach the cone's edge, profile the fov-tilt valley of the orientation fit with the cone's theta dependence")
    dop_fov_delta_chi2: float = opt(25.0, "the modulation depth pins the fov only when the cone violations at both ends of the profiled valley exceed its minimum by this much", lo=0.0, hi=1e9)
    max_incidence_deg: float = opt(89.0, "a fitted fov at which a modulating block's ray would meet the pane at more than this incidence (edge-on, or never in front of the camera: it could not modulate) is narrowed to the widest view that keeps every modulating block below it (the fov then NOT identified); 90 or more turns the check off", lo=1.0, hi=180.0)
    max_theta_sigma_deg: float = opt(0.5, "a fitted fov (hence theta) counts as identified only when theta's median 1-sigma is at most this, degrees", lo=0.0, hi=90.0)
    content: bool = opt(True, "where the DoP cone leaves n / the model open, try the layers' content: the gradients of R^ and T^ solved under the right zeta are least correlated (reconstruct.physics.exclusion); claimed only with a margin over the tiles' spread")
    content_sigma_px: float = opt(2.0, "smoothing (pixels) of the solved layers before their gradients are correlated (the sensor's fixed pattern correlates them at 1 px)", lo=0.0, hi=20.0)
    content_tiles: int = opt(6, "the content score's tiles per image axis (its spread across tiles gives the margin)", lo=2, hi=64)
    content_parts: int = opt(0, "time parts of the span: R^ of one part is correlated with T^ of another (independent spike noise); 0 = one part per CONTENT_PART_HALF_TURNS half turns of the polarizer, at least 2 (0.1 s at 30 rev/s: 2; 0.2 s: 4), so a longer span adds pairs instead of blurring the moving layers", lo=0, hi=64)
    content_power: str = opt("same", "normalisation of the content test's tile correlations: same (each part's own gradient power: content + spike noise, so hypotheses that amplify the noise score lower) or cross (the power crossed between time parts: content only)", choices=("same", "cross"))
    content_pixels: str = opt("auto", "pixels of the content test: same (both layers' gradients from every pixel), split (R^ from one checkerboard set, T^ from the other: the sensor's static fixed pattern, common to both layers at a pixel, drops out, which unbiases the index but widens its spread; docs/calibrate_pane.md round 5) or auto (split where the span holds CONTENT_SPLIT_PARTS time parts or more, whose extra pairs pay for the halved pixels: 0.2 s at 30 rev/s; same below; round 6)", choices=("auto", "same", "split"))
    content_best: bool = opt(True, "where the content test does not claim n / the model, its best hypothesis (still reported NOT identified) replaces the prior in the written maps")
    content_best_z: float = opt(1.0, "the content test's unclaimed best model replaces the prior only when the other model scores higher by at least this many standard errors (below: a coin flip, the prior stays)", lo=0.0, hi=100.0)
    content_z: float = opt(3.0, "a content claim needs the alternatives' score higher by this many standard errors (across tiles)", lo=0.0, hi=100.0)
    twin_check_ratio: float = opt(0.95, "fov fitted: where the orientation field scores the 90 deg twin above this fraction of the best (below the self-calibration's ambiguity limit), the twin family is profiled along the fov and its cone asked too", lo=0.0, hi=10.0)
    twin_profile_cost_tol: float = opt(0.05, "twin profile: only twin points whose orientation cost is within this fraction of the chosen pane's are judged by the cone", lo=0.0, hi=10.0)
    twin_close_factor: float = opt(4.0, "a twin overturns the orientation field's narrow choice only where the chosen pane's cone is violated this many times more (and by twin_delta_chi2)", lo=1.0, hi=1e6)
    twin_delta_chi2: float = opt(25.0, "an orientation field that cannot tell the pane from its 90 deg twin is resolved by the modulation depth only when one candidate's cone is violated by this much chi^2 less", lo=0.0, hi=1e9)
