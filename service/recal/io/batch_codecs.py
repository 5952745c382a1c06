"""Batch codecs: a RawBatch or CalibratedBatch as protobuf bytes and back (the schemas are
`recal.io.schemas`), in the bus's float64 form and the log's compact form.

The compact form (`encode_raw_compact`, `encode_calibrated_compact`) is what the recording
writer logs: a column is written either in its float64 field or in its compact one. Times are
the first stamp and the differences; raw readings that are all integers (ADC counts) and
calibrated values in micro-g (rounded: within half a micro-g) are differences from the sample
before (the first from 0); the detector in 2 micro-g steps (within one) as second differences;
sigma on its ladder of 1 % steps (`sigma_steps`) as the differences of the steps' numbers; the
device stamps as their distance from ``t_us``, differences; a joined raw message's arrival log
times as the differences of their lag behind the device time; all as zigzag varints, which a
few numpy passes write and read (`zigzag_varints_many`, `unzigzag_varints`); a column with a
value that is not finite or beyond +-2147 g stays in float64 (sigma that is not all positive:
micro-g differences). The fields of the compact form's first version (micro-g differences of
the detector and sigma, ``t_dev0`` + ``dt_dev``, ``arrival_log_dt_us``, ``body_rotation`` as 9
values) are still read. Differences make most varints one or two bytes, and zstd, restarted at
every one-second chunk, finds little else to take. The log's body topic holds no values
(`encode_body_rotation`): its samples' times and the rotation (as its unit quaternion) that
turns the calibrated topic's samples at those times (``decode_calibrated`` refuses such a
message; `recal.io.recording` reads it back). The bus keeps the float64 form: one sample is
cheapest to encode that way, and subscribers read either. The decoders accept both forms (and
older recordings, which have only the float64 fields).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np

from recal.io.protobuf_wire import (
    _VARINT_WT,
    _WT_I64,
    _WT_LEN,
    _as_bytes,
    _bools,
    _deltas,
    _fixed64,
    _join,
    _key,
    _last_string,
    _le_bytes,
    _len_prefixed,
    _Occurrence,
    _packed,
    _present,
    _scan,
    _sint_varints,
    _small_varints,
    _string_fields,
    _strings,
    _varint_field,
)
from recal.io.schemas import (
    _F_CAL_BODY_QUATERNION,
    _F_CAL_BODY_ROTATION,
    _F_CAL_DETECTOR,
    _F_CAL_DETECTOR_UG,
    _F_CAL_DETECTOR_UG_2,
    _F_CAL_DT_DEV,
    _F_CAL_QUASI_STATIC,
    _F_CAL_SIGMA,
    _F_CAL_SIGMA_STEP,
    _F_CAL_SIGMA_UG,
    _F_CAL_STATUS,
    _F_CAL_T_DEV,
    _F_CAL_T_DEV0,
    _F_CAL_T_DEV_OFFSET,
    _F_DT_US,
    _F_RAW_ARRIVAL_LAG_US,
    _F_RAW_ARRIVAL_LOG_US,
    _F_RAW_ARRIVAL_SAMPLES,
    _F_RAW_AUX,
    _F_RAW_AUX_NAMES,
    _F_SENSOR,
    _F_T0_US,
    _F_T_US,
    _F_X,
    _F_X_FIX,
    _F_Y,
    _F_Y_FIX,
    _F_Z,
    _F_Z_FIX,
)
from recal.samples import CalibratedBatch, RawBatch


def _axes_bytes(v: np.ndarray) -> list[memoryview]:
    """x, y, z columns as three byte runs, from one column-major copy."""
    n = len(v)
    columns = memoryview(v.astype("<f8", copy=False).tobytes(order="F"))
    return [columns[i * 8 * n:(i + 1) * 8 * n] for i in range(3)]


def encode_raw(sensor_id: str, batch: RawBatch) -> bytes:
    """Serialize a raw batch as a ``recal.RawBatch`` protobuf message (float64 form: the bus's,
    cheapest to make for a sample or two)."""
    x, y, z = _axes_bytes(batch.v)
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z)]
    return b"".join(parts + _aux_fields(batch))


def _aux_fields(batch: RawBatch) -> list[bytes | memoryview]:
    parts: list[bytes | memoryview] = []
    for name in batch.aux_names:
        # An empty name is still a list element, so it must be written (not omitted).
        parts += _len_prefixed(_F_RAW_AUX_NAMES, name.encode())
    if batch.aux.size:  # (an empty packed field is omitted)
        parts += _packed(_F_RAW_AUX, _le_bytes(batch.aux, "<f8"))
    return parts


def encode_calibrated(sensor_id: str, batch: CalibratedBatch) -> bytes:
    """Serialize a calibrated batch as a ``recal.CalibratedBatch`` protobuf message (float64
    form: the bus's)."""
    x, y, z = _axes_bytes(batch.a_g)
    # Packed bools are varints; 0 and 1 are single bytes, so uint8 is the wire form.
    quasi = _le_bytes(batch.quasi_static, "|u1")
    detector = _le_bytes(batch.detector_g, "<f8")
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_packed(_F_T_US, _le_bytes(batch.t_us, "<i8")),
             *_packed(_F_X, x), *_packed(_F_Y, y), *_packed(_F_Z, z),
             *_packed(_F_CAL_QUASI_STATIC, quasi), *_packed(_F_CAL_DETECTOR, detector)]
    if batch.recorded:  # statuses 0-5 are one-byte varints, so uint8 is the wire form
        parts += [*_packed(_F_CAL_STATUS, _le_bytes(batch.status, "|u1")),
                  *_packed(_F_CAL_SIGMA, _le_bytes(batch.sigma_mg, "<f8"))]
    if batch.t_dev is not None:
        parts += _packed(_F_CAL_T_DEV, _le_bytes(batch.t_dev, "<i8"))
    return b"".join(parts)


