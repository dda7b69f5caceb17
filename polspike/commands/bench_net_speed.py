"""``polspike bench net-speed``: the network path's CPU cost with ``--fast`` / ``--compile``, as ratios to the default path in one run."""

from __future__ import annotations

from pathlib import Path

import typer

from polspike.cli import bench_app


@bench_app.command("net-speed")
def bench_net_speed_cmd(
    out: Path = typer.Option(Path("out/bench/net_speed"), "--out", help="output folder: net_speed.json, net_speed.md"),
    width: int = typer.Option(400, "--width", help="frame width (H W divisible by 8)"),
    height: int = typer.Option(250, "--height", help="frame height"),
    frames: int = typer.Option(12, "--frames", help="timed output frames per variant (even: two windows per forward pass)"),
    variants: str = typer.Option("default,fast", "--variants", help="comma-separated, the first the reference: default, fast, compile, fast+compile, fast+bf16, fast+bf16+compile (compile: torch.compile, needs a C++ compiler, minutes of compile time on 2 cores; bf16: the learned layers in bfloat16 where the CPU has AMX or AVX-512 BF16)"),
    threads: int = typer.Option(1, "--threads", help="torch threads"),
    rir: str = typer.Option("window", "--rir", help="the windows' RIR shifts: window | chained (as polspike reconstruct --rir)"),
    weights: str = typer.Option("default", "--weights", help="comma-separated checkpoints (files, or the shipped default | fast), each run under every variant; the first row is the reference (e.g. default,fast with --variants default,fast+compile: the real-time network against the default in one run)"),
) -> None:
    """CPU seconds per frame by stage of the network's streaming path, per checkpoint and speed-up variant, beside the first (the reference), with how far T and R move."""
    from rich.console import Console

    from polinfra.atomic import json_safe, write_json, write_text
    from polinfra.errors import ConfigError
    from reconstruct.evaluate.net_speed_bench import NET_SPEED_VARIANTS, bench_net_speed, net_speed_markdown

    vs = tuple(v.strip() for v in variants.split(",") if v.strip())
    if not vs or [v for v in vs if v not in NET_SPEED_VARIANTS]:
        raise ConfigError(f"--variants {variants!r}: choose among {', '.join(NET_SPEED_VARIANTS)}")
    if frames < 2 or frames % 2:
        raise ConfigError(f"--frames {frames}: an even number >= 2 (two windows per forward pass)")
    if (height * width) % 8:
        raise ConfigError(f"{width} x {height}: a .dat frame needs H W divisible by 8")
    if threads < 1:
        raise ConfigError(f"--threads {threads}: at least 1")
    if rir not in ("window", "chained"):
        raise ConfigError(f"--rir {rir!r}: choose window or chained")
    from reconstruct.net.checkpoint import resolve_weights

    ws = tuple(w.strip() for w in weights.split(",") if w.strip())
    missing = [w for w in ws if not resolve_weights(w).is_file()]
    if not ws or missing:
        raise ConfigError(f"--weights {weights!r}: {', '.join(missing) or 'empty'} is neither a checkpoint file nor default / fast")
    con = Console(stderr=True)
    res = bench_net_speed(width, height, frames, vs, threads, rir, progress=lambda s: con.print(f"[dim]{s}[/]"), weights=ws)
    md = net_speed_markdown(res)
    write_json(out / "net_speed.json", json_safe(res))  # an identical other network's PSNR (inf) as null
    write_text(out / "net_speed.md", md)
    Console().print(md)
    Console().print(f"wrote {out / 'net_speed.json'}, {out / 'net_speed.md'}")
