"""Content checks of the README's CLI tour (tests/test_readme.py runs each command, then its check here).

Each check reads what its command printed or wrote: the files exist, with the shapes and value ranges they
should have, and one number is held against an oracle that is not the code under test: a closed form
(Fresnel amplitudes, paper Eq. (1)-(2), the integrate-and-fire firing rate), the scene or manifest the
command was given, or the render the stream was simulated from.  Every tour command needs a check.
"""

from __future__ import annotations

import json
import re
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)


def fresnel(n: float, theta: float) -> dict[str, float]:
    """Power reflectances and transmittances of one interface from the Fresnel amplitudes (s = perp, p = par)."""
    ci = np.cos(theta)
    ct = np.sqrt(1.0 - (np.sin(theta) / n) ** 2)
    rs, rp = (ci - n * ct) / (ci + n * ct), (n * ci - ct) / (n * ci + ct)
    ts, tp = 2 * ci / (ci + n * ct), 2 * ci / (n * ci + ct)
    k = n * ct / ci  # the transmitted beam's power per unit area, relative
    return {"R_perp": rs**2, "R_par": rp**2, "T_perp": k * ts**2, "T_par": k * tp**2}


def thin_slab(n: float, theta: float) -> dict[str, float]:
    """A lossless slab, incoherent sum over internal reflections: R' = R + T^2 R / (1 - R^2), T' = T^2 / (1 - R^2)."""
    f = fresnel(n, theta)
    out = {}
    for pol in ("perp", "par"):
        R, T = f[f"R_{pol}"], f[f"T_{pol}"]
        out[f"R_{pol}"] = R + T * T * R / (1 - R * R)
        out[f"T_{pol}"] = T * T / (1 - R * R)
    return out


def _opt(args: list[str], name: str) -> str:
    return args[args.index(name) + 1]


def _centre(a: np.ndarray) -> float:
    """Mean of the 2 x 2 pixels around the optical axis (an even-sized image has no pixel on it)."""
    h, w = a.shape[-2:]
    return float(a[..., h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1].mean())


def _scene(name: str) -> dict:
    return tomllib.loads((REPO / "scenes" / f"{name}.toml").read_text())


def check_version(cwd: Path, args: list[str], out: str) -> None:
    from importlib.metadata import version

    m = re.fullmatch(r"polspike (\S+), checkpoint (\S+\.pt)", out.strip())
    assert m, out
    assert m.group(1) == version("polspike")
    assert (REPO / "reconstruct" / "weights" / m.group(2)).is_file(), m.group(2)


def check_zeta(cwd: Path, args: list[str], out: str) -> None:
    """The printed row against the Fresnel amplitudes and paper Eq. (2) written out here."""
    row = [ln for ln in out.splitlines() if re.search(r"\d\.\d{6}", ln)]
    assert len(row) == 1, out
    got = [float(x) for x in re.findall(r"-?\d+\.\d+", row[0])]
    assert len(got) == 5, row
    n, theta = float(_opt(args, "--n")), np.radians(float(_opt(args, "--theta-deg")))
    d = np.radians(float(_opt(args, "--phi-deg")) - float(_opt(args, "--phi-perp-deg")))
    f = fresnel(n, theta)
    zeta = f["R_perp"] * np.cos(d) ** 2 + f["R_par"] * np.sin(d) ** 2
    np.testing.assert_allclose(got, [f["R_perp"], f["R_par"], f["T_perp"], f["T_par"], zeta], atol=2e-6)


def check_render(cwd: Path, args: list[str], out: str) -> None:
    """Frames at fps over the duration with S0, S1, S2, T, R; DoP <= 1; S0 = the layers through the pane maps
    (Stokes form of Eq. (1)); the thin slab's R_perp on the axis, where the incidence is the pane's tilt, from
    the Fresnel amplitudes.
    """
    from polinfra.exr import read_exr

    d = cwd / _opt(args, "--out")
    meta = json.loads((d / "render.json").read_text())
    scene = _scene(Path(args[1]).stem)
    n_frames = int(round(float(_opt(args, "--duration")) * scene["render"]["fps"])) + 1
    assert len(meta["frames"]) == n_frames and meta["complete"], meta["frames"]
    H, W = scene["camera"]["height"], scene["camera"]["width"]
    maps = read_exr(d / "maps.exr")
    assert {"R_perp", "R_par", "T_perp", "T_par", "phi_perp", "theta"} <= set(maps)
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        assert maps[k].shape == (H, W) and 0 <= maps[k].min() and maps[k].max() <= 1, k
    fr = read_exr(d / meta["frames"][-1])
    assert all(fr[k].shape == (H, W) for k in ("S0", "S1", "S2", "T", "R"))
    assert fr["T"].min() >= 0 and fr["R"].min() >= 0 and fr["S0"].min() > 0
    assert (np.hypot(fr["S1"], fr["S2"]) <= fr["S0"] * (1 + 1e-5) + 1e-7).all()
    s0 = 0.5 * (fr["T"] * (maps["T_perp"] + maps["T_par"]) + fr["R"] * (maps["R_perp"] + maps["R_par"]))
    np.testing.assert_allclose(fr["S0"], s0, atol=1e-5)
    _axis_fresnel(maps, scene)


