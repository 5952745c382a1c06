"""The vocabulary every layer shares: batches of raw and calibrated triaxial samples.

Plain frozen dataclasses over numpy arrays, no I/O. The core computes on them, the shell
(serial, Zenoh, MCAP, CSV) converts the world to and from them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

__all__ = ["REBATCH_SAMPLES", "CalibratedBatch", "RawBatch", "batch_groups", "conform_channels",
           "join_by_layout",
           "rebatch"]

T = TypeVar("T")

#: Samples per batch `rebatch` makes by default.
REBATCH_SAMPLES = 65_536


def _as_time_us(t_us: np.ndarray | Sequence[int]) -> np.ndarray:
    return np.ascontiguousarray(t_us, dtype=np.int64).reshape(-1)


@dataclass(frozen=True, eq=False)
class RawBatch:
    """Raw samples of one sensor, in arrival order.

    Attributes:
        t_us: (N,) int64 device time stamps in microseconds.
        v: (N, 3) float64 raw readings x, y, z in the sensor's own unit (ADC counts, g, m/s^2).
        aux: (N, K) float64 auxiliary channels (temperature, supply voltage, ...), K may be 0.
        aux_names: K channel names, as the device or file named them; never assumed fixed.
    """

    t_us: np.ndarray
    v: np.ndarray
    aux: np.ndarray
    aux_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        t = _as_time_us(self.t_us)
        v = np.ascontiguousarray(self.v, dtype=np.float64).reshape(-1, 3)
        names = tuple(str(n) for n in self.aux_names)
        aux = np.ascontiguousarray(self.aux, dtype=np.float64).reshape(len(t), len(names))
        if len(v) != len(t):
            raise ValueError(f"t_us has {len(t)} samples but v has {len(v)}")
        object.__setattr__(self, "t_us", t)
        object.__setattr__(self, "v", v)
        object.__setattr__(self, "aux", aux)
        object.__setattr__(self, "aux_names", names)

    @classmethod
    def of_checked(cls, t_us: np.ndarray, v: np.ndarray, aux: np.ndarray,
                   aux_names: tuple[str, ...]) -> RawBatch:
        """A batch of arrays that are already what the constructor would make of them
        (contiguous int64 (N,), float64 (N, 3) and (N, K), K names as a tuple of str): taken
        as they are, without conversion or check (a parser's one sample per arrival)."""
        new = object.__new__(cls)
        new.__dict__.update(t_us=t_us, v=v, aux=aux, aux_names=aux_names)
        return new

    @classmethod
    def empty(cls, aux_names: Sequence[str] = ()) -> RawBatch:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, len(aux_names))),
                   tuple(aux_names))

    @classmethod
    def concat(cls, batches: Sequence[RawBatch]) -> RawBatch:
        """Join batches that share the same auxiliary channel names."""
        if not batches:
            return cls.empty()
        names = batches[0].aux_names
        if any(b.aux_names != names for b in batches):
            raise ValueError("cannot concatenate batches with different auxiliary channels")
        return cls(np.concatenate([b.t_us for b in batches]),
                   np.concatenate([b.v for b in batches]),
                   np.concatenate([b.aux for b in batches]), names)

    def __len__(self) -> int:
        return len(self.t_us)

    def __getitem__(self, index: slice | np.ndarray) -> RawBatch:
        return RawBatch(self.t_us[index], self.v[index], self.aux[index], self.aux_names)

    def channel(self, name: str) -> np.ndarray:
        """One auxiliary channel by name (KeyError if the recording has no such channel)."""
        try:
            return self.aux[:, self.aux_names.index(name)]
        except ValueError:
            raise KeyError(f"no auxiliary channel {name!r}; have {list(self.aux_names)}") from None


