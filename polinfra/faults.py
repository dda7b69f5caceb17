"""Test-only fault injection: make this process ``kill -9`` itself at a named point.

Set ``POLSPIKE_FAULT_AT=POINT`` (or ``POINT@N``: at the N-th time the point is reached in
this process, default 1) and the process sends itself SIGKILL there: no ``finally``, no
``atexit``, exactly like a power cut or the OOM killer.  Unset (always, outside the tests)
a fault point costs one environment lookup.  The crash-resume tests use it to kill a build
or a training run at a precise moment.

Points:

* ``atomic:NAME`` - in :func:`polinfra.atomic.atomic_path`, after the temporary file of the
  final file called NAME has been written completely and before it is renamed over NAME
  (e.g. ``atomic:dataset.json``, ``atomic:last.pt``, ``atomic:checksums.json``);
* ``dataset.publish`` - in ``polspike.pipeline.dataset.build_group``, a finished group in
  ``DIR/.tmp`` just before the rename that publishes it under ``DIR/groups``;
* ``train.step.rank<R>`` - in a data-parallel training run (``reconstruct.net.distributed``), rank R after each
  of its optimizer steps (e.g. ``train.step.rank1@3``: rank 1 dies after its 3rd step; the other ranks
  see it when their next collective fails and torchrun stops them).
"""

from __future__ import annotations

import os
import signal
from collections import Counter

ENV = "POLSPIKE_FAULT_AT"
_hits: Counter[str] = Counter()

__all__ = ["ENV", "fault_point"]


def fault_point(name: str) -> None:
    """SIGKILL this process if ``POLSPIKE_FAULT_AT`` names ``name`` (at its N-th hit)."""
    spec = os.environ.get(ENV)
    if not spec:
        return
    target, _, nth = spec.partition("@")
    if target != name:
        return
    _hits[name] += 1
    if _hits[name] == (int(nth) if nth else 1):
        os.kill(os.getpid(), signal.SIGKILL)
