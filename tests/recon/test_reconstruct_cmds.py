"""CLI wiring of `polspike evaluate` and `polspike bench reconstruct`."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from polspike.cli import get_app


def test_evaluate_synthetic(tmp_path):
    r = CliRunner().invoke(get_app(), ["evaluate", "synthetic:3", "--out", str(tmp_path), "--synthetic-groups", "1", "--synthetic-frames", "8", "--synthetic-size", "40x24", "--quiet"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "results.csv").is_file() and (tmp_path / "figure.png").is_file()
    assert "rwps" in r.output


def test_evaluate_bad_method_is_a_one_line_error(tmp_path, polspike_main):
    r = polspike_main("evaluate", "synthetic", "--method", "svd", "--out", tmp_path / "e", "--quiet")
    polspike_main.one_line_exit_2(r, "svd")
    assert not (tmp_path / "e" / "results.csv").exists()


def test_evaluate_bad_self_fov_is_a_one_line_error(tmp_path, polspike_main):
    r = polspike_main("evaluate", "synthetic", "--zeta", "self", "--self-fov", "lens", "--out", tmp_path / "e", "--quiet")
    polspike_main.one_line_exit_2(r, "self_fov")
    assert not (tmp_path / "e" / "results.csv").exists()


def test_bench_reconstruct_small(tmp_path):
    r = CliRunner().invoke(get_app(), ["bench", "reconstruct", "--out", str(tmp_path), "--width", "32", "--height", "24", "--repeats", "1", "--batch", "2"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "reconstruct.json").read_text())
    assert res["results"]["cpu"]["rwps"]["fps"] > 0 and "rwps_over_ls_time" in res["results"]["cpu"]["ratios"]


def test_bench_reconstruct_device_selection(tmp_path):
    import torch

    args = ["bench", "reconstruct", "--out", str(tmp_path), "--width", "24", "--height", "16", "--repeats", "1", "--batch", "1"]
    r = CliRunner().invoke(get_app(), [*args, "--device", "cpu"])
    assert r.exit_code == 0, r.output
    res = json.loads((tmp_path / "reconstruct.json").read_text())
    assert list(res["results"]) == ["cpu"] and res["skipped"] == {}
    if not torch.cuda.is_available():
        bad = CliRunner().invoke(get_app(), [*args, "--device", "cuda"])
        assert bad.exit_code != 0 and "CUDA" in str(bad.exception)
