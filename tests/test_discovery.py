"""Effect discovery on simulated recordings with an effect nothing in the file names.

Each recording is a wearer-like simulation (30 min at 25 Hz) whose sensor has one extra effect
(or none, or two). The channels are called `board_temp` and `vbat`; discovery is called with
its defaults and never told what to look for. The noise-limited floor is the held-out error
the true parameters give on the same scored windows (the exact inverse of the simulator).
"""

from __future__ import annotations

import json
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from recal import cli
from recal.commands import discover as dr
from recal.config import PipelineSection, RediscoveryConfig, load_model_file
from recal.core import discovery as dc
from recal.core import discovery_data as dd
from recal.core.effects import Covariates, make_effect
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.residuals import ORIENTATION_FEATURES
from recal.errors import ConfigError, InputError, ModelError
from recal.io import csv_table
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.node.node import CalibrationNode, NodeSettings
from recal.samples import CalibratedBatch, RawBatch
from recal.sim import wearer as sim

RATE_HZ = 25.0
HOURS = 0.5
SEED = 11
#: A lively wearer: many short postures (orientations in every time block) and a board
#: temperature that wanders a few degrees within minutes. Nothing here names an effect.
WEARER = sim.WearerSpec(still_s=(10.0, 40.0), move_s=(3.0, 8.0), always_aux=True,
                        temp_wander_c=3.0, temp_wander_tau_min=5.0, temp_lag_min=1.0)
OFFSET_TC = (0.002, -0.0015, 0.002)  # g per °C
GAIN_TC = (0.001, -0.001, 0.0008)  # per °C (0.1 %/°C)
RATIO = 0.03  # per V
MISALIGN = tuple(np.radians([1.5, -1.0, 1.2]))
Q = (0.01, -0.01, 0.008)  # 1/g
DRIFT = (0.02, -0.02, 0.015)  # g per hour


def _sensor(**effects: object) -> sim.SensorSpec:
    return sim.SensorSpec.random(np.random.default_rng(3), temp_channel="board_temp",
                                 supply_channel="vbat", **effects)


def _discover(sensor: sim.SensorSpec, seed: int = SEED) -> tuple[dc.DiscoveryResult, float]:
    """Discovery with defaults on the recording, and the floor in mg on its scored windows."""
    raw = sim.simulate(HOURS, RATE_HZ, seed, sensor, WEARER).raw
    result = dc.discover(dd.data_from_batch(raw))
    data = result.data
    truth = sim.inverse_model(data.windows.v, sensor, temp_c=data.cov.get("board_temp"),
                              vdd_v=data.cov.get("vbat"), t_h=data.cov.t_h)
    xi = np.linalg.norm(truth, axis=1) - 1.0
    return result, 1e3 * float(np.sqrt(np.mean(xi[result.scored] ** 2)))


def _found(result: dc.DiscoveryResult) -> list[tuple[str, str | None]]:
    return [(e.kind, e.covariate) for e in result.selected]


CASES = {
    "offset_tc": ({"offset_tc_g_per_c": OFFSET_TC}, ("offset", "board_temp")),
    "gain_tc": ({"gain_tc_per_c": GAIN_TC}, ("gain", "board_temp")),
    "ratiometric": ({"ratiometric_per_v": RATIO}, ("ratiometric", "vbat")),
    "cross_axis": ({"misalignment_rad": MISALIGN}, ("cross_axis", None)),
    "nonlinearity": ({"q_per_g": Q}, ("nonlinearity", None)),
    "drift": ({"offset_drift_g_per_h": DRIFT}, ("offset", "time")),
}