# -- the compact form (the log's) -------------------------------------------------------------

_I32_MAX = 2**31 - 1
#: micro-g per g: calibrated values, the detector and sigma are logged as int32 micro-g
#: (rounded: within 0.5 micro-g of the float64 value, range +-2147 g).
UG_PER_G = 1e6


def _time_fields(t: np.ndarray, f_first: int, f_delta: int) -> list[bytes | memoryview]:
    """A stamp column as its first value (sfixed64) and the differences (sint64 varints: a
    few bytes each at any rate)."""
    if len(t) == 0:
        return []
    return [_key(f_first, _WT_I64), struct.pack("<q", int(t[0])),
            *_varint_field(f_delta, np.diff(t))]


def _fixed_point(values: np.ndarray, scale: float) -> np.ndarray | None:
    """``values * scale`` rounded to int32, or None if one is not finite or out of range
    (that column is then written as float64)."""
    scaled = np.rint(values * scale) if scale != 1.0 else values
    if scaled.size and not (np.abs(scaled).max() <= _I32_MAX):  # (NaN fails the test too)
        return None
    out = scaled.astype("<i4")
    if scale == 1.0 and not np.array_equal(out, values):  # raw values that are not integers
        return None
    return out


def _compact_axes(v: np.ndarray, scale: float, f_float: Sequence[int], f_fixed: Sequence[int]
                  ) -> list[bytes | memoryview]:
    """The three axes as sint64 varint deltas of their fixed-point values, or as float64
    columns if the fixed point cannot hold them."""
    fixed = _fixed_point(v, scale)
    if fixed is None:
        return [p for f, col in zip(f_float, _axes_bytes(v), strict=True) for p in _packed(f, col)]
    return [p for i, f in enumerate(f_fixed) for p in _varint_field(f, _deltas(fixed[:, i]))]


def _compact_column(values: np.ndarray, scale: float, f_float: int, f_fixed: int
                    ) -> list[bytes | memoryview]:
    """A column as sint64 varint deltas of its fixed-point values, or float64."""
    fixed = _fixed_point(values, scale)
    if fixed is None:
        return _packed(f_float, _le_bytes(values, "<f8"))
    return _varint_field(f_fixed, _deltas(fixed))


