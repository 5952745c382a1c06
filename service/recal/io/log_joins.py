"""How the recording writer joins batches: a topic's raw, calibrated or body batches wait in
a :class:`Pending` message and go into the file as one compact message (`recal.io.messages`),
and the times MCAP gives each message. The writer (`recal.io.recording_writer`) decides when.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from recal.io import messages
from recal.io.messages import SchemaSpec
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["MAX_U64", "Joins", "Pending", "check_log_time", "joined_messages", "plot_items",
           "plot_log_times", "publish_ns", "publish_ns_array", "rotation_bytes"]

MAX_U64 = 2**64 - 1
#: A batch longer than this (a file tool's) is logged in messages of this many samples.
_MAX_MESSAGE_SAMPLES = 16384


def publish_ns(t_us: int | None, fallback_ns: int) -> int:
    """A message's publish time: its first device time (us) in ns, else ``fallback_ns``."""
    if t_us is None:
        return fallback_ns
    # MCAP times are unsigned 64-bit; device clocks before their epoch are clamped, not lost.
    return min(max(int(t_us) * 1000, 0), MAX_U64)


def publish_ns_array(t_us: np.ndarray) -> np.ndarray:
    """`publish_ns` of each device time (us), as uint64."""
    t = np.clip(np.asarray(t_us, np.int64), 0, None).astype(np.uint64)
    big = t > np.uint64(MAX_U64 // 1000)
    out = t * np.uint64(1000)
    out[big] = MAX_U64
    return out


def rotation_bytes(rotation: np.ndarray) -> bytes:
    """A body rotation (3 x 3, ``R @ a``) as the float64 bytes a waiting message keeps."""
    r = np.ascontiguousarray(rotation, np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be 3 x 3, got shape {r.shape}")
    return r.tobytes()


def check_log_time(log_time_ns: int) -> int:
    """``log_time_ns`` as an int; ValueError unless it is an unsigned 64-bit integer."""
    value = int(log_time_ns)
    if not 0 <= value <= MAX_U64:
        raise ValueError(f"log_time_ns must be an unsigned 64-bit integer, got {log_time_ns}")
    return value


def _layout(batch: RawBatch | CalibratedBatch, raw: bool) -> Any:
    """What batches must share to be joined: the channels, or which optional columns exist."""
    if raw:
        return batch.aux_names  # type: ignore[union-attr]
    return (batch.t_dev is None, batch.recorded)  # type: ignore[union-attr]


@dataclass
class Pending:
    """Batches of one topic waiting to be logged as one message."""

    sensor_id: str
    raw: bool  # RawBatch (else CalibratedBatch)
    log_ns: int  # the first batch's log time: the message's
    publish_ns: int
    rotation: bytes | None = None  # body in the log's form: the rotation (float64 bytes)
    batches: list[Any] = field(default_factory=list)
    samples: int = 0
    sizes: list[int] = field(default_factory=list)  # raw: samples of each arrival
    log_times: list[int] = field(default_factory=list)  # raw: each arrival's log time


class Joins:
    """The messages waiting to be logged, one per topic (the writer's lock held)."""

    def __init__(self, log_batch_samples: int) -> None:
        self.pending: dict[str, Pending] = {}
        self.log_batch_samples = log_batch_samples

    def hold(self, topic: str, sensor_id: str, batch: RawBatch | CalibratedBatch, log_ns: int,
             raw: bool, arrivals: messages.Arrivals | None, rotation: bytes | None,
             emit: Callable[[str], None]) -> None:
        """Add a batch to its topic's waiting message (a list append per arrival: the join and
        the encoding happen once per message); ``emit(topic)`` logs a topic's message now
        (one that is full, or one of another layout or rotation)."""
        p = self.pending.get(topic)
        if p is not None and (p.rotation != rotation
                              or _layout(p.batches[0], raw) != _layout(batch, raw)):
            emit(topic)  # one message holds one layout (and one rotation)
            p = None
        if p is None:
            first = int(batch.t_us[0]) if len(batch) else None
            p = self.pending[topic] = Pending(sensor_id, raw, log_ns,
                                              publish_ns(first, log_ns), rotation)
        p.batches.append(batch)
        p.samples += len(batch)
        if raw and arrivals is None:  # (a calibrated message keeps no arrivals)
            p.sizes.append(len(batch))
            p.log_times.append(log_ns)
        elif raw and arrivals is not None:
            sizes, log_us = arrivals
            p.sizes += sizes.tolist()
            p.log_times += ([log_ns] * len(sizes) if log_us is None
                            else (log_ns + 1000 * log_us).tolist())
        if p.samples >= self.log_batch_samples:
            emit(topic)


def joined_messages(p: Pending, log_batch_samples: int) -> tuple[SchemaSpec, list[bytes], int]:
    """The waiting batches as compact messages: (schema, each message's bytes, raw samples
    they hold). One message, but a calibrated batch longer than a message may hold (a file
    tool's) is cut in several."""
    if p.raw:
        batch = p.batches[0] if len(p.batches) == 1 else RawBatch.concat(p.batches)
        # the arrivals, so that a replay gives the node the batches the live node had
        arrivals = (p.sizes, [(t - p.log_ns) // 1000 for t in p.log_times])
        return (messages.RAW_SCHEMA,
                [messages.encode_raw_compact(p.sensor_id, batch, arrivals)], len(batch))
    if p.rotation is not None:  # the body in the log's form: times and the rotation
        t_us = np.concatenate([b.t_us for b in p.batches])
        r = np.frombuffer(p.rotation, np.float64).reshape(3, 3)
        return messages.CALIBRATED_SCHEMA, [messages.encode_body_rotation(p.sensor_id, t_us,
                                                                          r)], 0
    cal = p.batches[0] if len(p.batches) == 1 else CalibratedBatch.concat(p.batches)
    step = max(log_batch_samples, _MAX_MESSAGE_SAMPLES)  # (a file tool's batches)
    return messages.CALIBRATED_SCHEMA, [
        messages.encode_calibrated_compact(p.sensor_id, cal if len(cal) <= step
                                           else cal[i:i + step])
        for i in range(0, max(len(cal), 1), step)], 0


def plot_items(batch: CalibratedBatch, indices: np.ndarray, log_ns: int
               ) -> list[tuple[bytes, int, int]]:
    """(data, log time, publish time) of a few plot samples of one arrival, packed one by one
    (no array set-up): each sample's log time is the batch's, moved back by its device-time
    distance to the batch's last sample (so a Plot panel draws them spread out)."""
    last_us = int(batch.t_us[-1])
    return [(data, lt, publish_ns(t, lt)) for data, t in zip(
        messages.encode_plot(batch, indices), batch.t_us[indices].tolist(), strict=True)
        for lt in (max(log_ns - (last_us - t) * 1000, 0),)]


def plot_log_times(batch: CalibratedBatch, indices: np.ndarray, log_ns: int,
                   arrivals: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, int]:
    """The log time of each plot sample (as `plot_items` gives them) and the call's; with
    ``arrivals`` (samples of each arrival, log time of each in ns) each sample's from its own
    arrival's log time and last device time."""
    t_us = batch.t_us[indices]
    if arrivals is None:
        last_us = int(batch.t_us[-1])
        return np.clip(log_ns - (last_us - t_us) * 1000, 0, None), log_ns
    sizes = np.asarray(arrivals[0], np.int64)
    log_ns_of = np.asarray(arrivals[1], np.int64)
    if sizes.sum() != len(batch) or len(log_ns_of) != len(sizes) or (sizes < 0).any():
        raise ValueError("arrivals do not describe the batch")
    if len(log_ns_of) and not (log_ns_of.min() >= 0 and log_ns_of.max() <= MAX_U64):
        raise ValueError("an arrival's log time is not an unsigned 64-bit integer")
    ends = np.cumsum(sizes)
    arrival = np.searchsorted(ends, indices, side="right")  # the arrival of each sample
    last = batch.t_us[ends[arrival] - 1]
    return (np.clip(log_ns_of[arrival] - (last - t_us) * 1000, 0, None),
            int(log_ns_of[arrival[0]]))
