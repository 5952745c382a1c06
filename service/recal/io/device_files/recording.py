"""A device file opened: its samples with true times, its aux channels, what it says about
the device, and what the user must be told (`DeviceRecording`, made by `open_device`).

Times (`block_times`): each sample is stamped between its block's time and the next block's;
gaps stay gaps; a clock set back is an event, not a step back. The file's own stamp of every
sample stays available (`file_times`), as ``t_dev`` keeps a serial device's. Time zone: the
file's stamps are the device's local wall-clock written as if UTC; where the file records its
zone the times are converted to UTC, else they stay local; ``metadata['time']`` and ``notes``
say which.
"""

from __future__ import annotations

import functools
import re
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from recal.core import low_rate
from recal.core.windower import WindowSums
from recal.errors import DeviceFileError
from recal.io.device_files import block_times as bt
from recal.io.device_files import guard, registry
from recal.io.device_files.parsed import Parsed
from recal.samples import REBATCH_SAMPLES, RawBatch

__all__ = ["SAMPLE_INDEX", "DeviceRecording", "is_device_file", "open_device"]

#: device times outside these years are no clock a device keeps (a damaged or crafted file)
_MIN_NS, _MAX_NS = 0, (2200 - 1970) * 365 * 86400 * 10**9
#: no worn accelerometer samples faster (AX3: 3200 Hz); a faster header is damaged
MAX_RATE_HZ = 10_000.0
#: `window_batch`'s last channel: each sample's index in the file (a window's sum of it
#: gives the window's first sample: `with_low_rate`)
SAMPLE_INDEX = "sample_index"