@pytest.mark.parametrize("case", list(CASES))
def test_an_undeclared_effect_is_found_and_the_error_falls_to_the_floor(case: str) -> None:
    effects, expected = CASES[case]
    sensor = _sensor(**effects)
    result, floor = _discover(sensor)
    print(f"{case}: {_found(result)} held-out {result.heldout_base_mg:.2f} -> "
          f"{result.heldout_final_mg:.2f} mg, floor {floor:.2f} mg")
    assert _found(result) == [expected]
    assert result.selected[0].reference is None
    assert result.heldout_base_mg > 2.0 * floor  # the effect was there to be found
    assert result.heldout_final_mg <= 1.5 * floor
    assert result.steps[0].action == "add" and result.steps[0].gain > 0.5
    params = result.selected[0].params
    # the fitted values are the simulator's, in the model's conventions
    if case == "offset_tc":
        got = [params[f"{ax}_mg_per_board_temp"] for ax in "xyz"]
        np.testing.assert_allclose(got, 1e3 * np.array(OFFSET_TC), rtol=0.15)
    elif case == "gain_tc":  # sim: additive to 1 + gain; model: a factor on the scale
        got = [params[f"{ax}_pct_per_board_temp"] for ax in "xyz"]
        np.testing.assert_allclose(got, 100 * np.array(GAIN_TC) / (1 + np.array(sensor.gain)),
                                   rtol=0.15)
    elif case == "ratiometric":
        assert params["rho_per_unit"] == pytest.approx(RATIO, rel=0.05)
    elif case == "cross_axis":
        truth = sensor.axis_angles_deg
        for k, v in result.selected[0].extra.items():
            assert v == pytest.approx(truth[k], abs=0.1)
    elif case == "nonlinearity":  # the correction undoes the sim's distortion: opposite sign
        got = [params[f"q_{ax}_per_g"] for ax in "xyz"]
        np.testing.assert_allclose(got, -np.array(Q), atol=0.0015)
    elif case == "drift":
        got = [params[f"{ax}_mg_per_time"] for ax in "xyz"]
        np.testing.assert_allclose(got, 1e3 * np.array(DRIFT), rtol=0.1)


def test_a_recording_without_an_extra_effect_gets_nothing_added() -> None:
    result, floor = _discover(_sensor())
    print(f"none: held-out {result.heldout_base_mg:.2f} mg, floor {floor:.2f} mg, best "
          f"{max(result.last_round, key=lambda c: c.gain).label}")
    assert result.selected == () and result.steps == ()
    assert len(result.last_round) >= 10  # every candidate was tried: 3 per channel + pair + 3
    assert not any(c.passed for c in result.last_round)
    assert result.heldout_final_mg == result.heldout_base_mg <= 1.5 * floor
    assert result.model.names == result.base_model.names


def test_two_effects_at_once_are_both_found() -> None:
    sensor = _sensor(offset_tc_g_per_c=OFFSET_TC, ratiometric_per_v=RATIO)
    result, floor = _discover(sensor)
    print(f"two: steps {[(s.action, s.effect.label) for s in result.steps]} held-out "
          f"{result.heldout_base_mg:.2f} -> {result.heldout_final_mg:.2f} mg, floor {floor:.2f}")
    assert sorted(_found(result), key=str) == [("offset", "board_temp"), ("ratiometric", "vbat")]
    assert all(e.reference is None for e in result.selected)
    assert result.heldout_final_mg <= 1.5 * floor


def test_residual_analysis_points_at_the_missing_effect() -> None:
    result, _ = _discover(_sensor(offset_tc_g_per_c=OFFSET_TC))
    before, after = result.analysis_base, result.analysis_final
    best = max(before.explained, key=before.explained.__getitem__)
    assert best == "offset[board_temp]" and before.explained[best] > 0.8
    assert after.rms_mg < 0.3 * before.rms_mg
    assert set(before.correlation) == {"board_temp", "vbat", "time"}
    assert set(before.orientation) == set(ORIENTATION_FEATURES)


def test_time_blocks_are_contiguous_equal_and_cut_between_postures() -> None:
    rng = np.random.default_rng(0)
    # 30 still runs of 3-12 windows 2 s apart, separated by 5-30 s of movement
    t, now = [], 0
    for _ in range(30):
        n = int(rng.integers(3, 13))
        t.extend(now + 2_000_000 * np.arange(n))
        now = t[-1] + int(rng.integers(5, 30)) * 1_000_000
    t = np.array(t)
    shuffled = rng.permutation(len(t))
    blocks = dd.time_blocks(t[shuffled], 10)[np.argsort(shuffled)]
    assert np.all(np.diff(blocks) >= 0) and set(blocks) == set(range(10))
    sizes = np.bincount(blocks)
    assert sizes.min() >= 0.5 * len(t) / 10 and sizes.max() <= 1.5 * len(t) / 10
    cuts = np.flatnonzero(np.diff(blocks)) + 1
    gaps = np.diff(t)[cuts - 1]
    assert np.all(gaps > 2_000_000)  # every boundary falls in a movement gap


