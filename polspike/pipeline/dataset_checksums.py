"""Checksums of built dataset groups: file sha256, the content checksum and the group-file check.

Used by :mod:`polspike.pipeline.dataset` (build, resume, verify); the definitions are in that
module's docstring ("Checksums and byte identity").
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from polinfra.errors import DataFormatError

__all__ = [
    "DATASET_FORMAT",
    "CHECKSUMS_FILE",
    "SPEC_FILE",
    "GROUP_FILES",
    "VOLATILE_KEYS",
    "CHECKSUM_DEFINITION",
    "file_sha256",
    "content_sha256",
    "verify_group_files",
]

DATASET_FORMAT = "polspike-dataset/1"
CHECKSUMS_FILE = "checksums.json"
SPEC_FILE = "group_spec.json"
GROUP_FILES = ("spikes.h5", "group.json", SPEC_FILE)
VOLATILE_KEYS = frozenset({"group_dir", "seconds", "sim_seconds", "pixel_steps_per_s"})
"""Keys left out of ``content_sha256``: wall-clock timings and the temporary build path."""
CHECKSUM_DEFINITION = (
    "files.*.sha256: sha256 of the file bytes (integrity). content_sha256: sha256 over every HDF5 dataset "
    "(name, dtype, shape, values) and attribute, group.json and group_spec.json, without the volatile keys "
    + ", ".join(sorted(VOLATILE_KEYS))
    + " (kept for builds that stored them). Files hold no timings: the same manifest gives the same bytes; timings are in build_log.json"
)


def file_sha256(path: str | os.PathLike, block: int = 1 << 22) -> str:
    """sha256 hex of a file's bytes (read in 4 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            b = fh.read(block)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def _strip_volatile(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip_volatile(v) for k, v in obj.items() if k not in VOLATILE_KEYS}
    if isinstance(obj, list):
        return [_strip_volatile(v) for v in obj]
    return obj


def _attr_canon(v: Any) -> bytes:
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    if isinstance(v, str):
        try:
            parsed = json.loads(v)
        except (json.JSONDecodeError, ValueError):
            return v.encode()
        if isinstance(parsed, (dict, list)):
            return json.dumps(_strip_volatile(parsed), sort_keys=True).encode()
        return v.encode()
    a = np.asarray(v)
    return a.dtype.str.encode() + repr(a.shape).encode() + a.tobytes()


def _h5_content(h: "hashlib._Hash", path: Path, rows: int = 2000) -> None:
    import h5py

    with h5py.File(path, "r") as f:
        objs: list[tuple[str, Any]] = [("/", f)]
        f.visititems(lambda name, o: objs.append((name, o)))
        for name, o in sorted(objs, key=lambda t: t[0]):
            h.update(b"\0obj\0" + name.encode())
            for k in sorted(o.attrs.keys()):
                h.update(b"\0attr\0" + k.encode() + b"=" + _attr_canon(o.attrs[k]))
            if isinstance(o, h5py.Dataset):
                h.update(o.dtype.str.encode() + repr(o.shape).encode())
                if o.shape and o.shape[0] > rows:
                    for i in range(0, o.shape[0], rows):
                        h.update(np.ascontiguousarray(o[i : i + rows]).tobytes())
                else:
                    h.update(np.ascontiguousarray(o[()]).tobytes())


def content_sha256(group_dir: str | os.PathLike) -> str:
    """Content checksum of a group folder (see the module docstring; volatile keys left out)."""
    g = Path(group_dir)
    h = hashlib.sha256()
    for name in GROUP_FILES:
        p = g / name
        if not p.is_file():
            raise DataFormatError(f"{g}: missing {name}; the group is incomplete, rebuild it")
        h.update(b"\0file\0" + name.encode())
        if name.endswith(".h5"):
            try:
                _h5_content(h, p)
            except (OSError, ValueError, RuntimeError, KeyError) as exc:
                raise DataFormatError(f"{p}: unreadable HDF5 content ({str(exc).splitlines()[0][:120]})") from None
        else:
            try:
                data = json.loads(p.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise DataFormatError(f"{p}: not valid JSON ({exc})") from None
            h.update(json.dumps(_strip_volatile(data), sort_keys=True).encode())
    return h.hexdigest()


def _file_table(group_dir: Path) -> dict[str, dict]:
    return {n: {"sha256": file_sha256(group_dir / n), "bytes": (group_dir / n).stat().st_size} for n in GROUP_FILES}


def verify_group_files(group_dir: str | os.PathLike, expected: dict | None = None) -> list[str]:
    """Problems (empty list = fine) of a built group's files against its checksums.json.

    Args:
        group_dir: ``DIR/groups/NAME``.
        expected: optional record (from dataset.json) whose ``files`` and
            ``spec_sha256`` must also match.
    """
    g = Path(group_dir)
    cs_path = g / CHECKSUMS_FILE
    if not g.is_dir():
        return ["missing folder"]
    if not cs_path.is_file():
        return [f"no {CHECKSUMS_FILE}"]
    try:
        cs = json.loads(cs_path.read_text())
        files = cs["files"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError):
        return [f"{CHECKSUMS_FILE} unreadable"]
    bad = []
    for name in GROUP_FILES:
        if name not in files:
            bad.append(f"{name} not listed in {CHECKSUMS_FILE}")
            continue
        p = g / name
        if not p.is_file():
            bad.append(f"{name} missing")
            continue
        if p.stat().st_size != files[name].get("bytes") or file_sha256(p) != files[name].get("sha256"):
            bad.append(f"{name} sha256 mismatch")
    if expected is not None:
        if expected.get("spec_sha256") != cs.get("spec_sha256"):
            bad.append("spec_sha256 differs from dataset.json")
        if expected.get("content_sha256") != cs.get("content_sha256"):
            bad.append("content_sha256 differs from dataset.json")
        if expected.get("files") != files:
            bad.append(f"{CHECKSUMS_FILE} differs from dataset.json")
    return bad
