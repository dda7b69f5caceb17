"""Opt-in inference speed-ups of the shipped network (reconstruct.net.inference) against the default path as the oracle.

``fast`` (channels-last convolutions) sums the convolutions in another order: T and R must stay within float32
rounding of the default (TOL), on a physical window with the inputs the shipped network reads.  ``compile`` without a
C++ compiler, or when compiling fails, must run the eager network: every float equal to the default.  ``bf16`` (the
learned layers in bfloat16) must really compute them in bfloat16 where the CPU has it natively, move T and R by no more
than bfloat16's rounding carried through the refinement (TOL_BF16), and leave every float as it was where it does not.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, load_model
from reconstruct.net.inference import accelerate, cxx_compiler, native_bf16
from reconstruct.stream.window_inputs import WindowInputs
from reconstruct.video.tiling import run_model_on_windows

N, H, W = 7, 44, 60
TOL = 1e-5
"""Largest |change| of T or R allowed, layer units (1.0 = the brightest layer value): float32 rounding of the
convolutions carried through the refinement (``fast``: measured at most 3.6e-7 on these windows; the compiled network
at most 8.1e-5 at 400 x 250 on the pane stream of polspike bench net-speed: TOL_COMPILE)."""
TOL_COMPILE = 2e-4
TOL_BF16 = (2e-3, 1e-2)
"""``bf16``: the largest RMS and the largest |change| of T or R, layer units.  bfloat16 keeps 8 significant bits (a
relative rounding of 2**-9 = 2e-3 per value); the refinement's layers carry it to its corrections (measured on the
windows of seeds 0-5: RMS at most 9.0e-4, |change| at most 3.6e-3); the test split moves by at most 0.01 dB (docs/realtime.md)."""


def _net():
    return load_model(DEFAULT_WEIGHTS, "cpu", use_rir=True, floor=True)[0]


def _window(seed: int = 0):
    """One window of paper Eq. (1)-(2) on smooth random T, R, Poisson spike counts at exposure 2 over 13 steps, with the
    long mean, its first harmonic, the wide windows (the same counts), the exposure and the span's steps.
    """
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    T = 0.15 + 0.6 * gaussian_filter(rng.random((H, W)), 2.0)
    R = 0.1 + 0.4 * gaussian_filter(rng.random((H, W)), 3.0)
    phi = (np.arange(N) - N // 2) * math.radians(31.5)
    perp = np.linspace(0.2, 1.1, W)[None, :] + 0.0 * T
    zeta = 0.3 * np.cos(phi[:, None, None] - perp) ** 2 + 0.04 * np.sin(phi[:, None, None] - perp) ** 2
    mix = 0.5 * (zeta * R + (1 - zeta) * T)
    exposure, steps = 2.0, 13
    I = rng.poisson(mix * exposure * steps) / (exposure * steps)
    ang = np.linspace(0, math.pi, 64, endpoint=False)
    zl = 0.3 * np.cos(ang[:, None, None] - perp) ** 2 + 0.04 * np.sin(ang[:, None, None] - perp) ** 2
    ml = 0.5 * (zl * R + (1 - zl) * T)
    I_mean = ml.mean(0)
    I_harm = np.stack([(ml * np.cos(2 * ang)[:, None, None]).mean(0), (ml * np.sin(2 * ang)[:, None, None]).mean(0)])
    f32 = lambda a: np.asarray(a, np.float32)[None]  # noqa: E731
    x = WindowInputs(f32(I), f32(phi), f32(I_mean), f32(I_harm), f32(I), exposure=exposure, span_steps=350, shifts=np.zeros((1, N, 2)))
    return x, f32(zeta)


def _run(net, x, zeta):
    return run_model_on_windows(net, x, "cpu", 0, zeta=zeta)


def test_fast_is_the_default_within_float_rounding():
    x, zeta = _window()
    ref = _run(_net(), x, zeta)
    net = _net()
    stats = accelerate(net, fast=True)
    assert stats.status == "off"
    assert net.refine.e1[0].conv.weight.is_contiguous(memory_format=torch.channels_last)
    got = _run(net, x, zeta)
    for k in ("T", "R", "T_base", "R_base"):
        assert np.isfinite(got[k]).all()
        assert np.abs(got[k] - ref[k]).max() <= TOL, k
    assert np.abs(ref["T"]).max() > 0.1  # a real separation, not zeros compared with zeros


def test_compile_without_a_compiler_runs_the_eager_network(monkeypatch):
    import reconstruct.net.inference as inf

    x, zeta = _window(1)
    ref = _run(_net(), x, zeta)
    monkeypatch.setattr(inf, "cxx_compiler", lambda: None)
    net = _net()
    stats = accelerate(net, compile_=True)
    assert stats.status.startswith("eager: no C++ compiler")
    got = _run(net, x, zeta)
    assert all(np.array_equal(got[k], ref[k]) for k in ref)


def test_compile_failure_falls_back_to_the_eager_network(monkeypatch):
    def broken(fn, **kw):
        def run(*a, **k):
            raise RuntimeError("C++ compile error: cannot find cstdint")

        return run

    monkeypatch.setattr(torch, "compile", broken)
    x, zeta = _window(2)
    ref = _run(_net(), x, zeta)
    net = _net()
    stats = accelerate(net, compile_=True)
    got = _run(net, x, zeta)
    assert stats.status.startswith("eager:") and "RuntimeError" in stats.status
    assert all(np.array_equal(got[k], ref[k]) for k in ref)


@pytest.mark.slow
@pytest.mark.skipif(cxx_compiler() is None, reason="torch.compile needs a C++ compiler")
@pytest.mark.skipif(not os.environ.get("POLSPIKE_TEST_COMPILE"), reason="compiling the network takes minutes on 2 cores: set POLSPIKE_TEST_COMPILE=1 (polspike bench net-speed --variants default,fast+compile measures the same)")
def test_compiled_network_is_the_default_within_float_rounding():
    x, zeta = _window(3)
    ref = _run(_net(), x, zeta)
    net = _net()
    stats = accelerate(net, fast=True, compile_=True)
    got = _run(net, x, zeta)
    assert stats.status == "on" and stats.first_calls == 1
    for k in ("T", "R"):
        assert np.abs(got[k] - ref[k]).max() <= TOL_COMPILE, k


@pytest.mark.skipif(not native_bf16(), reason="this CPU has no native bfloat16 (AMX or AVX-512 BF16)")
def test_bf16_runs_the_layers_in_bfloat16_within_its_rounding():
    x, zeta = _window(4)
    ref = _run(_net(), x, zeta)
    net = _net()
    stats = accelerate(net, fast=True, bf16=True)
    seen = []
    net.refine.e1[0].conv.register_forward_hook(lambda m, a, out: seen.append(out.dtype))
    net.param.enc[0].conv.register_forward_hook(lambda m, a, out: seen.append(out.dtype))
    got = _run(net, x, zeta)
    assert stats.bf16 == "on" and seen and set(seen) == {torch.bfloat16}  # the convolutions did run in bfloat16
    for k in ("T", "R"):
        d = got[k].astype(np.float64) - ref[k]
        assert got[k].dtype == np.float32 and np.isfinite(got[k]).all()
        assert np.sqrt(np.mean(d**2)) <= TOL_BF16[0] and np.abs(d).max() <= TOL_BF16[1], k
        assert np.abs(d).max() > 0  # bfloat16 did change the floats: the comparison is not of one path with itself


def test_bf16_without_native_support_keeps_float32(monkeypatch, caplog):
    import reconstruct.net.inference as inf

    x, zeta = _window(5)
    ref = _run(_net(), x, zeta)
    monkeypatch.setattr(inf, "native_bf16", lambda device="cpu": False)
    net = _net()
    with caplog.at_level("WARNING", logger="reconstruct.net.inference"):
        stats = accelerate(net, bf16=True)
    assert stats.bf16.startswith("off: no native bfloat16") and "float32" in caplog.text
    got = _run(net, x, zeta)
    assert all(np.array_equal(got[k], ref[k]) for k in ref)


@pytest.mark.parametrize("flag", ["--fast", "--bf16"])
def test_cli_refuses_speedups_for_a_physics_solver(tmp_path, flag):
    exe = Path(sys.executable).with_name("polspike")
    (tmp_path / "x.dat").write_bytes(bytes(8 * 400))  # 400 steps of an 8 x 8 sensor, no spikes
    r = subprocess.run([str(exe) if exe.exists() else "polspike", "reconstruct", str(tmp_path / "x.dat"), "--out", str(tmp_path / "o"), "--height", "8", "--width", "8",
                        "--phi0-deg", "0", "--rev-per-s", "30", "--method", "rwps", flag], capture_output=True, text=True)
    assert r.returncode == 2
    assert f"{flag} speeds up the network" in r.stderr + r.stdout and "Traceback" not in r.stderr


def test_net_speed_bench_reports_the_fast_path_against_the_default(tmp_path):
    from reconstruct.evaluate.net_speed_bench import bench_net_speed, net_speed_markdown

    res = bench_net_speed(48, 32, frames=2, variants=("default", "fast"), workdir=str(tmp_path))
    fast = res["variants"]["fast"]
    assert res["reference"] == "default" and fast["ratio_cpu"] > 0 and fast["cpu_s_per_frame"]["model"] > 0
    assert max(fast["max_abs_change"].values()) <= TOL
    assert "| fast |" in net_speed_markdown(res)


def test_net_speed_cli_rejects_an_unknown_variant(tmp_path):
    exe = Path(sys.executable).with_name("polspike")
    r = subprocess.run([str(exe) if exe.exists() else "polspike", "bench", "net-speed", "--variants", "default,turbo", "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "turbo" in r.stderr + r.stdout and "Traceback" not in r.stderr


def test_named_weights_are_the_shipped_files_and_a_file_of_that_name_wins(tmp_path, monkeypatch):
    from reconstruct.net.checkpoint import DEFAULT_WEIGHTS, FAST_WEIGHTS, resolve_weights

    assert resolve_weights(None) == DEFAULT_WEIGHTS and resolve_weights("default") == DEFAULT_WEIGHTS and resolve_weights("fast") == FAST_WEIGHTS
    assert FAST_WEIGHTS.is_file() and DEFAULT_WEIGHTS.is_file()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "fast").write_bytes(b"x")
    assert resolve_weights("fast") == Path("fast")  # a file the user names is never shadowed


def test_fast_weights_are_a_smaller_network_that_the_stream_runs_by_name(tmp_path):
    """The real-time checkpoint: the default's design, a third of its parameters and convolution work or less, RIR on
    as trained; the bench runs it beside the default and reports how far its frames lie from the default's.
    """
    from reconstruct.evaluate.bench import count_flops
    from reconstruct.evaluate.net_speed_bench import bench_net_speed, net_speed_markdown
    from reconstruct.net.checkpoint import load_model

    fast, dflt = load_model("fast")[0], load_model("default")[0]
    assert fast.cfg.use_rir and fast.cfg.base == dflt.cfg.base and fast.cfg.use_mean
    n = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert n(fast) < n(dflt) / 3
    assert count_flops(fast, 64, 96) < count_flops(dflt, 64, 96) / 3
    res = bench_net_speed(48, 32, frames=2, variants=("default",), workdir=str(tmp_path), weights=("default", "fast"))
    row = res["variants"]["fast:default"]
    assert res["reference"] == "default:default" and row["ratio_cpu"] > 0 and "max_abs_change" not in row
    assert 5.0 < row["psnr_vs_reference"]["T"] < 100.0  # another network: near the default's frames, not equal to them
    assert "| fast:default |" in net_speed_markdown(res)


def test_net_speed_cli_rejects_unknown_weights(tmp_path):
    exe = Path(sys.executable).with_name("polspike")
    r = subprocess.run([str(exe) if exe.exists() else "polspike", "bench", "net-speed", "--weights", "default,nosuch.pt", "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "nosuch.pt" in r.stderr + r.stdout and "default / fast" in r.stderr + r.stdout and "Traceback" not in r.stderr
