"""``polspike train --nproc N``: N data-parallel training processes on this machine, started by torchrun.

The launch is ``python -m torch.distributed.run --standalone --nproc-per-node N -m polspike train ...`` (the
same command line without ``--nproc``), so a single-machine run and a multi-machine ``torchrun`` run take the
one code path of :mod:`reconstruct.net.distributed`.  torchrun stops every rank when one fails (a rank killed,
an error); the run then resumes from its last checkpoint with the same command, with any N.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

__all__ = ["torchrun_command", "launch_local"]

log = logging.getLogger(__name__)


def torchrun_command(nproc: int, train_args: list[str]) -> list[str]:
    """The torchrun command line of ``polspike train TRAIN_ARGS`` on ``nproc`` local processes."""
    verbose = ["-v"] if logging.getLogger().getEffectiveLevel() <= logging.INFO else []
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes", "1", "--nproc-per-node", str(nproc), "-m", "polspike", *verbose, "train", *train_args]


def launch_local(nproc: int, train_args: list[str]) -> int:
    """Run the training on ``nproc`` local ranks; returns the exit code for the CLI (0, or 1 when a rank failed)."""
    env = dict(os.environ)
    # one rank per share of the cores (torchrun would set 1 and warn)
    env.setdefault("OMP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // nproc)))
    cmd = torchrun_command(nproc, train_args)
    log.info("launching %s", " ".join(cmd))
    rc = subprocess.run(cmd, env=env).returncode
    if rc != 0:
        from rich.console import Console

        Console(stderr=True).print(f"[bold red]error:[/] a training process failed (torchrun exit {rc}); the same command resumes from the last checkpoint", highlight=False, soft_wrap=True)
        return 1
    return 0