class DeviceRecording:
    """One device file, read. ``batches()`` yields its samples as raw batches (true times in
    µs, values in g as the reader gives them, aux channels named as the device names them,
    interpolated from their own rate to the samples)."""

    def __init__(self, path: Path, kind: registry.DeviceKind, parsed: Parsed) -> None:
        self.path, self.kind, self._p = path, kind.kind, parsed
        self.sensor_id = _sensor_id(parsed.device_id or path.name.split(".")[0])
        if not 0.1 <= parsed.nominal_rate_hz <= MAX_RATE_HZ:
            raise DeviceFileError(f"{path}: {kind.name} with a sample rate of "
                                  f"{parsed.nominal_rate_hz:g} Hz: refused (a damaged header)")
        nominal_ns = 1e9 / parsed.nominal_rate_hz
        starts = bt.block_starts(parsed.file_t_ns, nominal_ns, parsed.known_starts_ns)
        self._blocks = bt.block_times(parsed.file_t_ns, starts, nominal_ns)
        self._shift_ns = 0 if parsed.utc_offset_s is None else int(parsed.utc_offset_s * 1e9)
        first, last = (int(self._blocks.anchor_ns[0]) - self._shift_ns,
                       int(self._blocks.anchor_ns[-1]) - self._shift_ns)
        if first < _MIN_NS or last > _MAX_NS:
            raise DeviceFileError(f"{path}: {kind.name} with times outside 1970-2200: "
                                  "refused (a damaged or crafted file)")
        self.rate_hz = 1e9 / self._blocks.measured_period_ns
        # each low-rate channel's stamps in float64 once per file, not a week's per batch
        self._low_rate = [(lr.t_ns.astype(np.float64), lr.values) for lr in parsed.low_rate]
        self.aux_names = tuple([lr.name for lr in parsed.low_rate] + list(parsed.per_sample))
        self.skipped = {**parsed.skipped, "gaps": self._blocks.gaps,
                        "clock_changes": self._blocks.clock_changes}
        self.notes = [*_time_notes(parsed, self._blocks), *parsed.notes]
        self.metadata = _metadata(kind, parsed, self)

    def __len__(self) -> int:
        return len(self._p.file_t_ns)

    def batches(self, samples: int = REBATCH_SAMPLES) -> Iterator[RawBatch]:
        """The samples in batches of ``samples`` (the last may hold fewer)."""
        for lo in range(0, len(self), samples):
            yield self.batch(lo, min(len(self), lo + samples))

    def file_times(self, samples: int = REBATCH_SAMPLES) -> Iterator[np.ndarray]:
        """The file's own stamp of each sample (µs, the device's local wall-clock as the
        reader gives it), in the same batches as `batches`."""
        t = self._p.file_t_ns
        for lo in range(0, len(self), samples):
            yield t[lo:lo + samples] // 1000

    def readings(self, lo: int, hi: int) -> np.ndarray:
        """The readings of samples lo..hi-1 (N,3) as `batch` gives them, without their
        times and channels (what the detector needs)."""
        return self._p.v_g[lo:hi].astype(np.float64)

    def readings_by_axis(self, lo: int, hi: int) -> np.ndarray:
        """`readings` laid out axis by axis (Fortran order: the same values, each axis
        contiguous, which the detector's per-axis operations read faster)."""
        return np.asfortranarray(self._p.v_g[lo:hi], dtype=np.float64)

    @functools.cached_property
    def low_rate_closed(self) -> list[low_rate.Stretches] | None:
        """The low-rate channels as stretches between their stamps (channels sharing stamps
        together, in their order), where their window sums have a closed form
        (`core.low_rate.applies`); None where they do not (a stamp out of order, a value not
        finite): then only `batch` gives them."""
        x, groups = self._p.file_t_ns, []
        for lr in self._p.low_rate:
            if groups and np.array_equal(groups[-1][0], lr.t_ns):
                groups[-1][1].append(lr.values)
            else:
                groups.append((lr.t_ns, [lr.values]))
        out = []
        for t, values in groups:
            vals = np.column_stack(values).astype(np.float64)
            if not low_rate.applies(t, vals):
                return None
            # the file's times rise within each block (a step other than the nominal period
            # starts one): a pass over the blocks, not the samples
            out.append(low_rate.Stretches.of(x, t, vals, rises=self._blocks.start))
        return out

    def finite_everywhere(self, names: Iterable[str]) -> bool:
        """Whether the per-sample channels among ``names`` are finite at every sample (the
        low-rate ones are, where `low_rate_closed` is not None)."""
        ps = self._p.per_sample
        return all(bool(np.all(np.isfinite(ps[c]))) for c in names if c in ps)

    def window_batch(self, lo: int, hi: int) -> RawBatch:
        """Samples lo..hi-1 as `batch` gives them but for the low-rate channels, in their
        place each sample's index (SAMPLE_INDEX, after the per-sample channels): what a
        windower needs when the low-rate channels' sums are made apart (`with_low_rate`)."""
        p = self._p
        t_us = self._blocks.times_ns(lo, hi, self._shift_ns) // 1000
        aux = np.empty((hi - lo, len(p.per_sample) + 1))
        for i, a in enumerate(p.per_sample.values()):
            aux[:, i] = a[lo:hi]
        aux[:, -1] = np.arange(lo, hi, dtype=np.float64)
        return RawBatch.of_checked(t_us, self.readings(lo, hi), aux,
                                   (*p.per_sample, SAMPLE_INDEX))

    def with_low_rate(self, sums: WindowSums, lo: int, hi: int) -> WindowSums:
        """Windows of samples within lo..hi cut from `window_batch`es, with their channels
        as `batch` gives them: the low-rate channels' sums over each window's samples
        (`core.low_rate.window_sums`, to rounding; the first sample from the sum of
        SAMPLE_INDEX, n first + n (n - 1) / 2, exact in float64 below 2^53), then the
        per-sample ones. Only where `low_rate_closed` is not None."""
        groups = self.low_rate_closed
        if groups is None:
            raise ValueError("the low-rate channels have no closed form here: use batch()")
        n = sums.n
        first = np.rint((sums.sum_aux[:, -1] - n * (n - 1) / 2)
                        / np.maximum(n, 1)).astype(np.int64)
        x = self._p.file_t_ns[lo:hi]
        low = [low_rate.window_sums(g, x, lo, first, n) for g in groups]
        return replace(sums, sum_aux=np.hstack([*low, sums.sum_aux[:, :-1]]))

    def batch(self, lo: int, hi: int) -> RawBatch:
        """Samples lo..hi-1 (any range: the file is in memory)."""
        p = self._p
        t_us = self._blocks.times_ns(lo, hi, self._shift_ns) // 1000
        x = p.file_t_ns[lo:hi].astype(np.float64)
        cols = [np.interp(x, t, values) for t, values in self._low_rate]
        cols += [a[lo:hi] for a in p.per_sample.values()]
        aux = np.column_stack(cols) if cols else np.zeros((hi - lo, 0))
        return RawBatch(t_us, self.readings(lo, hi), aux, self.aux_names)


