"""Any accelerometer as it is plugged in: analog parts on unsigned ADCs, digital parts of
several ranges, phones in m/s^2; with no prior (zero-g and scale found from the data) and with
the shipped priors (gates relative to them). Accuracy is the 1 s vector RMS of
|calibrated - true| after the first 30 min against the simulator's truth (noise 4 mg at 50 Hz:
a floor of about 1 mg)."""

from __future__ import annotations

import json
import tomllib
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from recal import cli
from recal.config import model_and_prior, parse_config
from recal.core import static
from recal.core.bootstrap import locate
from recal.core.estimator import Prior
from recal.core.model import SensorModel
from recal.core.pipeline import Pipeline, from_state_dict
from recal.core.pipeline_config import PipelineConfig
from recal.io import recording as rec
from recal.io.recording_writer import RecordingWriter
from recal.samples import RawBatch
from recal.sim import wearer as sim

RATE = 50.0
SID = "s1"
SCORED_FROM_S = 30 * 60
LIMIT_MG = 1.5
GAIN_TOL_PCT = 0.2
WEARER = sim.WearerSpec(still_s=(8.0, 40.0), move_s=(2.0, 8.0), p_upright=0.2, p_lying=0.3,
                        p_any=0.5)
PRIORS_FILE = Path(__file__).resolve().parents[1] / "configs" / "sensor-priors.toml"


def _sim(kind: str, seed: int, minutes: float = 40.0, wearer: sim.WearerSpec = WEARER,
         **sensor: Any) -> sim.SimResult:
    spec = sim.sensor_type(kind, np.random.default_rng(seed), offset_mg=40.0, gain_pct=3.0,
                           **sensor)
    return sim.simulate(minutes / 60.0, RATE, seed, spec, wearer)


def _write_mcap(path: Path, raw: RawBatch) -> Path:
    with RecordingWriter(path, background_flush=False, fsync=False) as w:
        for i in range(0, len(raw), 250):
            w.write_raw(SID, raw[i:i + 250], 1_000_000_000 + int(raw.t_us[i]) * 1000)
    return path


def _error_mg(a_g: np.ndarray, s: sim.SimResult) -> float:
    k = int(SCORED_FROM_S * RATE)
    assert np.all(np.isfinite(a_g))
    return sim.error_1s_mg(a_g[k:], s.truth.a_true_g[k:], RATE)


def _true_rel_gain_pct(s: sim.SimResult) -> np.ndarray:
    """The simulated gains against their mean: what a fit with no prior can know."""
    g = 1.0 + np.asarray(s.truth.sensor.gain)
    return 100.0 * (g / g.mean() - 1.0)


def _gains_pct(described: dict) -> np.ndarray:
    return np.array([described["scale"][f"gain_{a}_pct"] for a in "xyz"])


def _scales(described: dict) -> np.ndarray:
    return np.array([described["scale"][f"s_{a}"] for a in "xyz"])


def _replay(tmp: Path, mcap: Path, name: str, *extra: str) -> tuple[dict, np.ndarray]:
    out, js = tmp / f"{name}.mcap", tmp / f"{name}.json"
    assert cli.main(["replay", str(mcap), "--out", str(out), "--quiet", "--json", str(js),
                     *extra]) == 0
    return (json.loads(js.read_text())["sensors"][SID],
            rec.read_all_calibrated(out, SID).a_g)


def _hindsight(tmp: Path, mcap: Path) -> tuple[dict, np.ndarray]:
    out, js = tmp / "hindsight.mcap", tmp / "hindsight.json"
    assert cli.main(["hindsight", str(mcap), "--out", str(out), "--quiet",
                     "--json", str(js)]) == 0
    return json.loads(js.read_text()), rec.read_all_calibrated(out, SID).a_g


def _discover(tmp: Path, mcap: Path) -> tuple[dict, Path]:
    js, model = tmp / "discover.json", tmp / "model.json"
    assert cli.main(["discover", str(mcap), "--json", str(js), "--write-model",
                     str(model)]) == 0
    return json.loads(js.read_text()), model