def test_ratiometric_with_a_reference_rail_jacobian_and_model_file() -> None:
    eff = make_effect("ratiometric", "vbat", 3.8, "vref", 2.5)
    model = SensorModel.diagonal(1000.0).with_effect(eff, 0.3)
    assert model.covariates == ("vbat", "vref") and eff.label == "ratiometric[vbat,vref]"
    again = SensorModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert again.names == model.names and again.effects[0] == eff
    rng = np.random.default_rng(1)
    v = rng.normal(size=(30, 3)) * 1000
    cov = Covariates(np.zeros(30), rng.normal(size=(30, 2)) * 0.2 + [3.8, 2.5], ("vbat", "vref"))
    p = model.nominal()
    p[:2] = [0.05, -0.03]
    xi, jac = model.residual_jacobian(p, v, cov)
    num = np.empty_like(jac)
    for j in range(len(p)):
        q = p.copy()
        q[j] += 1e-6 * max(1.0, abs(p[j]))
        num[:, j] = -(model.residual_jacobian(q, v, cov)[0] - xi) / (q[j] - p[j])
    np.testing.assert_allclose(jac, num, atol=1e-6 * np.abs(jac).max())
    with pytest.raises(ValueError, match="reference"):
        make_effect("gain", "vbat", 0.0, "vref")


class _Capture:
    """A sink that keeps the JSON messages (state and events) and the calibrated output."""

    def __init__(self) -> None:
        self.json_messages: list[tuple[str, dict]] = []
        self.cal: list[tuple[np.ndarray, np.ndarray]] = []  # (t_us, a_g) per batch

    def raw(self, *args: object, **kw: object) -> None:
        pass

    def calibrated(self, sensor_id: str, cal: CalibratedBatch, log_time_ns: int,
                   topic: str = "calibrated") -> None:
        if topic == "calibrated":
            self.cal.append((cal.t_us.copy(), cal.a_g.copy()))

    def calibrated_output(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.concatenate([t for t, _ in self.cal]),
                np.concatenate([a for _, a in self.cal]))

    def plot(self, *args: object, **kw: object) -> None:
        pass

    def json(self, sensor_id: str, suffix: str, obj: dict, log_time_ns: int) -> None:
        self.json_messages.append((suffix, obj))