def _sensor_id(text: str) -> str:
    sid = re.sub(r"[^A-Za-z0-9_.\-]", "_", text).lstrip("_.-")[:100]
    return sid or "device"


def _time_notes(p: Parsed, b: bt.BlockTimes) -> list[str]:
    if p.utc_offset_s is None:
        notes = ["times: the device's local wall-clock as the file holds it (the file records "
                 "no time zone), not UTC"]
    else:
        notes = [f"times: UTC, from the device's local wall-clock and the file's time zone "
                 f"(UTC{p.utc_offset_s / 3600:+g} h)"]
    notes.append("times: each sample stamped between its block's time and the next block's "
                 f"(measured rate {1e9 / b.measured_period_ns:.4f} Hz, nominal "
                 f"{p.nominal_rate_hz:g} Hz)")
    if b.gaps:
        notes.append(f"{b.gaps} gap(s) ({b.gap_s:.1f} s in all) kept as gaps (device off, idle "
                     "sleep or missing blocks; a forward clock change looks the same)")
    if b.clock_changes:
        notes.append(f"{b.clock_changes} clock change(s) (the file's time went back "
                     f"{b.clock_change_s:.1f} s in all): the samples continue at the measured "
                     "rate; the file's own stamps are kept")
    return notes


def _metadata(kind: registry.DeviceKind, p: Parsed, rec: DeviceRecording) -> dict[str, Any]:
    out: dict[str, Any] = {"kind": kind.kind, "format": kind.name}
    out.update({k: v for k, v in p.metadata.items() if v not in (None, "")})
    out["rate_hz"] = rec.rate_hz
    out["samples"] = len(p.file_t_ns)
    out["time"] = ("local wall-clock (no time zone in the file)" if p.utc_offset_s is None
                   else "UTC (converted with the file's time zone)")
    if p.utc_offset_s is not None:
        out["utc_offset_s"] = p.utc_offset_s
    out["aux_channels"] = ", ".join(rec.aux_names)
    for k, v in rec.skipped.items():
        out[f"skipped_{k}" if k not in ("gaps", "clock_changes") else k] = v
    return out


def open_device(path: str | Path, *, lenient: bool = True, threads: int = 1) -> DeviceRecording:
    """Read a device file recognised by its content (registry.KINDS). A kind recognised but
    not readable, anything else, or a damaged or crafted file: DeviceFileError, one line.
    ``lenient``: read up to what is whole (a cut-short file, corrupt blocks), counting what
    was skipped in ``notes``. ``threads``: a .cwa is decoded on that many (`cwa_sectors`)."""
    path = Path(path)
    kind = registry.kind_of(path)
    if kind is None:
        raise DeviceFileError(f"{path}: not a device file recal reads (Axivity .cwa, GENEActiv "
                              ".bin, ActiGraph .gt3x)")
    if kind.read is None:
        raise DeviceFileError(f"{path}: {kind.name}: recal cannot read this kind of file yet "
                              f"({kind.why_not})")
    if guard.is_gzip(path):
        with tempfile.TemporaryDirectory(prefix="recal-device-") as tmp:
            parsed = kind.read(guard.gunzip_to(path, tmp), path, lenient, threads)
    else:
        parsed = kind.read(path, path, lenient, threads)
    if not len(parsed.file_t_ns):
        raise DeviceFileError(f"{path}: {kind.name} that holds no samples")
    return DeviceRecording(path, kind, parsed)


def is_device_file(path: str | Path) -> bool:
    """Whether the content is a device file kind recal recognises (readable or not)."""
    return registry.sniff(path) is not None
