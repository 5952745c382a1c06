"""The pipeline's state in its parts (`core.pipeline_state`): each part writes and reads its own
(the detector's `DetectorState`, the windows as `buffer.Window`), a checkpoint's document keeps
its keys and order, and a document read back steps as the pipeline it came from."""

from __future__ import annotations

import json

import numpy as np

from recal.core import detector as det
from recal.core.buffer import Window
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline
from recal.core.pipeline_config import DETECTOR_KEYS, KEYS, PipelineConfig
from recal.sim.wearer import SensorSpec, simulate

RATE_HZ = 50.0

#: A checkpoint's top-level keys, in the order every checkpoint so far has written them (a
#: node logs the document as JSON text: the order is part of the bytes).
CHECKPOINT_KEYS = ["version", "config", "model", "prior", "estimate", "bootstrapped",
                   "from_prior", "centre0", "aux_names", "t0_us", "buffer", "detector", "open",
                   "pending", "fresh", "last_t_us", "last_gate", "counts", "last_report"]
DETECTOR_DOC_KEYS = ["s0", "zero_raw", "zi_hp", "zi_lp", "last_v", "same_run", "started",
                     "step_raw", "changes"]


def _raw(hours: float = 0.2, seed: int = 3):
    rng = np.random.default_rng(seed)
    return simulate(hours, RATE_HZ, seed, SensorSpec.random(rng, offset_mg=50, gain_pct=3)).raw


def test_the_detectors_settings_nest_in_the_config_and_its_keys_stay_flat() -> None:
    """A config file's [pipeline] keys and a checkpoint's "config" are flat (threshold_g beside
    window_s); the detector's are the nested DetectorConfig's, at the pipeline's rate."""
    cfg = PipelineConfig.of(rate_hz=100.0, threshold_g=0.02, flat_s=2.0, hp_hz=0.4,
                            lp_hz=0.3, window_s=3.0, full_scale_g=8.0)
    d = cfg.detection
    assert (d.rate_hz, d.threshold_g, d.flat_s, d.hp_hz, d.lp_hz) == (100.0, 0.02, 2.0, 0.4, 0.3)
    doc = cfg.to_dict()
    assert list(doc) == [*KEYS, "estimator", "buffer"]
    assert [doc[k] for k in DETECTOR_KEYS] == [0.02, 2.0, 0.4, 0.3]
    assert PipelineConfig.from_dict(json.loads(json.dumps(doc))) == cfg
    # the sensor's detector: the nested settings with its scale, zero-g and clip level
    sensor = cfg.detector(1024.0, (1.0, 2.0, 3.0))
    assert (sensor.threshold_g, sensor.rate_hz, sensor.s0) == (0.02, 100.0, 1024.0)
    assert sensor.clip_raw == 0.98 * 8.0 * 1024.0 and sensor.zero_raw == (1.0, 2.0, 3.0)
    # another rate, the detector's with it
    assert PipelineConfig(rate_hz=25.0).detection.rate_hz == 25.0


def test_detector_state_round_trips_through_json_bit_for_bit() -> None:
    cfg = PipelineConfig(rate_hz=RATE_HZ).detector(1024.0, (1.0, -2.0, 3.0))
    raw = _raw(0.01)
    st, _ = det.detect(cfg, det.init_state(cfg), raw.v)
    back = det.DetectorState.from_dict(json.loads(json.dumps(st.to_dict())))
    for name in ("zi_hp", "zi_lp", "last_v", "step_raw"):
        assert np.array_equal(getattr(back, name), getattr(st, name))
    assert (back.same_run, back.started, back.changes) == (st.same_run, st.started, st.changes)
    # the state read back goes on exactly as the one it was written from
    more = raw.v[:50] + 1.0
    (a_st, a), (b_st, b) = det.detect(cfg, st, more), det.detect(cfg, back, more)
    assert np.array_equal(a.detector_g, b.detector_g) and np.array_equal(a.gate, b.gate)
    assert np.array_equal(a_st.zi_lp, b_st.zi_lp)


def test_a_detector_before_its_first_sample_writes_none_for_its_last_sample() -> None:
    d = det.Detector(PipelineConfig(rate_hz=RATE_HZ).detector(256.0))
    doc = d.to_dict()
    assert list(doc) == DETECTOR_DOC_KEYS
    assert doc["last_v"] == [None, None, None] and doc["started"] is False
    assert doc["step_raw"] == [None, None, None]  # no step seen yet
    assert np.isnan(det.DetectorState.from_dict(doc).last_v).all()
    assert np.isinf(det.DetectorState.from_dict(doc).step_raw).all()


def test_a_window_round_trips_as_the_checkpoints_list() -> None:
    w = Window(np.array([1.5, -2.0, 1024.25]), np.array([21.0]), 123_456, 100, 0.75)
    doc = w.to_list()
    assert doc == [[1.5, -2.0, 1024.25], [21.0], 123_456, 100, 0.75]
    back = Window.from_list(json.loads(json.dumps(doc)))
    assert np.array_equal(back.v, w.v) and np.array_equal(back.aux, w.aux)
    assert (back.t_us, back.n, back.var) == (w.t_us, w.n, w.var)


def test_checkpoint_keeps_its_keys_in_order_and_resumes_exactly() -> None:
    raw = _raw()
    model = SensorModel.diagonal(1024.0)
    ref = Pipeline(PipelineConfig(rate_hz=RATE_HZ), model, Prior.default(model), raw.aux_names)
    a = ref.step(raw[:20_000]).calibrated
    doc = ref.state_dict()
    assert list(doc)[:len(CHECKPOINT_KEYS)] == CHECKPOINT_KEYS
    assert list(doc["detector"]) == DETECTOR_DOC_KEYS
    assert ref.counts["updates"] > 0 and doc["fresh"] == [w.to_list() for w in ref.fresh]
    back = Pipeline.from_state_dict(json.loads(json.dumps(doc)))
    assert json.dumps(back.state_dict()) == json.dumps(doc)
    b, c = ref.step(raw[20_000:]).calibrated, back.step(raw[20_000:]).calibrated
    assert len(a) and np.array_equal(b.a_g, c.a_g) and np.array_equal(b.status, c.status)
    assert json.dumps(back.state_dict()) == json.dumps(ref.state_dict())
