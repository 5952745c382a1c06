"""A posture the model misses is no offset jump (`estimator._posture_misfit_g2`).

A worn ActiGraph's axes are 1-3 degrees from square; under the diagonal model a still posture
not shown before misses by some mg, and the window means of that one posture (merged into one
slot of the buffer) all miss alike. Counted as independent windows against their averaged
noise, that posture looked like a knock: the offsets jumped, came back at the next posture,
and the output was suspect for 30 min after each, most of the time on real recordings. The
simulated wearer through a 256 counts/g, 30 Hz sensor (an ActiGraph's counts) with such a
cross-axis term shows it; a real knock on the same sensor is still one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.outputs import StepOutput
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import Status
from recal.samples import RawBatch
from recal.sim import wearer as sim
from recal.sim.sensor import SensorSpec

pytestmark = [pytest.mark.slow, pytest.mark.float_sensitive]

RATE_HZ = 30.0
S0 = 256.0  # an ActiGraph's counts per g: 3.9 mg steps
HOURS = 2.0
SENSOR = SensorSpec(counts_per_g=S0, full_scale_g=8.0, offset_g=(0.02, -0.04, 0.01),
                    gain=(0.005, 0.008, 0.018), misalignment_rad=(0.02, 0.0, 0.0))


def _run(raw: RawBatch) -> tuple[np.ndarray, list[StepOutput]]:
    model = SensorModel.diagonal(S0)  # no cross-axis terms: the model misses the sensor's
    pipe = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model))
    outs = [pipe.step(raw[i:i + 1000]) for i in range(0, len(raw), 1000)]
    return np.concatenate([o.calibrated.status for o in outs]), outs


def _jumps(outs: list[StepOutput]) -> list[int]:
    return [w.t_us for o in outs for w in o.watch
            if w.kind == "suspect" and "jumped" in str(w.detail.get("reason"))]


def test_a_posture_the_model_misses_is_no_jump() -> None:
    res = sim.simulate(HOURS, RATE_HZ, 3, SENSOR)
    status, outs = _run(res.raw)
    late = res.raw.t_us >= res.raw.t_us[0] + 3_600_000_000
    assert not _jumps(outs)
    assert np.mean(status[late] == Status.CALIBRATED) >= 0.9


def test_a_knock_on_that_sensor_is_still_a_jump() -> None:
    res = sim.simulate(HOURS, RATE_HZ, 3, SENSOR)
    knocked = sim.with_sensor(res, replace(SENSOR, offset_g=tuple(
        np.add(SENSOR.offset_g, (0.06, -0.05, 0.04)))))
    k = int(1.5 * 3600 * RATE_HZ)
    raw = RawBatch(res.raw.t_us, np.concatenate([res.raw.v[:k], knocked.raw.v[k:]]),
                   res.raw.aux, res.raw.aux_names)
    status, outs = _run(raw)
    jumps = _jumps(outs)
    assert jumps and jumps[0] >= raw.t_us[k]
    assert (jumps[0] - raw.t_us[k]) / 60e6 < 10.0  # found within 10 min
    assert np.any(status[k:] == Status.SUSPECT)