@dataclass(frozen=True, eq=False)
class CalibratedBatch:
    """Calibrated acceleration of one sensor, sample for sample with the raw batch it came from.

    Attributes:
        t_us: (N,) int64 device time stamps in microseconds.
        a_g: (N, 3) float64 calibrated acceleration in g, sensor frame.
        quasi_static: (N,) bool, the detector's gate (Lötters eq. 2 below threshold, and not
            rejected as clipped, flat-lined or far from 1 g).
        detector_g: (N,) float64 the detector output LPF(REC(HPF(|v|))) in g.
        status: (N,) uint8 `recal.core.status.Status` of each sample (uncalibrated,
            bootstrapping, calibrated, held, suspect); 0 (not recorded, the default): a
            recording made before statuses existed.
        sigma_mg: (N,) float64 the predicted 1-sigma error of the calibrated vector from the
            parameters' uncertainty, mg (`core.status.predicted_sigma_mg`); NaN: not recorded,
            inf: nothing known (a sample published zeroed).
        t_dev: (N,) int64 the device's own time stamp of each sample, exactly as the raw
            batch carried it (its unit is the time base's, `recal.core.timebase`): the key
            that joins a calibrated sample to its raw one. ``t_us`` is the service's time
            base, which never goes back and so continues past a reboot; ``t_dev`` restarts
            with the device. None: not recorded (a recording made before it was kept).
    """

    t_us: np.ndarray
    a_g: np.ndarray
    quasi_static: np.ndarray
    detector_g: np.ndarray
    status: np.ndarray | None = None
    sigma_mg: np.ndarray | None = None
    t_dev: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = _as_time_us(self.t_us)
        n = len(t)
        object.__setattr__(self, "t_us", t)
        object.__setattr__(self, "a_g", np.ascontiguousarray(self.a_g, np.float64).reshape(-1, 3))
        object.__setattr__(self, "quasi_static",
                           np.ascontiguousarray(self.quasi_static, bool).reshape(-1))
        object.__setattr__(self, "detector_g",
                           np.ascontiguousarray(self.detector_g, np.float64).reshape(-1))
        object.__setattr__(self, "status", np.zeros(n, np.uint8) if self.status is None
                           else np.ascontiguousarray(self.status, np.uint8).reshape(-1))
        object.__setattr__(self, "sigma_mg", np.full(n, np.nan) if self.sigma_mg is None
                           else np.ascontiguousarray(self.sigma_mg, np.float64).reshape(-1))
        if self.t_dev is not None:
            object.__setattr__(self, "t_dev", _as_time_us(self.t_dev))
        if not (len(self.a_g) == len(self.quasi_static) == len(self.detector_g) == n
                == len(self.status) == len(self.sigma_mg)
                == (n if self.t_dev is None else len(self.t_dev))):
            raise ValueError("calibrated batch fields differ in length")

    @classmethod
    def empty(cls) -> CalibratedBatch:
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0))

    @classmethod
    def of_checked(cls, t_us: np.ndarray, a_g: np.ndarray, quasi_static: np.ndarray,
                   detector_g: np.ndarray, status: np.ndarray, sigma_mg: np.ndarray,
                   t_dev: np.ndarray | None = None) -> CalibratedBatch:
        """A batch of arrays that are already what the constructor would make of them
        (contiguous, of the documented dtypes and shapes, one length): taken as they are,
        without conversion or check. For the live path, which builds a batch or two from
        checked ones at every arrival, where the seven conversions cost more than the rest."""
        new = object.__new__(cls)
        new.__dict__.update(t_us=t_us, a_g=a_g, quasi_static=quasi_static,
                            detector_g=detector_g, status=status, sigma_mg=sigma_mg, t_dev=t_dev)
        return new

    @classmethod
    def concat(cls, batches: Sequence[CalibratedBatch]) -> CalibratedBatch:
        if not batches:
            return cls.empty()
        devs = [b.t_dev for b in batches]
        return cls(np.concatenate([b.t_us for b in batches]),
                   np.concatenate([b.a_g for b in batches]),
                   np.concatenate([b.quasi_static for b in batches]),
                   np.concatenate([b.detector_g for b in batches]),
                   np.concatenate([b.status for b in batches]),
                   np.concatenate([b.sigma_mg for b in batches]),
                   None if any(d is None for d in devs) else np.concatenate(devs))

    @property
    def recorded(self) -> bool:
        """Whether the batch carries statuses (a recording from before them does not)."""
        return bool(self.status.any())

    def __len__(self) -> int:
        return len(self.t_us)

    def with_device_time(self, t_dev: np.ndarray) -> CalibratedBatch:
        """This batch with the device's own stamps (``t_dev``), its other arrays shared and
        not converted or checked again: the live node attaches them to every batch it
        publishes, where a whole construction would cost more than the rest of the copy."""
        t = _as_time_us(t_dev)
        if len(t) != len(self.t_us):
            raise ValueError("calibrated batch fields differ in length")
        return CalibratedBatch.of_checked(self.t_us, self.a_g, self.quasi_static,
                                          self.detector_g, self.status, self.sigma_mg, t)

    def __getitem__(self, index: slice | np.ndarray) -> CalibratedBatch:
        return CalibratedBatch(self.t_us[index], self.a_g[index], self.quasi_static[index],
                               self.detector_g[index], self.status[index], self.sigma_mg[index],
                               None if self.t_dev is None else self.t_dev[index])