def encode_raw_compact(sensor_id: str, batch: RawBatch,
                       arrivals: tuple[Sequence[int], Sequence[int]] | None = None) -> bytes:
    """A ``recal.RawBatch`` in the log's compact form: ``t0_us`` + ``dt_us`` deltas, integer
    readings (ADC counts) as deltas ``x_counts_delta`` ... (each value minus the one before;
    readings that are not all integers stay float64 in ``x`` ...), all deltas zigzag varints.
    `decode_raw` reads both forms.

    ``arrivals``: (samples per arrival, log time of each in us after the message's) of a
    batch joined from several arrivals (`decode_raw_arrivals` reads them back)."""
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_time_fields(batch.t_us, _F_T0_US, _F_DT_US),
             *_compact_axes(batch.v, 1.0, (_F_X, _F_Y, _F_Z), (_F_X_FIX, _F_Y_FIX, _F_Z_FIX))]
    if arrivals is not None and len(arrivals[0]) > 1:
        sizes = np.asarray(arrivals[0], np.int64)
        parts += _varint_field(_F_RAW_ARRIVAL_SAMPLES, sizes)
        lag = _arrival_lag_us(batch.t_us, sizes)
        if lag is None:
            parts += _varint_field(_F_RAW_ARRIVAL_LOG_US, _deltas(np.asarray(arrivals[1])))
        else:
            parts += _varint_field(_F_RAW_ARRIVAL_LAG_US,
                                   _deltas(np.asarray(arrivals[1], np.int64) - lag))
    return _join(parts + _aux_fields(batch))


def _arrival_lag_us(t_us: np.ndarray, sizes: np.ndarray) -> np.ndarray | None:
    """Each arrival's last device time after the message's first (us), what an arrival's log
    time is coded against (``arrival_lag_delta_us``: the lag's deltas, a few bytes of jitter
    where the log times' own deltas carry the sample interval too); None if the sizes do not
    describe the batch or an arrival is empty (the log times are then coded on their own)."""
    if len(sizes) == 0 or sizes.sum() != len(t_us) or (sizes < 1).any():
        return None
    return t_us[np.cumsum(sizes) - 1] - t_us[0]


def encode_calibrated_compact(sensor_id: str, batch: CalibratedBatch) -> bytes:
    """A ``recal.CalibratedBatch`` in the log's compact form: times as ``t0_us`` + ``dt_us``
    deltas, values as deltas of their micro-g values (``x_ug_delta`` ...: each value minus the
    one before, the first as it is; Foxglove plots the ``plot`` topic, whose values are
    whole), the detector in 2 micro-g steps as second differences (``detector_2ug_delta2``),
    sigma on its 1 % steps (`sigma_steps`) as the steps' numbers' deltas
    (``sigma_step_delta``), the device stamps as ``t_dev - t_us`` deltas
    (``t_dev_offset_delta``), all zigzag varints; a column with a value that is not finite or
    beyond +-2147 g stays float64 in its old field. `decode_calibrated` reads every form."""
    parts = [*_string_fields(_F_SENSOR, sensor_id),
             *_time_fields(batch.t_us, _F_T0_US, _F_DT_US),
             *_compact_axes(batch.a_g, UG_PER_G, (_F_X, _F_Y, _F_Z),
                            (_F_X_FIX, _F_Y_FIX, _F_Z_FIX)),
             *_packed(_F_CAL_QUASI_STATIC, _le_bytes(batch.quasi_static, "|u1")),
             *_detector_fields(batch.detector_g)]
    if batch.recorded:
        parts += [*_packed(_F_CAL_STATUS, _le_bytes(batch.status, "|u1")),
                  *_sigma_fields(sigma_steps(batch.sigma_mg))]
    if batch.t_dev is not None:
        # the device stamp's distance from t_us changes only when the time base does (a
        # reboot, a gap): its deltas are zeros where the stamps' own carry the jitter
        parts += _varint_field(_F_CAL_T_DEV_OFFSET, _deltas(batch.t_dev - batch.t_us))
    return _join(parts)


#: The detector's step in the log, g: within 1 micro-g of its value (it is compared with a
#: threshold of milli-g; one bit less a sample than micro-g steps).
DETECTOR_STEP_G = 2e-6


def _detector_fields(detector_g: np.ndarray) -> list[Any]:
    """The detector in steps of ``DETECTOR_STEP_G`` as second differences
    (``detector_2ug_delta2``: it is a low-pass filter's output, so its slope changes less
    than its value), or float64."""
    fixed = _fixed_point(detector_g, 1.0 / DETECTOR_STEP_G)
    if fixed is None:
        return _packed(_F_CAL_DETECTOR, _le_bytes(detector_g, "<f8"))
    return _varint_field(_F_CAL_DETECTOR_UG_2, _deltas(_deltas(fixed)))


