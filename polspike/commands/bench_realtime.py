"""``polspike bench realtime``: real-time factor of the live physics path per stage and end to end, beside the
streaming path in the same run; latency of --follow at real time; peak memory of a long stream.
"""

from __future__ import annotations

from pathlib import Path

import typer

from polspike.cli import bench_app


@bench_app.command("realtime")
def bench_realtime_cmd(
    out: Path = typer.Option(Path("out/bench/realtime"), "--out", help="output folder: realtime.json, realtime.md"),
    width: int = typer.Option(400, "--width", help="frame width (H W divisible by 8)"),
    height: int = typer.Option(250, "--height", help="frame height"),
    short_s: float = typer.Option(0.25, "--short-s", help="the shorter recording of the marginal throughput, seconds"),
    long_s: float = typer.Option(1.0, "--long-s", help="the longer recording, seconds"),
    methods: str = typer.Option("ls,rwps+rir", "--methods", help="comma-separated: ls, rwps, ls+rir, rwps+rir (+rir = RIR on)"),
    memory_s: float = typer.Option(60.0, "--memory-s", help="length of the constant-memory run, seconds (0 = skip)"),
    latency_s: float = typer.Option(1.0, "--latency-s", help="seconds written at real time for the --follow latency (0 = skip)"),
    reference: bool = typer.Option(True, "--reference/--no-reference", help="also run the streaming path (the ratio)"),
    video: bool = typer.Option(True, "--video/--no-video", help="write and time the MP4s"),
    variants: str = typer.Option("torch", "--live-variants", help="comma-separated live-path settings also run, each a ratio: torch (torch solvers and RIR fit, CRF-10 videos with the preview: the live path before its fused kernels), high-video (CRF 10 with the preview), preview (the defaults plus preview.mp4), coarse-rir, threads2 (the fused RWPS on two numba threads), gray-video (4:0:0 H.264), y4m (raw .y4m, no encoder), serial (rwps: the solve on the stream's thread, no solve thread), unshared (rwps: the stream's thread does not take pixel rows of the solve); '' for none"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress lines"),
) -> None:
    """Frames/s (wall and CPU) of the live path and the streaming path, per-stage real-time factors, --follow latency, peak RSS."""
    from rich.console import Console

    from polinfra.atomic import write_json, write_text
    from polinfra.errors import ConfigError
    from reconstruct.evaluate.realtime_bench import LIVE_VARIANTS, bench_realtime, realtime_markdown

    ms = tuple(m.strip() for m in methods.split(",") if m.strip())
    bad = [m for m in ms if m not in ("ls", "rwps", "ridge", "irls", "ls+rir", "rwps+rir", "ridge+rir", "irls+rir")]
    if bad or not ms:
        raise ConfigError(f"--methods {methods!r}: choose among ls, rwps, ridge, irls, each optionally +rir")
    vs = tuple(v.strip() for v in variants.split(",") if v.strip())
    if [v for v in vs if v not in LIVE_VARIANTS]:
        raise ConfigError(f"--live-variants {variants!r}: choose among {', '.join(LIVE_VARIANTS)}")
    if not 0 < short_s < long_s:
        raise ConfigError(f"--short-s {short_s} / --long-s {long_s}: need 0 < short < long")
    if (height * width) % 8:
        raise ConfigError(f"{width} x {height}: a .dat frame needs H W divisible by 8")
    con = Console(stderr=True)
    res = bench_realtime(width, height, short_s, long_s, memory_s, latency_s, ms, reference, video, progress=None if quiet else (lambda s: con.print(f"[dim]{s}[/]")), variants=vs)
    md = realtime_markdown(res)
    write_json(out / "realtime.json", res)
    write_text(out / "realtime.md", md)
    Console().print(md)
    Console().print(f"wrote {out / 'realtime.json'}, {out / 'realtime.md'}")