def test_discovery_is_on_by_default_in_the_daemon() -> None:
    """The node's discovery with its defaults (its schedule, evidence, adoption and restart:
    tests/test_live_discovery.py)."""
    raw = sim.simulate(0.4, RATE_HZ, SEED, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw
    model = SensorModel.diagonal(1024.0)
    sink = _Capture()
    node = CalibrationNode(NodeSettings("s1", PipelineSection(), model, Prior.default(model),
                                        RATE_HZ), sink)
    for i in range(0, len(raw), 1000):
        node.process(raw[i:i + 1000], 0)
    assert node.settings.rediscovery == RediscoveryConfig() and RediscoveryConfig().active
    found = [o["detail"]["added"] for _, o in sink.json_messages
             if o.get("kind") == "discovery"]
    assert found[:2] == [["offset[board_temp]"]] * 2  # selected, then confirmed
    assert node.pipeline is not None and node.pipeline.model.has("offset", "board_temp")


def test_cli_discover_writes_the_report_and_a_model_replay_accepts(tmp_path: Path,
                                                                   capsys) -> None:
    raw = sim.simulate(0.4, RATE_HZ, 5, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw
    mcap = tmp_path / "in.mcap"
    with RecordingWriter(mcap, overwrite=True) as w:
        for i in range(0, len(raw), 1000):
            w.write_raw("wrist", raw[i:i + 1000], int(raw.t_us[i]) * 1000 + 1)
    report, model_file, plots = tmp_path / "r.json", tmp_path / "m.json", tmp_path / "plots"
    assert cli.main(["discover", str(mcap), "--json", str(report), "--write-model",
                     str(model_file), "--plots", str(plots)]) == 0
    table = capsys.readouterr().out
    assert "offset[board_temp]" in table and "held-out error" in table
    doc = json.loads(report.read_text())
    assert {"effects_selected", "heldout_error_mg", "steps"} <= set(doc)
    assert {"base", "final"} <= set(doc["heldout_error_mg"])
    assert doc["heldout_error_mg"]["final"] < 0.5 * doc["heldout_error_mg"]["base"]
    sel = doc["effects_selected"]
    assert [(e["kind"], e["covariate"]) for e in sel] == [("offset", "board_temp")]
    assert set(sel[0]["params"]) == {f"{ax}_mg_per_board_temp" for ax in "xyz"}
    assert doc["steps"][0]["effect"] == "offset[board_temp]" and doc["steps"][0]["candidates"]
    assert sorted(p.name for p in plots.iterdir()) == [
        "orientation_coverage.png", "residual_over_time.png", "residual_vs_covariate.png"]
    assert all(p.stat().st_size > 10_000 for p in plots.iterdir())
    model, prior = load_model_file(model_file)
    assert model.has("offset", "board_temp") and prior is not None

    out = tmp_path / "out.mcap"
    assert cli.main(["replay", str(mcap), "--out", str(out), "--model", str(model_file),
                     "--quiet"]) == 0
    states = [o for _, o, _ in rec.iter_json([out], "/wrist/calibration")]
    assert states and {f"o_board_temp_{ax}" for ax in "xyz"} <= set(states[-1]["params"])
    assert states[-1]["model"] == "offset+offset[board_temp]+scale"
    assert len(rec.read_all_calibrated(out, "wrist")) == len(raw)


def test_cli_discover_reads_a_static_table_and_a_csv_time_series(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=(24, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    table = tmp_path / "poses.csv"
    rows = 9.81 * u * [1.02, 0.99, 1.01] + [0.1, -0.05, 0.2] + rng.normal(0, 0.002, (24, 3))
    table.write_text("x_ms2,y_ms2,z_ms2\n" + "\n".join(",".join(map(str, r)) for r in rows))
    report = tmp_path / "t.json"
    assert cli.main(["discover", str(table), "--json", str(report), "--blocks", "6"]) == 0
    doc = json.loads(report.read_text())
    assert doc["input"]["kind"] == "table" and doc["input"]["windows"] == 24
    assert doc["effects_selected"] == []  # offsets and gains explain the table
    assert doc["held_at_start"] == []  # 24 directions all round: every parameter determined
    assert doc["heldout_error_mg"]["final"] < 1.0
    assert not dr.csv_has_time(table)

    series = tmp_path / "series.csv"
    raw = sim.simulate(0.4, RATE_HZ, 7, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw
    csv_table.write_raw_csv(series, raw)
    assert dr.csv_has_time(series)
    assert cli.main(["discover", str(series), "--json", str(report)]) == 0
    doc = json.loads(report.read_text())
    assert doc["input"]["kind"] == "windows" and doc["input"]["aux_names"] == ["board_temp",
                                                                               "vbat"]
    assert [(e["kind"], e["covariate"]) for e in doc["effects_selected"]] == [
        ("offset", "board_temp")]


def test_windows_read_batch_by_batch_are_those_of_the_whole_recording() -> None:
    """data_from_batches (bounded memory: `recal discover` of a long recording) gives
    data_from_batch of the batches joined: s0, the same windows at the same times, their means
    equal but for the order of the sums (a window cut by a batch end adds two partial sums)."""
    raw = sim.simulate(0.3, RATE_HZ, 3, _sensor(offset_tc_g_per_c=OFFSET_TC), WEARER).raw
    whole = dd.data_from_batch(raw)
    cuts = [0, 1, 997, 5000, 5001, 20_000, len(raw)]
    parts = [raw[a:b] for a, b in pairwise(cuts)]
    split = dd.data_from_batches(lambda: iter(parts))
    assert split.s0 == whole.s0 and len(split) == len(whole) > 50
    for name in ("t_us", "n"):
        np.testing.assert_array_equal(getattr(split.windows, name), getattr(whole.windows, name))
    for name in ("v", "aux", "var"):
        np.testing.assert_allclose(getattr(split.windows, name), getattr(whole.windows, name),
                                   rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(split.cov.t_h, whole.cov.t_h)


def test_the_rate_comes_from_a_median_of_counted_time_steps() -> None:
    """The sample rate's median time step, from counts of each step (memory by distinct steps,
    not by samples), is np.median of the steps, odd and even counts alike."""
    import collections

    rng = np.random.default_rng(0)
    for n in range(1, 60):
        steps = rng.integers(9_990, 10_010, n)
        counts = collections.Counter(steps.tolist())
        assert dd._median_of_counts(counts) == float(np.median(steps))


def test_the_detector_scale_is_the_median_norm_from_counts_per_bin() -> None:
    """s0 for the detector comes from counts of each norm's bin (memory by bins, not by
    samples): within 1.2e-4 of np.median of the norms, in any unit, and the same whatever the
    batches; non-finite samples (a library caller's batch) are left out instead of making it
    NaN."""
    import collections

    rng = np.random.default_rng(2)
    for scale in (1.0, 9.81, 1024.0, 3.3e-3):
        v = rng.normal(0, 0.01, (rng.integers(1, 20_000), 3)) + np.array([0.3, -0.2, 0.93])
        v[rng.random(len(v)) < 0.2] *= rng.uniform(0.1, 3.0)  # movement: norms far from 1
        v *= scale
        counts = collections.Counter()
        for part in np.array_split(v, 7):
            dd._count(counts, dd._norm_bins(part))
        lo, hi = dd._median_keys(counts)
        s0 = (dd._bin_middle(lo) + dd._bin_middle(hi)) / 2
        exact = float(np.median(np.linalg.norm(v, axis=1)))
        assert abs(s0 / exact - 1) <= 1.23e-4
        assert len(counts) < 20_000 / 4 or len(v) < 5000  # bins, not samples
    raw = sim.simulate(0.3, RATE_HZ, 3, _sensor(), WEARER).raw
    v = raw.v.copy()
    v[100:103] = np.nan
    v[500, 1] = np.inf
    gappy = dd.data_from_batch(RawBatch(raw.t_us, v, raw.aux, raw.aux_names))
    whole = dd.data_from_batch(raw)
    assert np.isfinite(gappy.s0) and abs(len(gappy) - len(whole)) <= 2 and len(whole) > 50


def test_what_a_user_can_act_on_is_raised_as_a_recal_error() -> None:
    """Bad settings, a bad model spec, data without enough to discover on and a channel the
    model needs but the data lacks: each a recal.errors subclass the command line reports."""
    with pytest.raises(ConfigError, match="at least 3 blocks"):
        dc.DiscoveryConfig(blocks=2)
    with pytest.raises(ConfigError, match="unknown effect kind 'wobble'"):
        make_effect("wobble")
    with pytest.raises(InputError, match="2 windows are too few"):
        dc.discover(dd.data_from_table(np.array([[1.0, 0, 0], [0, 1.0, 0]])))
    t = np.arange(5, dtype=np.int64) * 20_000
    zeros = RawBatch(t, np.zeros((5, 3)), np.zeros((5, 0)), ())
    with pytest.raises(InputError, match="no sample has a finite, nonzero reading"):
        dd.rate_and_scale([zeros])
    frozen = RawBatch(np.full(5, 7, np.int64), np.ones((5, 3)), np.zeros((5, 0)), ())
    with pytest.raises(InputError, match="time stamps never advance"):
        dd.rate_and_scale([frozen])
    with pytest.raises(ModelError, match="model needs channel 'vbat'"):
        Covariates(np.zeros(2), np.zeros((2, 0)), ()).get("vbat")