def _sigma_fields(steps_mg: np.ndarray) -> list[Any]:
    """Sigma already on its ladder (`sigma_steps`) as the steps' numbers k (sigma =
    (1 + ``SIGMA_STEP``) ** k mg), differences (``sigma_step_delta``: a change of one step is
    the same byte at any sigma, which a micro-g difference is not); sigma that is not all on
    the ladder (zero, negative, not finite) as micro-g differences, or float64."""
    if len(steps_mg) and np.all(np.isfinite(steps_mg) & (steps_mg > 0)):
        k = np.rint(np.log(steps_mg) / _LOG_SIGMA_STEP)
        if np.array_equal(_ladder_mg(k), steps_mg):
            return _varint_field(_F_CAL_SIGMA_STEP, _deltas(k))
    return _compact_column(steps_mg, UG_PER_G / 1e3, _F_CAL_SIGMA, _F_CAL_SIGMA_UG)


def _ladder_mg(k: np.ndarray) -> np.ndarray:
    """Sigma, mg, of the ladder's steps ``k`` (`sigma_steps`)."""
    return np.exp(np.asarray(k, np.float64) * _LOG_SIGMA_STEP)


#: Relative step of the sigma the log keeps: sigma is itself an estimate (its own relative
#: uncertainty is several percent), so 1 % steps say all it means; between updates it then
#: stays on one step for long runs, which the delta field and zstd store in next to nothing
#: (the raw value wanders by parts per thousand from sample to sample).
SIGMA_STEP = 0.01
_LOG_SIGMA_STEP = math.log1p(SIGMA_STEP)


def sigma_steps(sigma_mg: np.ndarray) -> np.ndarray:
    """Each positive finite sigma on the nearest step of a geometric ladder of ratio
    1 + ``SIGMA_STEP`` (the steps are ``(1 + SIGMA_STEP) ** k`` mg, k an integer: within half
    a step, 0.5 %, of the value); zero, negative and non-finite values as they are. What the
    log's compact form keeps of sigma."""
    s = np.asarray(sigma_mg, np.float64)
    ok = np.isfinite(s) & (s > 0)
    if not ok.any():
        return s
    out = s.copy()
    out[ok] = _ladder_mg(np.rint(np.log(s[ok]) / _LOG_SIGMA_STEP))
    return out


def _same_length(t_us: np.ndarray, **columns: np.ndarray) -> None:
    """ValueError naming the first column whose length is not ``t_us``'s (a malformed message)."""
    for name, column in columns.items():
        if len(column) != len(t_us):
            raise ValueError(f"{name} has {len(column)} values but t_us has {len(t_us)}")


def _stamps(buf: bytes, fields: dict[int, list[_Occurrence]], f_abs: int, f_first: int,
            f_delta: int, what: str) -> np.ndarray | None:
    """A stamp column from its absolute field or from first value + deltas; None if the
    message has neither."""
    if _present(fields, f_first, (_WT_I64,)):
        first = _fixed64(buf, fields[f_first], "<i8", what)
        dt = _sint_varints(buf, fields.get(f_delta), what)
        t = np.empty(len(dt) + 1, np.int64)
        t[0] = first[-1]  # a singular field: the last occurrence wins
        np.cumsum(dt, out=t[1:])
        t[1:] += t[0]
        return t
    if f_abs in fields:
        return np.array(_fixed64(buf, fields[f_abs], "<i8", what), dtype=np.int64)
    return None


