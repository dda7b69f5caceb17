"""Global camera motion and sensor-model draws of the ``paper_motion`` sampler profile, and the camera-motion
regimes of the stress set.

A camera that turns (pan: yaw / pitch), rolls about its optical axis, zooms or shakes in the hand moves the
image of every layer alike, whatever its depth: a pure rotation of a pinhole camera has no parallax, and the
reflected layer is seen through the same camera.  So a global camera motion is the same image motion added to
both layers' ``motion`` (translation, rotation, log zoom and a shared random-walk shake, ``shake_per_s`` with one
``shake_seed``), on top of their own independent motion.  A camera translation (with parallax) is left out.

Draws, per group (U = uniform, LU = log-uniform; speeds in view widths per second, isotropic in pixels):

==========================  =====================================================
camera motion               static 20 %, pan 40 %, shake 15 %, rotation 12.5 %, zoom 12.5 %
pan                         speed LU[0.05, 3] view widths/s in a uniform direction
shake                       random walk of the velocity, rms speed U[0.5, 1.5] view widths/s, seeded
rotation                    about the optical axis, |rate| U[30, 90] deg/s, either sign
zoom                        |log zoom rate| U[0.2, 1.0] 1/s, in or out
sensor                      spike_sim preset ideal / default / noisy / plain_if, 1/4 each
==========================  =====================================================
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CAMERA_MOTIONS", "CAMERA_RANGES", "SENSOR_PRESETS", "STRESS_CAMERA", "camera_motion", "add_camera_motion", "camera_tag", "sensor_preset"]

CAMERA_MOTIONS: tuple[tuple[str, float], ...] = (("static", 0.2), ("pan", 0.4), ("shake", 0.15), ("rotate", 0.125), ("zoom", 0.125))
"""Kinds of global camera motion and their probabilities."""

CAMERA_RANGES: dict[str, tuple[float, float]] = {
    "pan_view_per_s": (0.05, 3.0),  # log-uniform
    "shake_rms_view_per_s": (0.5, 1.5),
    "rotate_deg_per_s": (30.0, 90.0),  # magnitude
    "zoom_per_s": (0.2, 1.0),  # magnitude
}
"""Ranges of the camera-motion draws (module docstring)."""

SENSOR_PRESETS: tuple[tuple[str, float], ...] = (("ideal", 0.25), ("default", 0.25), ("noisy", 0.25), ("plain_if", 0.25))
"""Spike simulator presets (:data:`spike_sim.config.PRESETS`) and their probabilities."""

STRESS_CAMERA: tuple[dict, ...] = (
    {"tag": "pan1p1", "refl": "strong", "light": "bright", "inc": "brewster", "pane": "slab", "kind": "pan", "speed": 1.1},
    {"tag": "pan3", "refl": "strong", "light": "bright", "inc": "normal", "pane": "single", "kind": "pan", "speed": 3.0},
    {"tag": "shake1", "refl": "strong", "light": "dim", "inc": "brewster", "pane": "single", "kind": "shake", "speed": 1.0},
    {"tag": "naturalpan1p1", "refl": "weak", "ratio": 0.2, "natural": True, "light": "bright", "inc": "brewster", "pane": "slab", "kind": "pan", "speed": 1.1},
    {"tag": "brightrefl", "refl": "dominant", "ratio": 8.0, "t_brightness": 0.4, "light": "dim", "inc": "normal", "pane": "single", "kind": "static", "speed": 0.0},
)
"""Camera-motion regimes added to the stress grid (test only): pans at 1.1 and 3 view widths/s (horizontal),
a hand-held shake of 1 view width/s rms, a weak reflection (R/T 0.2) of natural images under a 1.1 view/s pan,
and a near-normal pane whose reflection outshines T eight-fold (T brightness 0.4).  ``speed``: view widths/s."""


def _pick(rng: np.random.Generator, table: tuple[tuple[str, float], ...]) -> str:
    p = np.array([w for _, w in table])
    return table[int(rng.choice(len(table), p=p / p.sum()))][0]


def camera_motion(rng: np.random.Generator, aspect: float, kind: str | None = None, speed: float | None = None) -> dict:
    """One global camera motion: ``{"kind", "translate_per_s", "rotate_deg_per_s", "zoom_per_s", "shake_per_s",
    "shake_seed"}`` in the units of :class:`generator.scene.MotionConfig` (``aspect`` = width / height turns a
    speed in view widths into view heights for the vertical component).  ``kind`` / ``speed`` fix the draw
    (stress regimes; a pan is then horizontal).
    """
    kind = kind or _pick(rng, CAMERA_MOTIONS)
    out = {"kind": kind, "translate_per_s": [0.0, 0.0], "rotate_deg_per_s": 0.0, "zoom_per_s": 0.0, "shake_per_s": 0.0, "shake_seed": 0}
    if kind == "pan":
        if speed is None:
            lo, hi = CAMERA_RANGES["pan_view_per_s"]
            speed, ang = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))), float(rng.uniform(0.0, 2.0 * math.pi))
        else:
            ang = 0.0
        out["translate_per_s"] = [round(speed * math.cos(ang), 4), round(speed * math.sin(ang) * aspect, 4)]
        out["speed"] = speed
    elif kind == "shake":
        out["shake_per_s"] = round(float(rng.uniform(*CAMERA_RANGES["shake_rms_view_per_s"])) if speed is None else speed, 4)
        out["shake_seed"] = int(rng.integers(1, 2**31 - 1))
    elif kind == "rotate":
        out["rotate_deg_per_s"] = round(float(rng.uniform(*CAMERA_RANGES["rotate_deg_per_s"])) * (1 if rng.random() < 0.5 else -1), 3)
    elif kind == "zoom":
        out["zoom_per_s"] = round(float(rng.uniform(*CAMERA_RANGES["zoom_per_s"])) * (1 if rng.random() < 0.5 else -1), 4)
    return out


def add_camera_motion(layer_motion: dict, cam: dict) -> dict:
    """``layer_motion`` (a layer's ``motion`` table) with the camera's motion added (a new dict)."""
    m = dict(layer_motion)
    t = m.get("translate_per_s", [0.0, 0.0])
    m["translate_per_s"] = [round(t[0] + cam["translate_per_s"][0], 4), round(t[1] + cam["translate_per_s"][1], 4)]
    m["rotate_deg_per_s"] = round(m.get("rotate_deg_per_s", 0.0) + cam["rotate_deg_per_s"], 3)
    m["zoom_per_s"] = round(m.get("zoom_per_s", 0.0) + cam["zoom_per_s"], 4)
    if cam["shake_per_s"] > 0:
        m["shake_per_s"], m["shake_seed"] = cam["shake_per_s"], cam["shake_seed"]
    return m


def camera_tag(cam: dict) -> str | None:
    """Description tag of a camera motion, None when static."""
    k = cam["kind"]
    if k == "pan":
        return f"camera pan {cam['speed']:.2f} view/s"
    if k == "shake":
        return f"camera shake {cam['shake_per_s']:.2f} view/s rms"
    if k == "rotate":
        return f"camera rotation {cam['rotate_deg_per_s']:.0f} deg/s"
    if k == "zoom":
        return f"camera zoom {cam['zoom_per_s']:.2f} 1/s"
    return None


def sensor_preset(rng: np.random.Generator) -> str:
    """One spike simulator preset drawn from :data:`SENSOR_PRESETS`."""
    return _pick(rng, SENSOR_PRESETS)
