"""A quiet digital wearable (an AX3: counts of 1/256 g, 0.5 mg of noise, its oscillator 0.3 %
off the nominal 100 Hz) that lies on a table for a stretch: the simulator's wearer, rounded to
whole counts and given in g as a device-file reader gives it."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from recal.samples import RawBatch
from recal.sim.sensor import SensorSpec, forward_model
from recal.sim.wearer import WearerSpec, simulate

COUNTS_PER_G = 256.0
SENSOR = SensorSpec(counts_per_g=COUNTS_PER_G, full_scale_g=8.0, noise_g=0.0005,
                    offset_g=(0.02, -0.015, 0.03), gain=(0.01, -0.008, 0.012))


def table_up(sensor: SensorSpec) -> np.ndarray:
    """A table tilted a few degrees (never quite level) so that the sensor reads the middle of one
    count on every axis: 0.5 mg of noise then never moves a reading (the case where a still
    quantized sensor repeats itself for minutes)."""
    ideal = replace(sensor, noise_g=0.0, quantize=False)
    x, y = np.meshgrid(np.arange(0.005, 0.08, 0.0002), np.arange(-0.08, -0.005, 0.0002))
    x, y = x.ravel(), y.ravel()
    u = np.column_stack([x, y, np.sqrt(1.0 - x * x - y * y)])
    c = forward_model(u, ideal)
    return u[int(np.argmin(np.max(np.abs(c - np.round(c)), axis=1)))]


@dataclass(frozen=True, eq=False)
class Quiet:
    """The recording (values in g), the truth, and which samples are still / on the table."""

    batch: RawBatch
    a_true_g: np.ndarray
    still: np.ndarray
    table: np.ndarray
    sensor: SensorSpec


def quiet_ax3(hours: float = 1.0, table_s: tuple[float, float] = (1200.0, 1200.0),
              real_hz: float = 100.3, seed: int = 3, sensor: SensorSpec = SENSOR) -> Quiet:
    """`hours` of a wearer sampled at real_hz on the device's clock, with the device on a
    table (perfectly still, `table_up`) for table_s = (start, length) seconds."""
    sim = simulate(hours, real_hz, seed, sensor, replace(WearerSpec(), always_aux=True))
    a = sim.truth.a_true_g.copy()
    still = sim.truth.still.copy()
    i0, i1 = (int(x * real_hz) for x in (table_s[0], sum(table_s)))
    a[i0:i1] = table_up(sensor)
    still[i0:i1] = True
    table = np.zeros(len(a), bool)
    table[i0:i1] = True
    raw = sim.raw
    counts = forward_model(a, sensor, temp_c=raw.channel(sensor.temp_channel),
                           vdd_v=raw.channel(sensor.supply_channel),
                           t_h=(raw.t_us - raw.t_us[0]) / 3.6e9,
                           rng=np.random.default_rng(seed + 7919))
    v_g = counts / sensor.counts_per_g if sensor.counts_per_g else counts
    return Quiet(RawBatch(raw.t_us, v_g, raw.aux, raw.aux_names), a, still, table, sensor)