def _axis_fresnel(maps: dict, scene: dict) -> None:
    pane = scene["pane"]
    assert pane["model"] == "thin_slab"
    assert abs(np.degrees(_centre(maps["theta"])) - pane["tilt_deg"]) < 0.01, ("incidence on the axis", np.degrees(_centre(maps["theta"])))
    want = thin_slab(pane["n"], np.radians(pane["tilt_deg"]))
    for k in ("R_perp", "R_par", "T_perp", "T_par"):
        assert abs(_centre(maps[k]) - want[k]) < 5e-4, (k, _centre(maps[k]), want[k])


def check_validate_zeta(cwd: Path, args: list[str], out: str) -> None:
    """Verdict pass within the stated tolerance, and the Mitsuba maps tier's own coefficients on the axis
    against the thin slab's closed form (the tool compares them with the analytic tier, which is code too).
    """
    from polinfra.exr import read_exr

    d = cwd / _opt(args, "--out")
    s = json.loads((d / "summary.json").read_text())
    assert s["verdict"] == "pass" and s["tier"] == _opt(args, "--tier") and s["spp"] == int(_opt(args, "--spp"))
    assert s["errors"]["zeta_worst_over_phi"]["max"] < s["tolerance"] <= 1e-3
    for f in ("figures/error_maps.png", "figures/zeta_error_hist.png"):
        assert (d / f).stat().st_size > 1000, f
    _axis_fresnel(read_exr(d / "scene" / "maps.exr"), _scene(args[1]))