def batch_groups(items: Iterable[tuple[RawBatch, T]], min_samples: int = REBATCH_SAMPLES
                 ) -> Iterator[list[tuple[RawBatch, T]]]:
    """Consecutive (batch, anything) pairs in groups of at least ``min_samples`` samples (the
    last may hold fewer; a batch with other channels than the one before starts a new group,
    so whoever reads them still sees the change)."""
    group: list[tuple[RawBatch, T]] = []
    held = 0
    for item in items:
        if group and item[0].aux_names != group[0][0].aux_names:
            yield group
            group, held = [], 0
        group.append(item)
        held += len(item[0])
        if held >= min_samples:
            yield group
            group, held = [], 0
    if group:
        yield group


def rebatch(batches: Iterable[RawBatch], min_samples: int = REBATCH_SAMPLES
            ) -> Iterator[RawBatch]:
    """Consecutive batches joined into batches of at least ``min_samples`` (`batch_groups`);
    a batch that is big enough passes through as it is.

    Batch work in numpy costs per call as well as per sample, so fewer, larger batches cost
    less (docs/design.md, "Figures behind choices"), with the same windows (their state
    carries across batches; bit for bit on integer readings such as ADC counts, else a window
    cut by a batch end may differ in its last bit, `core.window_means`). `recal hindsight` and
    `recal discover` read recordings this way.
    """
    for group in batch_groups(((b, None) for b in batches), min_samples):
        yield group[0][0] if len(group) == 1 else RawBatch.concat([b for b, _ in group])


def join_by_layout(batches: list[RawBatch]) -> list[RawBatch]:
    """Consecutive batches joined where their channel layout is the same (it rarely changes:
    a device that re-announces a different header)."""
    groups: list[list[RawBatch]] = []
    for b in batches:
        if groups and groups[-1][0].aux_names == b.aux_names:
            groups[-1].append(b)
        else:
            groups.append([b])
    return [g[0] if len(g) == 1 else RawBatch.concat(g) for g in groups]


def conform_channels(batch: RawBatch, names: tuple[str, ...], needed: Sequence[str]
                     ) -> RawBatch | str:
    """The batch with exactly the channels ``names`` (reordered; unused missing ones NaN), or
    the reason it cannot be calibrated (a channel the model needs is missing)."""
    if batch.aux_names == names:
        return batch
    cols = []
    for name in names:
        if name in batch.aux_names:
            cols.append(batch.aux[:, batch.aux_names.index(name)])
        elif name in needed:
            return f"the model needs channel {name!r}, the stream has {list(batch.aux_names)}"
        else:
            cols.append(np.full(len(batch), np.nan))
    aux = np.column_stack(cols) if cols else np.zeros((len(batch), 0))
    return RawBatch(batch.t_us, batch.v, aux, names)
