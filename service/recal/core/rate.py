"""A stream's sample rate from its time stamps, when nobody configured it.

The node holds a stream's first samples until it knows the rate (recal.node.node); the rule is a
pure function of the stamps, so it lives in the core. The median of the positive steps: a
repeated stamp, a dropped sample or a clock jump moves it little.
"""

from __future__ import annotations

import numpy as np

__all__ = ["infer_rate_hz"]


def infer_rate_hz(t_us: np.ndarray) -> float | None:
    """Sample rate in Hz from device time stamps (median positive step), None if unknown."""
    dt = np.diff(np.asarray(t_us, np.int64))
    dt = dt[dt > 0]
    if len(dt) == 0:
        return None
    return float(1e6 / np.median(dt))