def test_analog_unsigned_sensor_without_prior_through_replay_hindsight_discover(
        tmp_path: Path, capsys: Any) -> None:
    s = _sim("adxl335-adc12", seed=3)
    assert s.raw.v.min() >= 0 and abs(np.median(s.raw.v) - 2048) < 400  # unsigned, mid-scale
    mcap = _write_mcap(tmp_path / "raw.mcap", s.raw)
    info, a = _replay(tmp_path, mcap, "replay")
    assert info["bootstrapped"] and info["counts"]["updates_rejected"] == 0
    assert _error_mg(a, s) <= LIMIT_MG
    truth = _true_rel_gain_pct(s)
    np.testing.assert_allclose(_gains_pct(info["described"]), truth, atol=GAIN_TOL_PCT)
    hs, a_h = _hindsight(tmp_path, mcap)
    assert _error_mg(a_h, s) <= LIMIT_MG and hs["residual_rms_mg"] < 1.0
    assert hs["gain_reference"]["source"] == "fit"
    np.testing.assert_allclose(_gains_pct(hs["described"]), truth, atol=GAIN_TOL_PCT)
    disc, _ = _discover(tmp_path, mcap)
    assert disc["effects_selected"] == []  # an ideal analog part: nothing to add
    assert disc["input"]["zero_g"] == pytest.approx([2048.0] * 3, abs=0.1 * 372)
    assert "not calibrated" not in capsys.readouterr().out


def test_ratiometric_unsigned_sensor_with_sagging_supply(tmp_path: Path) -> None:
    """The whole output of a ratiometric part (zero-g too) follows the supply while the ADC's
    reference stays: discovery finds it, and the model it writes replays to the floor."""
    wearer = sim.WearerSpec(**{**WEARER.to_dict(), "vdd_start_v": 3.3, "vdd_end_v": 2.9})
    s = _sim("adxl335-adc12", seed=2, wearer=wearer, ratiometric_per_v=1 / 3.3, v_ref_v=3.3)
    mcap = _write_mcap(tmp_path / "raw.mcap", s.raw)
    disc, model = _discover(tmp_path, mcap)
    assert [e["label"] for e in disc["effects_selected"]] == ["ratiometric[vdd_v]"]
    info, a = _replay(tmp_path, mcap, "replay-model", "--model", str(model))
    assert info["counts"]["updates_rejected"] == 0
    assert _error_mg(a, s) <= LIMIT_MG


@pytest.mark.parametrize(("kind", "seed"), [("digital-2g", 3), ("digital-16g", 4),
                                            ("phone-ms2", 5)])
def test_digital_and_phone_sensors_without_prior_agree_across_tools(
        tmp_path: Path, kind: str, seed: int) -> None:
    s = _sim(kind, seed)
    mcap = _write_mcap(tmp_path / "raw.mcap", s.raw)
    info, a = _replay(tmp_path, mcap, "replay")
    hs, a_h = _hindsight(tmp_path, mcap)
    disc, _ = _discover(tmp_path, mcap)
    assert _error_mg(a, s) <= LIMIT_MG and _error_mg(a_h, s) <= LIMIT_MG
    truth = _true_rel_gain_pct(s)
    true_s = s.truth.sensor.counts_per_g * (1.0 + np.asarray(s.truth.sensor.gain))
    for described in (info["described"], hs["described"], disc["model"]["described"]):
        np.testing.assert_allclose(_gains_pct(described), truth, atol=GAIN_TOL_PCT)
        np.testing.assert_allclose(_scales(described), true_s, rtol=GAIN_TOL_PCT / 100)
    # one reference (the mean fitted scale) for all three
    ref_h, ref_d = hs["gain_reference"], disc["model"]["gain_reference"]
    assert ref_h["source"] == ref_d["source"] == "fit"
    assert ref_h["counts_per_g"] == pytest.approx(ref_d["counts_per_g"], rel=1e-6)


#: The sensor each shipped prior is for (`sim.SENSOR_TYPES`).
PRIOR_SENSORS = {"adxl345-10bit-4mg": "adxl345-10bit", "lis3dh-2g-hr": "digital-2g",
                 "mma7260-adc14": "mma7260-adc14", "sim-1024": "default",
                 "adxl335-adc12": "adxl335-adc12", "phone-ms2": "phone-ms2"}


def test_every_shipped_prior_has_a_simulated_sensor() -> None:
    names = set(tomllib.loads(PRIORS_FILE.read_text())["priors"])
    assert names == set(PRIOR_SENSORS)


@pytest.mark.parametrize("name", sorted(PRIOR_SENSORS))
def test_shipped_prior_calibrates_a_sensor_of_its_type(name: str) -> None:
    cfg = parse_config({"priors_file": str(PRIORS_FILE),
                        "sensors": [{"id": SID, "prior": name}]}, PRIORS_FILE.parent, "test")
    model, prior = model_and_prior(cfg.sensors[0], cfg.pipeline)
    assert prior is not None
    s = _sim(PRIOR_SENSORS[name], seed=7)
    pipe = Pipeline(PipelineConfig(rate_hz=RATE), model, prior, s.raw.aux_names)
    a = np.concatenate([pipe.step(s.raw[i:i + 500]).calibrated.a_g
                        for i in range(0, len(s.raw), 500)])
    summ = pipe.summary()
    assert summ["phase"] == "prior" and summ["gain_reference"]["source"] == "prior"
    assert summ["counts"]["updates"] > 10 and summ["counts"]["updates_rejected"] == 0
    assert _error_mg(a, s) <= LIMIT_MG