def _axes(buf: bytes, fields: dict[int, list[_Occurrence]], names: Sequence[str],
          scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Time stamps and the (N, 3) axis block (float64 fields, or the fixed-point deltas summed
    and divided by ``scale``), with the lengths checked against each other."""
    t_us = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
    if t_us is None:
        t_us = np.zeros(0, np.int64)
    if any(_present(fields, f, _VARINT_WT) for f in (_F_X_FIX, _F_Y_FIX, _F_Z_FIX)):
        columns = [np.cumsum(_sint_varints(buf, fields.get(f), name)) / scale
                   for f, name in zip((_F_X_FIX, _F_Y_FIX, _F_Z_FIX), names, strict=True)]
    else:
        columns = [_fixed64(buf, fields.get(f), "<f8", name)
                   for f, name in zip((_F_X, _F_Y, _F_Z), names, strict=True)]
    _same_length(t_us, **dict(zip(names, columns, strict=True)))
    v = np.empty((len(t_us), 3))
    for i, column in enumerate(columns):
        v[:, i] = column
    return t_us, v


def _column(buf: bytes, fields: dict[int, list[_Occurrence]], f_float: int, f_fixed: int,
            scale: float, what: str) -> np.ndarray:
    if _present(fields, f_fixed, _VARINT_WT):
        return np.cumsum(_sint_varints(buf, fields[f_fixed], what)) / scale
    return np.array(_fixed64(buf, fields.get(f_float), "<f8", what), dtype=np.float64)


_STAMP_FIELDS = (_F_T_US, _F_T0_US, _F_DT_US)
_RAW_FIELDS = frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_X, _F_Y, _F_Z, _F_RAW_AUX_NAMES,
                         _F_RAW_AUX, _F_X_FIX, _F_Y_FIX, _F_Z_FIX, _F_RAW_ARRIVAL_SAMPLES,
                         _F_RAW_ARRIVAL_LOG_US, _F_RAW_ARRIVAL_LAG_US))
_CAL_FIELDS = frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_X, _F_Y, _F_Z, _F_CAL_QUASI_STATIC,
                         _F_CAL_DETECTOR, _F_CAL_STATUS, _F_CAL_SIGMA, _F_CAL_T_DEV,
                         _F_X_FIX, _F_Y_FIX, _F_Z_FIX, _F_CAL_DETECTOR_UG, _F_CAL_SIGMA_UG,
                         _F_CAL_T_DEV0, _F_CAL_DT_DEV, _F_CAL_BODY_ROTATION,
                         _F_CAL_SIGMA_STEP, _F_CAL_DETECTOR_UG_2, _F_CAL_T_DEV_OFFSET,
                         _F_CAL_BODY_QUATERNION))


def decode_raw(data: bytes | bytearray | memoryview) -> tuple[str, RawBatch]:
    """Parse a ``recal.RawBatch`` message (either form) into (sensor_id, batch); ValueError if
    malformed."""
    sensor_id, batch, _ = decode_raw_arrivals(data)
    return sensor_id, batch


#: A joined raw message's arrivals: samples per arrival, and the log time of each in us after
#: the message's (None if the message has no log times).
Arrivals = tuple[np.ndarray, np.ndarray | None]


def decode_raw_arrivals(data: bytes | bytearray | memoryview
                        ) -> tuple[str, RawBatch, Arrivals | None]:
    """`decode_raw` and the message's arrivals in one reading of it: (sensor_id, batch,
    arrivals), arrivals None for a message of one arrival (any message of an older
    recording). ValueError if malformed, or if the arrival sizes do not add up to the
    message's samples."""
    buf = _as_bytes(data)
    fields = _scan(buf, _RAW_FIELDS)
    t_us, v = _axes(buf, fields, ("x", "y", "z"), 1.0)
    names = tuple(_strings(buf, fields.get(_F_RAW_AUX_NAMES)))
    aux = np.array(_fixed64(buf, fields.get(_F_RAW_AUX), "<f8", "aux"), dtype=np.float64)
    if len(aux) != len(t_us) * len(names):
        raise ValueError(f"aux has {len(aux)} values, expected {len(t_us)} samples x "
                         f"{len(names)} channels")
    batch = RawBatch(t_us, v, aux.reshape(len(t_us), len(names)), names)
    return _last_string(buf, fields.get(_F_SENSOR)), batch, _arrivals(buf, fields, t_us)


def _arrivals(buf: bytes, fields: dict[int, list[_Occurrence]], t_us: np.ndarray
              ) -> Arrivals | None:
    """The arrival fields of a raw message already scanned (None if it has none)."""
    if not _present(fields, _F_RAW_ARRIVAL_SAMPLES, _VARINT_WT):
        return None
    sizes = _sint_varints(buf, fields[_F_RAW_ARRIVAL_SAMPLES], "arrival_samples")
    if (sizes < 0).any() or sizes.sum() != len(t_us):
        raise ValueError("arrival_samples do not add up to the message's samples")
    log_us = None
    if _present(fields, _F_RAW_ARRIVAL_LAG_US, _VARINT_WT):
        lag = _arrival_lag_us(t_us, sizes)
        if lag is None:
            raise ValueError("arrival_lag_delta_us needs arrivals of at least one sample")
        log_us = np.cumsum(_sint_varints(buf, fields[_F_RAW_ARRIVAL_LAG_US],
                                         "arrival_lag_delta_us"))
        if len(log_us) == len(sizes):
            log_us += lag
    elif _F_RAW_ARRIVAL_LOG_US in fields:
        log_us = np.cumsum(_sint_varints(buf, fields[_F_RAW_ARRIVAL_LOG_US], "arrival_log_us"))
    if log_us is not None and len(log_us) != len(sizes):
        raise ValueError(f"arrival log times: {len(log_us)} values for {len(sizes)} arrivals")
    return sizes, log_us


