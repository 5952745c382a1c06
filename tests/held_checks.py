"""What a moment of doubt (a port reopened, a gap in device time) must do to the statuses
from sample k on, shared by the tests of each moment."""

from __future__ import annotations

import numpy as np

from recal.core.status import Status


def held_until_contradicted(status: np.ndarray, k: int, rate_hz: float) -> None:
    """Another sensor from sample k: calibrated before it, suspect within 5 min, and no
    sample of it marked calibrated before that."""
    assert np.all(status[k - 1000:k] == Status.CALIBRATED)  # the first sensor was calibrated
    suspect = np.flatnonzero(status[k:] == Status.SUSPECT)
    assert len(suspect) and suspect[0] / rate_hz < 5 * 60, suspect[:1]
    assert not np.any(status[k:k + suspect[0]] == Status.CALIBRATED)


def held_until_agreed(status: np.ndarray, k: int, rate_hz: float) -> None:
    """The same sensor from sample k: held there, no suspect sample, calibrated again within
    a minute (its first still window) and from then on."""
    assert np.all(status[k - 1000:k] == Status.CALIBRATED)
    after = status[k:]
    assert after[0] == Status.HELD and not np.any(after == Status.SUSPECT)
    back = np.flatnonzero(after == Status.CALIBRATED)
    assert len(back) and back[0] / rate_hz < 60, back[:1]
    assert np.all(after[back[0]:] == Status.CALIBRATED)