def test_a_prior_whose_zero_g_is_wrong_calibrates_nothing_and_counts_it() -> None:
    """An unsigned part given a prior at zero-g 0 (its readings ~9.5 g long): every window
    fails the norm gate around that prior, none reaches the estimator, the counts say so and
    the output is held (the prior, nothing informed) until the first such window, which
    contradicts it grossly: suspect from there. After 3 minutes of that the self-watch
    (core/status.py) resets: the prior does not fit those windows either, so the pipeline
    bootstraps from them (suspect, then the bootstrap's own phase)."""
    from recal.core.status import SUSPECT_AFTER_S, Status

    s = _sim("adxl335-adc12", seed=3, minutes=10.0)
    model = SensorModel.diagonal(372.0)
    pipe = Pipeline(PipelineConfig(rate_hz=RATE), model, Prior.default(model), ())
    outs = []
    for i in range(0, len(s.raw), 1000):
        outs.append(pipe.step(s.raw[i:i + 1000]))
        if s.raw.t_us[min(i + 999, len(s.raw) - 1)] - s.raw.t_us[0] < SUSPECT_AFTER_S * 1e6:
            c = pipe.counts  # until the self-watch may fire
            assert c["windows"] == 0 and c["updates"] == 0
            assert pipe.summary()["phase"] == "prior"
            assert pipe.status == (Status.SUSPECT if c["windows_rejected"] else Status.HELD)
    assert pipe.counts["windows_rejected"] > 50
    watch = [w for o in outs for w in o.watch]
    assert [w.kind for w in watch] == ["suspect", "suspect"]
    assert [w.detail["reason"] for w in watch] == [
        "a still window contradicts the estimate grossly",
        "still windows fail the norm gate under the estimate"]
    assert pipe.summary()["phase"] == "bootstrap" and pipe.status == Status.SUSPECT


def _run(pipe: Pipeline, raw: RawBatch, size: int) -> tuple[np.ndarray, list]:
    outs, ups, n = [], [], 0
    for i in range(0, len(raw), size):
        o = pipe.step(raw[i:i + size])
        outs.append(o.calibrated.a_g)
        ups += [(u.index + n, u.bootstrap, u.report.accepted) for u in o.updates]
        n += len(o.calibrated.a_g)
    return np.concatenate(outs), ups


def test_unsigned_start_is_the_same_for_any_batching_and_after_a_checkpoint() -> None:
    """Zero-g found inside a batch restarts the detector after that sample, as if the batch
    had ended there: batches of 1000 and of 37 samples give the same output, and a checkpoint
    taken between the re-centring and the bootstrap continues bit for bit."""
    s = _sim("adxl335-adc12", seed=3, minutes=12.0)
    new = lambda: Pipeline(PipelineConfig(rate_hz=RATE), SensorModel.diagonal(), None, ())  # noqa: E731
    a1, u1 = _run(new(), s.raw, 1000)
    a2, u2 = _run(new(), s.raw, 37)
    np.testing.assert_array_equal(a1, a2)
    assert u1 == u2 and any(b for _, b, _ in u1)
    pipe = new()
    i = 0
    while not pipe.centre0.any():  # bounded: the recording's length
        assert i < len(s.raw)
        pipe.step(s.raw[i:i + 37])
        i += 37
    assert not pipe.bootstrapped and pipe.phase == "provisional"
    assert abs(pipe.model.s0 / 372.0 - 1) < 0.1
    resumed = from_state_dict(json.loads(json.dumps(pipe.state_dict())))
    rest = s.raw[i:]
    b1, v1 = _run(pipe, rest, 500)
    b2, v2 = _run(resumed, rest, 500)
    np.testing.assert_array_equal(b1, b2)
    assert v1 == v2 and pipe.phase == resumed.phase == "bootstrap"