def decode_calibrated(data: bytes | bytearray | memoryview) -> tuple[str, CalibratedBatch]:
    """Parse a ``recal.CalibratedBatch`` (either form) into (sensor_id, batch); ValueError if
    malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, _CAL_FIELDS)
    if any(_present(fields, f, (_WT_LEN, _WT_I64))
           for f in (_F_CAL_BODY_ROTATION, _F_CAL_BODY_QUATERNION)):
        raise ValueError("a body message of the log's form holds a rotation, not samples: "
                         "its samples are the calibrated topic's rotated (decode_body_rotation, "
                         "recording.read_all_calibrated)")
    t_us, a_g = _axes(buf, fields, ("x_g", "y_g", "z_g"), UG_PER_G)
    quasi = _bools(buf, fields.get(_F_CAL_QUASI_STATIC), "quasi_static")
    if _present(fields, _F_CAL_DETECTOR_UG_2, _VARINT_WT):
        detector = np.cumsum(np.cumsum(_sint_varints(
            buf, fields[_F_CAL_DETECTOR_UG_2], "detector_g"))) * DETECTOR_STEP_G
    else:
        detector = _column(buf, fields, _F_CAL_DETECTOR, _F_CAL_DETECTOR_UG, UG_PER_G,
                           "detector_g")
    _same_length(t_us, quasi_static=quasi, detector_g=detector)
    status = sigma = None  # absent: a recording from before statuses (not recorded, NaN)
    if (_F_CAL_STATUS in fields or _F_CAL_SIGMA in fields
            or _present(fields, _F_CAL_SIGMA_UG, _VARINT_WT)
            or _present(fields, _F_CAL_SIGMA_STEP, _VARINT_WT)):
        status = _small_varints(buf, fields.get(_F_CAL_STATUS), "status")
        if _present(fields, _F_CAL_SIGMA_STEP, _VARINT_WT):
            sigma = _ladder_mg(np.cumsum(_sint_varints(buf, fields[_F_CAL_SIGMA_STEP],
                                                       "sigma_mg")))
        else:
            sigma = _column(buf, fields, _F_CAL_SIGMA, _F_CAL_SIGMA_UG, UG_PER_G / 1e3,
                            "sigma_mg")
        _same_length(t_us, status=status, sigma_mg=sigma)
    # absent: a recording from before device times were kept
    if _present(fields, _F_CAL_T_DEV_OFFSET, _VARINT_WT):
        offset = np.cumsum(_sint_varints(buf, fields[_F_CAL_T_DEV_OFFSET], "t_dev"))
        _same_length(t_us, t_dev=offset)
        t_dev: np.ndarray | None = t_us + offset
    else:
        t_dev = _stamps(buf, fields, _F_CAL_T_DEV, _F_CAL_T_DEV0, _F_CAL_DT_DEV, "t_dev")
    if t_dev is not None:
        _same_length(t_us, t_dev=t_dev)
    return _last_string(buf, fields.get(_F_SENSOR)), CalibratedBatch(t_us, a_g, quasi, detector,
                                                                      status, sigma, t_dev)


def encode_body_rotation(sensor_id: str, t_us: np.ndarray, rotation: np.ndarray) -> bytes:
    """The log's body message: the times of its samples (``t0_us`` + ``dt_us``) and the
    rotation ``body_rotation`` (3 x 3, row-major) that turns the calibrated topic's samples at
    those times into the body frame (``R @ a``, `recal.core.alignment.to_body`); no value the
    calibrated topic and the alignment already say. `decode_body_rotation` reads it back."""
    r = np.asarray(rotation, np.float64)
    if r.shape != (3, 3):
        raise ValueError(f"rotation must be 3 x 3, got shape {r.shape}")
    q = _quaternion(r)
    # a rotation in 4 numbers instead of 9, if they give it back to rounding (else the matrix)
    kept = (_packed(_F_CAL_BODY_QUATERNION, _le_bytes(q, "<f8"))
            if np.max(np.abs(_rotation_of(q) - r)) <= _QUATERNION_TOL
            else _packed(_F_CAL_BODY_ROTATION, _le_bytes(r.reshape(9), "<f8")))
    return _join([*_string_fields(_F_SENSOR, sensor_id),
                  *_time_fields(np.asarray(t_us, np.int64), _F_T0_US, _F_DT_US), *kept])


#: How far the matrix a body quaternion gives back may be from the rotation logged (each
#: element): a few float64 roundings, a body value 1e-14 g away (the matrix otherwise).
_QUATERNION_TOL = 1e-14


def _quaternion(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method:
    the largest of the four squared components first, for accuracy)."""
    tr = float(np.trace(r))
    diag = np.diag(r)
    i = int(np.argmax([tr, *diag]))
    if i == 0:
        s = 2.0 * math.sqrt(max(1.0 + tr, 0.0))
        q = [s / 4, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif i == 1:
        s = 2.0 * math.sqrt(max(1.0 + r[0, 0] - r[1, 1] - r[2, 2], 0.0))
        q = [(r[2, 1] - r[1, 2]) / s, s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif i == 2:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] + r[1, 1] - r[2, 2], 0.0))
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(max(1.0 - r[0, 0] - r[1, 1] + r[2, 2], 0.0))
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4]
    out = np.array(q, np.float64) if s > 0 else np.full(4, np.nan)
    return -out if out[0] < 0 else out


