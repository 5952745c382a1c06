"""Bounded polling for tests that wait on another thread, process or Zenoh session."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_for(cond: Callable[[], bool], timeout_s: float, interval_s: float = 0.02) -> bool:
    """Poll ``cond`` until true, bounded by time and by a number of polls; its last value."""
    deadline = time.monotonic() + timeout_s
    for _ in range(int(timeout_s / interval_s) + 2):
        if cond():
            return True
        if time.monotonic() >= deadline:
            break
        time.sleep(interval_s)
    return bool(cond())
