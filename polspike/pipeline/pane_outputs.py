"""calibrate-pane's outputs: the fitted scene file, figures, report and maps, and the synthetic bench stream."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from reconstruct.pane.calibrate import _json_safe, _normal

log = logging.getLogger(__name__)


def fitted_scene_dict(params: dict, width: int, height: int, base: dict | None = None, name: str = "fitted_pane") -> dict:
    """Scene data (``generator.scene`` schema) of the fitted setup: the base scene (a group's, or the defaults)
    with the camera's fov and size and the pane's tilt, tilt axis, index and model replaced.
    """
    from generator.scene import SceneConfig, check_scene_geometry, scene_from_dict
    from polinfra.config import to_dict
    from polinfra.errors import SceneError

    d = json.loads(json.dumps(base)) if base else to_dict(SceneConfig())
    d.pop("objects", None)
    d["name"] = name
    d["description"] = f"fitted by polspike calibrate-pane: tilt {params['tilt_deg']:.2f} deg, azimuth {params['azimuth_deg']:.2f} deg, fov {params['fov_deg']:.2f} deg, n {params['n']:.4f}, {params['model']}"
    d.setdefault("camera", {})
    d["camera"].update({"width": int(width), "height": int(height), "fov_deg": round(float(params["fov_deg"]), 4)})
    pane = d.setdefault("pane", {})
    pane.update({"model": params["model"], "n": round(float(params["n"]), 5), "glass": params.get("glass"), "normal": None})
    # the scene's pane_plane(): -forward rotated by tilt about the in-image axis at tilt_axis;
    # the fitted normal (away from the camera) has its image projection at `azimuth`: the axis is perpendicular
    sc = scene_from_dict(d, where="fitted scene")
    cam = sc.camera_model()
    want = _normal([math.radians(params["tilt_deg"]), math.radians(params["azimuth_deg"])])
    want_w = -(want[0] * (-cam.right) + want[1] * cam.up + want[2] * cam.forward)  # reference frame right = -x: world normal facing the camera
    best = None
    for ax in (params["azimuth_deg"] + 90.0, params["azimuth_deg"] - 90.0):
        a = ((ax + 180.0) % 360.0) - 180.0
        pane.update({"tilt_deg": round(float(params["tilt_deg"]), 4), "tilt_axis_deg": round(a, 4)})
        got = scene_from_dict(d, where="fitted scene").pane_plane().normal
        err = float(np.degrees(np.arccos(np.clip(abs(float(np.dot(got, want_w) / np.linalg.norm(got))), -1, 1))))
        if best is None or err < best[0]:
            best = (err, a)
    pane["tilt_axis_deg"] = round(best[1], 4)
    for _ in range(8):  # the pane must cover the view
        try:
            check_scene_geometry(scene_from_dict(d, where="fitted scene"))
            break
        except SceneError as e:
            if "does not cover" not in str(e):  # edge-on for part of the view: no size helps
                raise SceneError(f"the fitted pane (tilt {params['tilt_deg']:.1f} deg, fov {params['fov_deg']:.1f} deg) is edge-on or behind the camera for part of the view, which a scene file cannot hold") from None
            pane["size_m"] = [2.0 * float(v) for v in pane.get("size_m", (4.0, 3.0))]
    scene_from_dict(d, where="fitted scene")
    return d


def scene_toml_text(d: dict, header: str) -> str:
    """TOML text of scene data (the manifest writer's table dumper)."""
    from polspike.pipeline.manifest import _toml_table

    lines = [f"# {ln}" for ln in header.splitlines()]
    _toml_table(lines, "", d)
    return "\n".join(lines) + "\n"


def _figures(out: Path, res: dict) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from polinfra.plotting import save_figure

    f = res["figs"]
    names = []
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4))
    h = f["history"]
    ax[0].semilogy([e["iter"] for e in h], [max(e["chi2"], 1e-30) for e in h], "o-")
    ax[0].set(xlabel="Gauss-Newton iteration", ylabel="orientation cost", title="geometry fit")
    gm = f["gl"]["models"]
    for k, v in gm.items():
        if len(v["grid_n"]) > 1:
            ax[1].plot(v["grid_n"], v["grid_loss"], label=k)
    ax[1].set(xlabel="n", ylabel="cone-edge loss", title="glass search")
    if any(len(v["grid_n"]) > 1 for v in gm.values()):
        ax[1].legend()
    save_figure(fig, out / "convergence.png")
    plt.close(fig)
    names.append("convergence.png")
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
    mpsi = np.where(f["mask"], np.degrees(f["psi"]), np.nan)
    im = ax[0].imshow(mpsi, cmap="twilight", vmin=0, vmax=90)
    ax[0].set_title("measured AoLP mod 90 (deg)")
    plt.colorbar(im, ax=ax[0], fraction=0.046)
    im = ax[1].imshow(np.degrees(np.mod(f["phi_fit_blocks"], np.pi / 2)), cmap="twilight", vmin=0, vmax=90)
    ax[1].set_title("fitted phi_perp mod 90 (deg)")
    plt.colorbar(im, ax=ax[1], fraction=0.046)
    im = ax[2].imshow(np.where(f["mask"], f["residual_deg"], np.nan), cmap="magma", vmin=0, vmax=max(1.0, float(np.nanpercentile(np.where(f["mask"], f["residual_deg"], np.nan), 95))))
    ax[2].set_title("|residual| (deg)")
    plt.colorbar(im, ax=ax[2], fraction=0.046)
    for a in ax:
        a.axis("off")
    save_figure(fig, out / "aolp_residual.png")
    plt.close(fig)
    names.append("aolp_residual.png")
    st, th = f["st"], np.degrees(f["theta_g"])
    v = st["valid"]
    g = gm[f["model_key"]]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.scatter(th[v], st["upper"][v], s=6, label="max rho per block (R side)")
    ax.scatter(th[v], st["lower"][v], s=6, label="min rho per block (T side)")
    o = np.argsort(th[v])
    ax.plot(th[v][o], g["dop_R"][v][o], "k-", label="fitted DoP_R")
    ax.plot(th[v][o], g["dop_T"][v][o], "k--", label="fitted -DoP_T")
    ax.set(xlabel="incidence theta (deg)", ylabel="modulation depth rho = m / a0", title=f"modulation depth vs fitted cone ({f['model_key']})")
    ax.legend(fontsize=7)
    save_figure(fig, out / "modulation_depth.png")
    plt.close(fig)
    names.append("modulation_depth.png")
    return names


