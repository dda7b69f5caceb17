"""``bench reconstruct-net`` pieces: the FLOP count against the closed form of a convolution, and a
two-model run on tiny frames (ratios, table) in seconds.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch

from reconstruct.evaluate.bench import bench_reconstruct_net, count_flops, net_table
from reconstruct.net.network import NetConfig, PolSpikeNet, init_weights


class _OneConv(torch.nn.Module):
    """A model-like object whose cost is one 3x3 convolution N -> 5 channels (2 Cin Cout k^2 H W FLOPs)."""

    def __init__(self, n_obs=7):
        super().__init__()
        self.cfg = SimpleNamespace(n_obs=n_obs, inputs=frozenset())
        self.pad_multiple = 8
        self.conv = torch.nn.Conv2d(n_obs, 5, 3, padding=1)

    def forward(self, I, phi):
        y = self.conv(I)
        return SimpleNamespace(T=y[:, 0], R=y[:, 1], T_base=y[:, 2], R_base=y[:, 3])


def test_flop_count_matches_the_convolution_closed_form():
    m = _OneConv()
    # 250 rows are padded to 256 (pad_multiple 8), as the stream pads them
    assert count_flops(m, 250, 400) == 2 * 7 * 5 * 9 * 256 * 400


def test_two_model_run_gives_ratios_and_a_table(tmp_path):
    small = dict(use_rir=False, ref_ch=(8, 8, 8), dec_ch=(8, 8, 8))
    v1 = init_weights(PolSpikeNet(NetConfig(arch="v1", feat_ch=16, **small)), torch.Generator().manual_seed(0)).eval()
    v2 = init_weights(PolSpikeNet(NetConfig(arch="v2", lr_ch=8, w_ch=4, **small)), torch.Generator().manual_seed(0)).eval()
    res = bench_reconstruct_net({"v1": v1, "v2": v2}, height=24, width=40, frames=1, threads=(1,), variants=False, stream_frames={"v2": 2}, work_dir=tmp_path)
    r1, r2 = res["models"]["v1"], res["models"]["v2"]
    assert r1["gflop_per_frame"] > r2["gflop_per_frame"] > 0
    q = res["ratios"]["v2"]
    assert abs(q["flops_reduction"] - r1["gflop_per_frame"] / r2["gflop_per_frame"]) < 1e-9
    assert r2["reconstruct"]["frames"] == 2 and r2["reconstruct"]["feature_cache"]["encoded_frames"] == 2 + 6
    t = net_table(res)
    assert "GFLOP / frame" in t and f"{r1['parameters']:,}" in t and "v2 vs v1" in t


def test_cli_bench_with_the_shipped_default_times_its_training(tmp_path, polspike_cli):
    """`polspike bench reconstruct-net` on the shipped default (a network that reads the long spike mean and the wide
    windows) against v1: its training items carry what each network reads (without them the run stopped with
    "a use_mean network needs I_mean"); tiny frames, a few steps.
    """
    import json

    out = tmp_path / "bn.json"
    r = polspike_cli("bench", "reconstruct-net", "--height", "24", "--width", "40", "--frames", "1", "--stream-frames", "2", "--train-steps", "3",
                     "--no-variants", "--threads", "1", "--json", out, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(out.read_text())
    new = [m for name, m in res["models"].items() if "polspike_v1.pt" not in name][0]
    assert new["train_1thr"] and new["reconstruct"] and new["gflop_per_frame"] > 0