def check_simulate(cwd: Path, args: list[str], out: str) -> None:
    """Spike count per step against integrate-and-fire: a pixel at photocurrent x (thresholds per step) fires
    x spikes per step on average, x = exposure * I + dark, I = 1/2 S0 behind a polarizer that turns through
    whole half turns (3 over 50 ms at 30 rev/s: the S1, S2 terms average out); S0 from the render's frames,
    trapezoid mean over time.  The .dat holds the same spikes, one bit per pixel-step.
    """
    import h5py

    from polinfra.exr import read_exr

    g = cwd / _opt(args, "--out")
    meta = json.loads((g / "group.json").read_text())
    cfg = meta["config"]
    H, W, rate = cfg["height"], cfg["width"], cfg["rate_hz"]
    n_steps = int(round(float(_opt(args, "--duration")) * rate))
    with h5py.File(g / "spikes.h5", "r") as f:
        sp = f["spikes"][:]
        assert sp.shape == (n_steps, H * W // 8) and sp.dtype == np.uint8
        assert f["gt/T"].shape[1:] == (H, W) and f["gt/T"].shape[0] == f["output/times_s"].shape[0] == meta["summary"]["n_output_frames"]
        phi = f["polarizer/phi_true_rad"][:]
    turns = (phi[-1] - phi[0]) / np.pi
    assert abs(turns - round(turns)) < 0.05, turns  # whole half turns: the closed form below holds
    count = int(_POPCOUNT[sp].sum())
    dat = np.fromfile(cwd / _opt(args, "--dat"), dtype=np.uint8)
    assert dat.size == n_steps * H * W // 8 and int(_POPCOUNT[dat].sum()) == count
    rd = cwd / args[1]
    frames = json.loads((rd / "render.json").read_text())["frames"]
    s0 = np.array([read_exr(rd / p, ["S0"])["S0"].mean() for p in frames])
    w = np.ones(s0.size)
    w[[0, -1]] = 0.5
    want = cfg["exposure"] * 0.5 * float((s0 * w).sum() / w.sum()) + cfg["dark_mean"]
    got = count / (n_steps * H * W)
    assert abs(got / want - 1) < 0.02, (got, want)  # measured 0.2 % (threshold and gain spreads, leakage)
    assert abs(meta["summary"]["mean_rate"] - got) < 1e-6


def check_calibrate(cwd: Path, args: list[str], out: str) -> None:
    """The phase and rate estimated from the spikes against the scene's polarizer (what the stream was made with)."""
    est = json.loads(out)
    pol = json.loads((cwd / args[1] / "group.json").read_text())["polarizer"]
    err = (est["phi0_deg"] - pol["phase_deg"] + 90) % 180 - 90  # a polarizer angle is defined modulo 180 deg
    assert abs(err) < 1.0, est  # measured 0.57 deg
    assert abs(est["rate_hz"] - pol["rate_hz"]) < 0.1, est  # measured 0.03 Hz
    assert est["verdict"] == "pass"


def check_reconstruct(cwd: Path, args: list[str], out: str) -> None:
    """T.mp4 decoded (8 bit -> linear through the stated display gain and 1/2.2 gamma) against the ground-truth T
    the simulator stored at the same output frames (frame j of the video is Eq. (3) frame K + j, K = 3): PSNR
    over 30 dB (measured 34.8 and 35.4 dB; the plain TFP image scores ~27 dB).
    """
    import h5py
    import imageio.v2 as iio

    d = cwd / _opt(args, "--out")
    meta = json.loads((d / "reconstruct.json").read_text())
    n = int(_opt(args, "--max-frames"))
    assert meta["frames"] == n and meta["nan_frames"] == 0
    vids = {k: np.stack(iio.mimread(d / f"{k}.mp4")) for k in ("T", "R", "preview")}
    H, W = meta["size"]
    assert vids["T"].shape[:3] == vids["R"].shape[:3] == (n, H, W), {k: v.shape for k, v in vids.items()}
    assert vids["preview"].shape[0] == n and vids["preview"].shape[2] >= 3 * W
    T = (vids["T"][..., 0].astype(np.float64) / 255) ** 2.2 / meta["display_gain"]["T"]
    with h5py.File(cwd / args[1] / "spikes.h5", "r") as f:
        gt = f["gt/T"][3 : 3 + n].astype(np.float64)
    for j in range(n):
        psnr = 10 * np.log10(1.0 / np.mean((T[j] - gt[j]) ** 2))
        assert psnr > 30.0, (j, psnr)
    z = json.loads((d / "zeta.json").read_text())["selfcal"]
    assert abs(np.degrees(np.arccos(abs(z["normal"][2]))) - _scene("brewster")["pane"]["tilt_deg"]) < 1.5, z["normal"]


def check_dataset_build(cwd: Path, args: list[str], out: str) -> None:
    """The groups of the manifest, each a complete group of its size and duration."""
    import h5py

    man = tomllib.loads((cwd / args[2]).read_text())
    d = cwd / _opt(args, "--out")
    ds = json.loads((d / "dataset.json").read_text())
    got, want = [(g["name"], g["split"]) for g in ds["groups"]], [(g["name"], g["split"]) for g in man["groups"]]
    assert ds["complete"] and got == want, ("groups built, in the manifest", got, want)
    cam, dur = man["defaults"]["camera"], man["defaults"]["duration_s"]
    for g in ds["groups"]:
        with h5py.File(d / g["path"] / "spikes.h5", "r") as f:
            sp = f["spikes"]
            assert sp.shape == (int(round(dur * 20000)), cam["width"] * cam["height"] // 8), (g["name"], sp.shape)
            rate = int(_POPCOUNT[sp[:]].sum()) / (sp.shape[0] * cam["width"] * cam["height"])
        assert 0.005 < rate < 1.0, (g["name"], rate)


def check_dataset_inspect(cwd: Path, args: list[str], out: str) -> None:
    """The drawn files; zeta from paper Eq. (2) of the stored maps at the frame's angle, the mixed light from
    Eq. (1); the frame's 13-step counts average to exposure x that light (integrate-and-fire).
    """
    d = cwd / _opt(args, "--out")
    info = json.loads((d / "inspect.json").read_text())
    for f in info["files"]:
        assert (d / f).stat().st_size > 1000, f
    a = np.load(d / "inspect_data.npz")
    dphi = float(a["phi_true"]) - a["phi_perp"].astype(np.float64)
    zeta = a["R_perp"] * np.cos(dphi) ** 2 + a["R_par"] * np.sin(dphi) ** 2
    np.testing.assert_allclose(a["zeta"], zeta, atol=1e-6)
    np.testing.assert_allclose(a["mixed_gt"], 0.5 * (zeta * a["R"] + (1 - zeta) * a["T"]), atol=1e-5)
    assert 0 <= a["dop"].min() and a["dop"].max() <= 1
    assert abs(float(a["mixed_I"].mean()) / (float(a["exposure"]) * float(a["mixed_gt"].mean())) - 1) < 0.1  # 2560 px x 13 steps


def check_evaluate(cwd: Path, args: list[str], out: str) -> None:
    """One overall row per method and baseline, over the manifest's test groups, each on --max-frames frames, PSNR
    in a plausible range; the table's files agree; the TFP row's PSNR equals the one computed here from the raw spikes.
    """
    d = cwd / _opt(args, "--out")
    res = json.loads((d / "results.json").read_text())
    built = json.loads((cwd / args[1] / "dataset.json").read_text())
    want = [g["name"] for g in built["groups"] if g["split"] == _opt(args, "--split")]
    assert res["config"]["groups"] == want and len(want) == 1
    methods = _opt(args, "--method").split(",")
    rows = {r["method"]: r for r in res["rows"] if r["group"] == "overall"}
    assert set(methods) | {"tfp", "best_frame", "spike_mean"} <= set(rows), sorted(rows)
    for m, r in rows.items():
        assert r["n_frames"] == int(_opt(args, "--max-frames")), (m, r)
        assert 10 < r["psnr_T"] < 60 and 0 < r["ssim_T"] <= 1, (m, r)
    csv = (d / "results.csv").read_text()
    assert f"{rows['full']['psnr_T']:.2f}" in (d / "results.md").read_text() and "full" in csv
    hand = _tfp_psnr(cwd / args[1] / "groups" / want[0], rows["tfp"]["n_frames"])
    assert rows["tfp"]["psnr_T"] == pytest.approx(hand, abs=1e-4), ("TFP PSNR: table, by hand", rows["tfp"]["psnr_T"], hand)


def _tfp_psnr(group: Path, n_frames: int, K: int = 3, w: int = 13, stride_deg: float = 31.5) -> float:
    """Mean T PSNR of the TFP baseline over the first ``n_frames`` frames with K Eq. (3) frames on each side, from its
    definition: frame m is centred on the step where the mid-step polarizer angle has turned by m x stride since
    t = 0 (rounded to a step); T = 2 x the mean of the 2K + 1 w-step spike counts / (w x exposure) around the centres;
    PSNR = 10 log10(1 / MSE) against the T stored for that step, the estimate clipped to [0, 1].
    """
    import h5py

    meta = json.loads((group / "group.json").read_text())
    exposure = meta["config"]["exposure"]
    with h5py.File(group / "spikes.h5", "r") as f:
        H, W = f["gt/T"].shape[1:]
        phi = f["polarizer/phi_nominal_rad"][:]
        turned = phi - np.radians(meta["polarizer"]["phase_deg"])  # the nominal angle at t = 0 is the phase
        c = np.rint(np.interp(np.arange(0.0, turned[-1], np.radians(stride_deg)), turned, np.arange(phi.size))).astype(int)
        c = c[c >= w // 2]
        gt_at = {int(s): j for j, s in enumerate(f["output/step_index"][:])}
        out = []
        for i in range(K, K + n_frames):
            I = [np.unpackbits(f["spikes"][c[k] - w // 2 : c[k] + w // 2 + 1], axis=1, bitorder="little")[:, : H * W].sum(0) / (w * exposure) for k in range(i - K, i + K + 1)]
            T = np.clip(2.0 * np.mean(I, 0).reshape(H, W), 0.0, 1.0)
            out.append(10 * np.log10(1.0 / np.mean((T - f["gt/T"][gt_at[int(c[i])]].astype(np.float64)) ** 2)))
    return float(np.mean(out))


CHECKS: dict[tuple[str, ...], Callable[[Path, list[str], str], None]] = {
    ("--version",): check_version,
    ("zeta",): check_zeta,
    ("render",): check_render,
    ("validate-zeta",): check_validate_zeta,
    ("simulate",): check_simulate,
    ("calibrate",): check_calibrate,
    ("reconstruct",): check_reconstruct,
    ("dataset", "build"): check_dataset_build,
    ("dataset", "inspect"): check_dataset_inspect,
    ("evaluate",): check_evaluate,
}


def tour_check(args: list[str]) -> Callable[[Path, list[str], str], None] | None:
    for key in sorted(CHECKS, key=len, reverse=True):
        if tuple(args[: len(key)]) == key:
            return CHECKS[key]
    return None