def write_outputs(out: Path, res: dict, *, base_scene: dict | None = None, width: int, height: int) -> dict:
    """Write DIR/pane.toml, DIR/maps.exr, DIR/report.json and the figures (each file atomically)."""
    from polinfra.atomic import ensure_dir, write_json, write_text
    from polinfra.errors import SceneError
    from polinfra.exr import write_exr

    ensure_dir(out)
    rep = res["report"]
    if not res["ok"]:
        write_json(out / "report.json", _json_safe(rep))
        return rep
    files = []
    try:
        d = fitted_scene_dict(res["params"], width, height, base_scene)
    except SceneError as e:  # the maps and the report still hold; only the scene file cannot be written
        log.warning("%s: no pane.toml written (maps.exr and report.json are)", e)
        rep["pane_toml"] = {"written": False, "why": str(e)}
    else:
        ident = rep["identifiability"]
        hdr = (f"Scene of the pane fitted by polspike calibrate-pane to {rep['input']}.\n"
               f"Fitted: tilt {res['params']['tilt_deg']:.3f} +- {rep['uncertainty_1sigma']['tilt_deg']:.3f} deg, fov {res['params']['fov_deg']:.3f} deg; "
               f"n {'fitted' if ident['n']['identified'] else 'given' if ident['n']['identified'] is None else 'NOT identified (prior)'}; "
               f"model {'fitted' if ident['model']['identified'] else 'given' if ident['model']['identified'] is None else 'NOT identified (prior)'}.\n"
               "Layers, polarizer and render settings come from the input's own scene when it has one, else the defaults. See report.json.")
        write_text(out / "pane.toml", scene_toml_text(d, hdr))
        rep["pane_toml"] = {"written": True}
        files.append("pane.toml")
    ch = {k: res["maps"][k].astype(np.float32) for k in ("theta", "phi_perp", "R_perp", "R_par", "T_perp", "T_par")}
    write_exr(out / "maps.exr", ch, attrs={"source": "polspike calibrate-pane", "tier": "maps (differentiable Dr.Jit pane model)"})
    rep["figures"] = _figures(out, res)
    rep["files"] = [*files, "maps.exr", "report.json", *rep["figures"]]
    write_json(out / "report.json", _json_safe(rep))
    return rep

