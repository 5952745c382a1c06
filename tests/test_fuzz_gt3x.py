"""Mutated .gt3x files (damaged records inside a good zip, and damaged zips): the decoder reads
them or says one `DeviceFileError`, never another exception, in bounded time and memory."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gt3x_writers import LogFile, nhanes_entries, zip_gt3x
from recal.errors import DeviceFileError
from recal.io.gt3x import read_gt3x

FUZZ = settings(max_examples=60, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
# What a small file may cost at most: far above the file and its samples, far below what a
# header that is believed would allocate.
PEAK_BYTES = 64 << 20


def _link() -> dict[str, bytes]:
    c = np.random.default_rng(5).integers(-600, 600, size=(30 * 8, 3))
    return LogFile(counts=c, rate_hz=30, asleep=(3,), battery_mv={1: 4000}, lux={2: 7},
                   imu_records=2).entries()


def _nhanes() -> dict[str, bytes]:
    c = np.random.default_rng(6).integers(-2000, 2000, size=(30 * 8, 3))
    return nhanes_entries(c, 30, 1_300_000_000, [30, 40, 50])


# anywhere, or in the first or last 100 bytes (zip headers, the central directory at the end)
where = st.integers(0, 1 << 20) | st.integers(0, 99) | st.integers(-100, -1)
edits = st.lists(st.tuples(where, st.integers(0, 255)), min_size=1, max_size=12)


def _mutate(data: bytes, changes: list[tuple[int, int]], cut: int | None) -> bytes:
    b = bytearray(data)
    for at, value in changes:
        if b:
            b[at % len(b)] = value
    return bytes(b[:cut % (len(b) + 1)] if cut is not None else b)


def _read_bounded(path: Path) -> None:
    tracemalloc.start()
    try:
        d = read_gt3x(path)
        assert len(d.t_us) == len(d.acc_g) and np.all(np.isfinite(d.acc_g))
    except DeviceFileError as exc:
        assert "\n" not in str(exc)
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert peak < PEAK_BYTES


@FUZZ
@given(layout=st.sampled_from(["log.bin", "activity.bin", "info.txt"]), changes=edits,
       cut=st.none() | st.integers(0, 1 << 20))
def test_damaged_entries_in_a_good_zip(tmp_path: Path, layout: str,
                                       changes: list[tuple[int, int]], cut: int | None) -> None:
    entries = _nhanes() if layout == "activity.bin" else _link()
    entries[layout] = _mutate(entries[layout], changes, cut)
    _read_bounded(zip_gt3x(tmp_path / "f.gt3x", entries))


@FUZZ
@given(changes=edits, cut=st.none() | st.integers(0, 1 << 20), nhanes=st.booleans())
def test_damaged_zips(tmp_path: Path, changes: list[tuple[int, int]], cut: int | None,
                      nhanes: bool) -> None:
    good = zip_gt3x(tmp_path / "good.gt3x", _nhanes() if nhanes else _link())
    bad = tmp_path / "bad.gt3x"
    bad.write_bytes(_mutate(good.read_bytes(), changes, cut))
    _read_bounded(bad)
