"""``recal import``: a CSV time series into an MCAP raw topic, with the live node's time base.

The CSV is read a chunk at a time (a week-long file must not have to fit in memory); its
times go through `recal.core.timebase` as the live node's would (a time column in
milliseconds under a microsecond name, a wrapping counter, a reboot), so the recording holds
what the node would have calibrated, and what was changed is said. Nothing half-imported is
left behind.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from recal.core import timebase as tb
from recal.errors import UsageError
from recal.io import csv_table
from recal.io.recording_writer import FILE_TO_FILE_FLUSH_S, RecordingWriter
from recal.io.sources import open_recording, recording_kind, source_lines, string_metadata
from recal.samples import RawBatch

__all__ = ["ImportClock", "import_csv", "import_device", "write_raw_messages"]

MESSAGE_SAMPLES = 1000  # samples per raw message written


def write_raw_messages(writer: RecordingWriter, sensor_id: str,
                       batch: RawBatch) -> None:
    """A batch as raw messages of 1000 samples (`recal simulate`, `recal import`), each logged
    at its first sample's device time."""
    for i in range(0, len(batch), MESSAGE_SAMPLES):
        b = batch[i:i + MESSAGE_SAMPLES]
        writer.write_raw(sensor_id, b, int(b.t_us[0]) * 1000)


def import_csv(source: str, out: str, *, units: str | None, rate_hz: float | None,
               sensor_id: str | None, quiet: bool) -> list[str]:
    """Write the CSV or device file ``source`` (by content) to the recording ``out``
    (replaced); returns the lines that say what was imported. UsageError for a CSV without a
    valid row or with times out of range."""
    from tqdm import tqdm  # the progress bar, only when importing

    if recording_kind(source) == "device":
        return import_device(source, out, sensor_id=sensor_id, quiet=quiet)
    sensor_id = sensor_id or "imported"

    writer: RecordingWriter | None = None
    samples, skipped, bad_lines = 0, 0, []
    table_units, aux_names = "", ()
    clock = ImportClock(rate_hz)
    # a bar on a terminal only: not in a pipe, a log or a test's captured stderr
    bar = tqdm(total=Path(source).stat().st_size, unit="B", unit_scale=True, desc="import",
               disable=quiet or not sys.stderr.isatty(), leave=False)
    try:  # a chunk at a time: a week-long CSV must not have to fit in memory
        for table in csv_table.iter_csv(source, units=units, rate_hz=rate_hz,
                                        on_bytes=bar.update):
            skipped += table.skipped_rows
            bad_lines += table.skipped_lines
            batch = table.batch
            if not len(batch):
                continue
            t_us = batch.t_us
            if t_us.min() < 0 or t_us.max() >= 2**64 // 1000:  # MCAP log time = t_us * 1000 ns
                raise UsageError(f"{source}: times must be from 0 to 584 years in "
                                 f"microseconds (found {t_us.min()} to {t_us.max()})")
            batch = clock.step(batch)  # the file's times as they are checked, then this
            if writer is None:
                table_units, aux_names = table.units, batch.aux_names
                writer = RecordingWriter(out, overwrite=True, metadata={"units": table.units},
                                         flush_interval_s=FILE_TO_FILE_FLUSH_S)
            write_raw_messages(writer, sensor_id, batch)
            samples += len(batch)
    except BaseException:
        if writer is not None:  # nothing half-imported is left behind
            writer.close()
            Path(out).unlink(missing_ok=True)
        raise
    finally:
        bar.close()
    if writer is None:
        lines = ", ".join(map(str, bad_lines[:5]))
        raise UsageError(f"{source}: no valid rows ({skipped} bad"
                         + (f", first at lines {lines})" if lines else ")"))
    writer.close()
    return [f"imported {samples} samples ({table_units}, channels {list(aux_names) or 'none'}) "
            f"into {out}; {skipped} bad rows skipped", *clock.lines()]


def import_device(source: str, out: str, *, sensor_id: str | None, quiet: bool) -> list[str]:
    """A device file's samples (true times, values in g, its aux channels) to the raw topic of
    ``out``, with the device's metadata in the recording's metadata record. The times need
    no time base: they are the device's, in microseconds, strictly increasing."""
    from tqdm import tqdm

    src = open_recording(source, sensor_id)
    assert src.device is not None
    bar = tqdm(total=len(src.device), unit="sample", unit_scale=True, desc="import",
               disable=quiet or not sys.stderr.isatty(), leave=False)
    samples = 0
    try:
        with RecordingWriter(out, overwrite=True, flush_interval_s=FILE_TO_FILE_FLUSH_S,
                             metadata={"units": "g", **string_metadata(src)}) as writer:
            for batch in src.batches():
                write_raw_messages(writer, src.sensor_id, batch)
                samples += len(batch)
                bar.update(len(batch))
    except BaseException:
        Path(out).unlink(missing_ok=True)  # nothing half-imported is left behind
        raise
    finally:
        bar.close()
    return [f"imported {samples} samples (g, channels {list(src.device.aux_names) or 'none'}) "
            f"of {src.sensor_id} into {out}", *source_lines(src)]


class ImportClock:
    """`recal import`'s time base (recal.core.timebase), chunk by chunk: a time column in
    milliseconds under a microsecond name, a wrapping counter, a reboot are written as the
    live node would calibrate them (unwrapped microseconds, never backwards) and said."""

    def __init__(self, rate_hz: float | None) -> None:
        self.cfg = tb.TimebaseConfig(rate_hz=rate_hz)
        self.state: tb.TimebaseState | None = None
        self.events: list[dict] = []

    def step(self, batch: RawBatch) -> RawBatch:
        if self.state is None:
            self.state, self.events = tb.start(batch.t_us, self.cfg)
        self.state, t_us, events = tb.step(self.state, batch.t_us, self.cfg)
        self.events += [e for e in events if e["kind"] != "time_anomalies"]
        if np.array_equal(t_us, batch.t_us):
            return batch
        return RawBatch(t_us, batch.v, batch.aux, batch.aux_names)

    def lines(self) -> list[str]:
        """What the time base did, for a person (nothing when the times were clean)."""
        out = []
        for e in self.events:
            d = e["detail"]
            if e["kind"] == "time_units":
                out.append(f"time: the time column counts {d['unit']}, not microseconds (as "
                           f"microseconds it implies {d['implied_rate_hz_as_us']:.0f} Hz); "
                           f"written as {d['rate_hz']:.4g} Hz in microseconds")
            elif e["kind"] == "time_implausible":
                out.append(f"time: the time column implies {d['implied_rate_hz']:.4g} Hz in "
                           "any unit; written as it is (check it)")
        s = self.state
        if s is not None and s.wraps:
            out.append(f"time: the counter wrapped {s.wraps} time(s) (period {s.period} "
                       f"{s.unit}); written unwrapped")
        if s is not None and s.reboots:
            out.append(f"time: the device time restarted near 0 {s.reboots} time(s) (a "
                       "reboot); written continuing")
        if s is not None and s.backwards + s.duplicates + s.jumps:
            out.append(f"time: {s.backwards} steps back, {s.duplicates} repeated and "
                       f"{s.jumps} jumps over 2 s; written never going back")
        return out