def test_unsigned_start_reports_each_message_state_when_messages_are_joined() -> None:
    """`step_many` across the re-centring (which redoes part of the batch): the states at the
    batches' ends are those stepping each message alone shows, and so is the output."""
    s = _sim("adxl335-adc12", seed=3, minutes=12.0)
    rng = np.random.default_rng(5)
    cuts = np.cumsum(rng.integers(1, 700, size=len(s.raw)))
    cuts = [0, *cuts[cuts < len(s.raw)].tolist(), len(s.raw)]
    msgs = [s.raw[a:b] for a, b in pairwise(cuts)]
    new = lambda: Pipeline(PipelineConfig(rate_hz=RATE), SensorModel.diagonal(), None, ())  # noqa: E731
    seq, expected, a_seq = new(), {}, []
    for m, end in zip(msgs, cuts[1:], strict=True):
        out = seq.step(m)
        a_seq.append(out.calibrated.a_g)
        if out.updates:
            expected[end] = json.dumps(seq.summary(), sort_keys=True, default=str)
    joined, got, a_joined = new(), {}, []
    for lo in range(0, len(msgs), 7):  # 7 messages per step
        outs = joined.step_many(msgs[lo:lo + 7])
        a_joined += [out.calibrated.a_g for out in outs]
        got |= {end: json.dumps(out.state[1], sort_keys=True, default=str)
                for out, end in zip(outs, cuts[lo + 1:lo + 8], strict=True)
                if out.state is not None}
    np.testing.assert_array_equal(np.concatenate(a_seq), np.concatenate(a_joined))
    assert len(expected) >= 10 and got == expected
    assert seq.phase == joined.phase == "bootstrap"


def test_locate_finds_zero_g_and_scale_from_window_means_only_when_covered() -> None:
    rng = np.random.default_rng(1)
    u = rng.normal(size=(60, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    centre, scale = np.array([2050.0, 2040.0, 2061.0]), 372.0
    v = centre + scale * u + rng.normal(0, 1.5, (60, 3))
    v[:6] += 0.3 * scale * u[:6]  # movement: means beyond 1 g
    loc = locate(v)
    assert loc is not None and loc.covers(cells=8)
    np.testing.assert_allclose(loc.centre, centre, atol=2.0)
    assert loc.scale == pytest.approx(scale, rel=0.005)
    assert not loc.inliers[:6].any() and loc.inliers[6:].all()
    one_pose = centre + scale * u[0] + rng.normal(0, 1.5, (40, 3))
    got = locate(one_pose)
    assert got is None or not got.covers()


def test_static_tables_of_an_unsigned_adc() -> None:
    """`recal static` on a 12-bit analog part's table (zero-g ~2048): both fits find it, and
    gains are named against the fitted scale, not the rows' median norm (~9 g)."""
    rng = np.random.default_rng(4)
    dirs = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)
                     if (x, y, z) != (0, 0, 0)], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    gains = np.array([1.02, 0.985, 1.0])
    zero = np.array([2051.0, 2040.0, 2060.0])
    v = np.round(zero + 372.0 * gains * dirs + rng.normal(0, 0.3, dirs.shape))
    rows = np.ones(len(v), bool)
    fit = static.fit_unknown_orientations(v, rows, full=False, loss="l2")
    assert fit.rel_norm_error.max() < 0.003
    assert fit.params["gain_reference"]["counts_per_g"] == pytest.approx(372.0 * gains.mean(),
                                                                          rel=0.002)
    got = [fit.params["described"]["scale"][f"gain_{a}_pct"] for a in "xyz"]
    np.testing.assert_allclose(got, 100 * (gains / gains.mean() - 1), atol=0.1)
    faces = np.flatnonzero(np.abs(dirs).max(axis=1) == 1.0)  # the six face positions
    known = np.zeros(len(v), bool)
    known[faces] = True
    fk = static.fit_known_orientations(v, known)
    np.testing.assert_allclose(fk.params["O"], zero, atol=1.5)
    assert fk.rel_norm_error[known].max() < 0.003


def test_cli_simulate_writes_a_sensor_type(tmp_path: Path, capsys: Any) -> None:
    out = tmp_path / "a.mcap"
    assert cli.main(["simulate", "--out", str(out), "--hours", "0.02", "--rate", "25",
                     "--sensor-type", "adxl335-adc12"]) == 0
    v = rec.read_all_raw(out, "sim0").v
    assert v.min() >= 0 and v.max() <= 4095 and np.all(v == np.round(v))
    assert abs(float(np.median(v)) - 2048) < 400
    assert cli.main(["simulate", "--out", str(tmp_path / "b.mcap"), "--hours", "0.02",
                     "--sensor-type", "no-such-part"]) == 2
    assert "--sensor-type must be one of" in capsys.readouterr().err