def _rotation_of(q: np.ndarray) -> np.ndarray:
    """The rotation matrix of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def decode_body_rotation(data: bytes | bytearray | memoryview
                         ) -> tuple[str, np.ndarray, np.ndarray] | None:
    """(sensor_id, t_us, rotation 3 x 3) of a body message in the log's form
    (`encode_body_rotation`), None for a message of samples (`decode_calibrated` reads it);
    ValueError if malformed."""
    buf = _as_bytes(data)
    fields = _scan(buf, frozenset((_F_SENSOR, *_STAMP_FIELDS, _F_CAL_BODY_ROTATION,
                                   _F_CAL_BODY_QUATERNION)))
    if _present(fields, _F_CAL_BODY_QUATERNION, (_WT_LEN, _WT_I64)):
        q = _fixed64(buf, fields[_F_CAL_BODY_QUATERNION], "<f8", "body_quaternion")
        if len(q) != 4:
            raise ValueError(f"body_quaternion has {len(q)} values, not 4")
        r = _rotation_of(q)
    elif _present(fields, _F_CAL_BODY_ROTATION, (_WT_LEN, _WT_I64)):
        values = _fixed64(buf, fields[_F_CAL_BODY_ROTATION], "<f8", "body_rotation")
        if len(values) != 9:
            raise ValueError(f"body_rotation has {len(values)} values, not 9")
        r = values.reshape(3, 3).copy()
    else:
        return None
    t_us = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
    return (_last_string(buf, fields.get(_F_SENSOR)),
            np.zeros(0, np.int64) if t_us is None else t_us, r)


def batch_extent(data: bytes | bytearray | memoryview) -> tuple[int, int | None, int | None]:
    """(sample count, first t_us, last t_us) of a RawBatch or CalibratedBatch message (either
    form).

    Reads only the time fields (both messages keep them as fields 2, 11 and 12), so summaries
    of long recordings need not decode the samples. Times are None for an empty batch.
    """
    buf = _as_bytes(data)
    fields = _scan(buf, frozenset(_STAMP_FIELDS))
    if _present(fields, _F_T0_US, (_WT_I64,)):
        t = _stamps(buf, fields, _F_T_US, _F_T0_US, _F_DT_US, "t_us")
        assert t is not None
        return len(t), int(t[0]), int(t[-1])
    runs = [(s, e) for wt, s, e in fields.get(_F_T_US, ())
            if wt in (_WT_LEN, _WT_I64) and e > s]
    if any((e - s) % 8 for s, e in runs):
        raise ValueError("packed field t_us is not a multiple of 8 bytes")
    if not runs:
        return 0, None, None
    count = sum((e - s) // 8 for s, e in runs)
    first = int(np.frombuffer(buf, "<i8", 1, runs[0][0])[0])
    last = int(np.frombuffer(buf, "<i8", 1, runs[-1][1] - 8)[0])
    return count, first, last
