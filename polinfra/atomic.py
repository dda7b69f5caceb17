"""Atomic file output: write to a temporary name in the same folder, then rename.

Nothing is ever half-written under its final name: a crash leaves at most a
``*.tmp-*`` file, which the next run may delete.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from polinfra.errors import OutputError
from polinfra.faults import fault_point

__all__ = ["atomic_path", "write_bytes", "write_json", "write_text", "ensure_dir", "json_safe"]


def ensure_dir(path: str | os.PathLike) -> Path:
    """Create ``path`` (and parents) or raise :class:`OutputError` saying why."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create output folder {p}: {exc.strerror}; choose a writable --out") from None
    if not os.access(p, os.W_OK):
        raise OutputError(f"output folder {p} is not writable; choose a writable --out")
    return p


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``final``; rename it to ``final`` on success.

    Args:
        final: the destination file.
        suffix: suffix of the temporary name (defaults to the final suffix, so
            writers that look at extensions, such as image libraries, work).
    """
    final = Path(final)
    ensure_dir(final.parent)
    sfx = final.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.tmp-", suffix=sfx, dir=final.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual file mode
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        fault_point(f"atomic:{final.name}")  # test-only kill -9 injection (polinfra.faults)
        os.replace(tmp_path, final)
    except OSError as exc:
        tmp_path.unlink(missing_ok=True)
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            raise OutputError(f"no space left (or file size limit reached) while writing {final}; free space or choose another --out") from None
        if exc.errno in (errno.EACCES, errno.EROFS, errno.EPERM):
            raise OutputError(f"cannot write {final}: {exc.strerror}; choose a writable --out") from None
        raise
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        errno_ = getattr(exc, "errno", None) or getattr(getattr(exc, "__cause__", None), "errno", None)
        if errno_ in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG) or "No space left" in str(exc) or "File too large" in str(exc):
            raise OutputError(f"no space left (or file size limit reached) while writing {final}; free space or choose another --out") from None
        raise


def finish_atomic(ctx: contextlib.AbstractContextManager, ok: bool) -> None:
    """Leave an :func:`atomic_path` context entered by hand (a writer object that spans calls):
    publish the file when ``ok``, otherwise delete the temporary file and publish nothing.
    """
    if ok:
        ctx.__exit__(None, None, None)
        return
    err = RuntimeError("aborted")
    try:
        ctx.__exit__(RuntimeError, err, None)
    except RuntimeError:
        pass


def write_bytes(final: str | os.PathLike, data: bytes) -> Path:
    """Atomically write ``data`` to ``final`` (fsync before rename)."""
    with atomic_path(final) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(final)


def write_text(final: str | os.PathLike, text: str) -> Path:
    """Atomically write UTF-8 ``text`` to ``final``."""
    return write_bytes(final, text.encode("utf-8"))


def write_json(final: str | os.PathLike, obj: Any) -> Path:
    """Atomically write ``obj`` as indented JSON (NaN/Inf rejected)."""
    return write_text(final, json.dumps(obj, indent=2, sort_keys=True, allow_nan=False, default=_json_default) + "\n")


def json_safe(o: Any) -> Any:
    """A copy of ``o`` that :func:`write_json` takes: non-finite floats -> None (JSON has no inf / NaN; a result that
    holds one says so as null instead of failing the write), numpy scalars -> Python.
    """
    import math

    import numpy as np

    if isinstance(o, dict):
        return {k: json_safe(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [json_safe(v) for v in o]
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(float(o)) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
