"""Stored-window training data for ``polspike train --data DIR`` (see :mod:`reconstruct.windows`)."""

from __future__ import annotations

from reconstruct.windows import StoreWindows, open_window_datasets

__all__ = ["StoreWindows", "open_window_datasets"]
