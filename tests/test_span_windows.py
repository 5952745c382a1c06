"""A device file's windows on threads (`commands.span_windows`, `core.batch_windows` in spans):
the same windows, bit for bit, as one reading from the start on the same batches, for every
format's quantization, gaps and idle sleep; also where a segment's warm-up falls short and
it must be run again; and `recal hindsight --threads` gives the same calibration."""

from __future__ import annotations

import json
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from device_writers import DeviceRun, device_signal, write_cwa, write_geneactiv_bin, write_gt3x
from recal.cli import main
from recal.commands.span_windows import span_windows
from recal.core import batch_windows as bw
from recal.core import detector as det
from recal.core import low_rate
from recal.core.model import SensorModel
from recal.core.pipeline_config import PipelineConfig
from recal.core.quantization import LATTICE_CHANGES
from recal.io.device_files import DeviceRecording, open_device

BATCH = 1024  # small batches and segments: a short file is many of each
SEGMENT_BATCHES = 6


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """50 min at 50 Hz with a gap and a stretch on a table, as each device writes it (the
    ActiGraph with idle sleep on the table)."""
    run = DeviceRun(hours=50 / 60, nominal_hz=50, real_hz=50.15, gap_s=(300.0, 40.0),
                    table_s=(1500.0, 150.0))
    sig = device_signal(run)
    tmp = tmp_path_factory.mktemp("devices")
    return {"cwa": write_cwa(tmp / "w.cwa", sig).path,
            "bin": write_geneactiv_bin(tmp / "w.bin", sig).path,
            # an ActiGraph samples on its real-time clock: exactly the nominal rate
            "gt3x": write_gt3x(tmp / "w.gt3x", device_signal(replace(run, real_hz=50.0))).path}


def _in_order(rec: DeviceRecording, cfg: PipelineConfig, model: SensorModel, s0: float,
              zero: np.ndarray | None) -> bw.Windowing:
    """The reference: every batch of the grid in turn through one `Windowing`."""
    w = bw.Windowing(cfg, model, s0, zero)
    for b in rec.batches(BATCH):
        w.add(b)
    return w


def _assert_same(got: tuple, want: bw.Windowing) -> None:
    """The same windows: every sum bit for bit, but the low-rate channels', which are made in
    closed form (`core.low_rate`): to the rounding of the reference's times (np.interp of
    nanoseconds since 1970 as floats: 256 ns steps, 1e-9 of a value's change over a block)."""
    sums, aux_names, t0_us, step = got
    kept = want.kept()
    assert len(kept) > 20
    for f in fields(kept):
        if f.name != "sum_aux":
            np.testing.assert_array_equal(getattr(sums, f.name), getattr(kept, f.name), f.name)
    np.testing.assert_allclose(sums.sum_aux, kept.sum_aux, rtol=1e-8, atol=1e-9)
    assert aux_names == want.aux_names and t0_us == want.t0_us
    np.testing.assert_array_equal(step, want.step_raw)


@pytest.mark.parametrize("kind", ["cwa", "bin", "gt3x"])
def test_windows_on_threads_are_those_of_one_reading(files: dict[str, Path], kind: str) -> None:
    rec = open_device(files[kind])
    cfg = PipelineConfig(rate_hz=rec.rate_hz)
    model = SensorModel.diagonal(1.0)
    told: list[int] = []
    find = span_windows(rec, 2, told.append, batch=BATCH, segment_batches=SEGMENT_BATCHES)
    _assert_same(find(cfg, model, 1.0, None), _in_order(rec, cfg, model, 1.0, None))
    assert sum(told) == len(rec)  # the progress: every sample once
    # centred elsewhere (an analog part's second pass) and a model with a channel (its
    # samples must have it finite to count)
    zero = np.array([0.01, -0.02, 0.005])
    temp = SensorModel.from_dict({"s0": 1.0, "effects": [
        {"kind": "offset"}, {"kind": "scale"},
        {"kind": "offset", "covariate": rec.aux_names[0], "ref": 0.0}]})
    _assert_same(find(cfg, temp, 1.02, zero), _in_order(rec, cfg, temp, 1.02, zero))


def test_a_warm_up_that_falls_short_is_run_again(files: dict[str, Path],
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    rec = open_device(files["cwa"])
    cfg = PipelineConfig(rate_hz=rec.rate_hz)
    model = SensorModel.diagonal(1.0)
    again: list[int] = []
    add = bw.Settler.add

    def counted(self, segment, run_again):
        def counting(s, state):
            again.append(s.lo)
            return run_again(s, state)
        return add(self, segment, counting)

    monkeypatch.setattr(bw.Settler, "add", counted)
    monkeypatch.setattr(bw, "WARM_S", 0.5)  # a second: the filters cannot have forgotten
    find = span_windows(rec, 2, batch=BATCH, segment_batches=SEGMENT_BATCHES)
    _assert_same(find(cfg, model, 1.0, None), _in_order(rec, cfg, model, 1.0, None))
    segments = -(-len(rec) // (BATCH * SEGMENT_BATCHES))
    assert len(again) == segments - 1  # each segment after the first, from the right state


def test_same_future_compares_what_the_detector_uses() -> None:
    cfg = PipelineConfig(rate_hz=50.0).detector(1.0, None)
    a = replace(det.init_state(cfg), started=True, zi_hp=np.ones((1, 2)),
                last_v=np.array([0.0, 0.0, 1.0]), step_raw=np.full(3, 1 / 256),
                changes=LATTICE_CHANGES)
    assert bw.same_future(cfg, a, replace(a, step_raw=np.full(3, 1 / 255)))  # both coarse
    assert not bw.same_future(cfg, a, replace(a, step_raw=np.full(3, 1e-6)))  # one fine
    assert not bw.same_future(cfg, a, replace(a, changes=10))  # one still learning
    assert not bw.same_future(cfg, a, replace(a, same_run=3))
    assert not bw.same_future(cfg, a, replace(a, zi_hp=np.nextafter(a.zi_hp, 2.0)))
    young = replace(a, changes=10)
    assert bw.same_future(cfg, young, replace(young, zi_lp=young.zi_lp.copy()))
    assert not bw.same_future(cfg, young, replace(young, step_raw=np.full(3, 1 / 255)))


def test_spans_start_where_the_detector_gates_nothing() -> None:
    gate = np.ones(100, bool)
    gate[[5, 23, 24, 61]] = False
    state = det.init_state(PipelineConfig(rate_hz=50.0).detector(1.0, None))

    def span_starts(gate: np.ndarray, every: int) -> list[int]:
        """Where `span_windows` starts its spans: after the first segment, each one's first
        sample the detector does not gate."""
        segments = [bw.Segment(lo, state, gate[lo:lo + every], state)
                    for lo in range(0, len(gate), every)]
        return [0] + [s.first_ungated for s in segments[1:] if s.first_ungated is not None]

    assert span_starts(gate, 20) == [0, 23, 61]  # none in 40..59: no span there
    assert span_starts(np.ones(50, bool), 10) == [0]
    assert bw.Segment(7, state, np.zeros(0, bool), state).first_ungated is None


def test_hindsight_threads_give_the_same_calibration(files: dict[str, Path], tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr("recal.commands.span_windows.SEGMENT_BATCHES", 1)  # 64 Ki samples
    out = {}
    for threads in (1, 2):
        path = tmp_path / f"t{threads}.json"
        assert main(["hindsight", str(files["cwa"]), "--json", str(path), "--quiet",
                     "--threads", str(threads)]) == 0
        out[threads] = json.loads(path.read_text())
    for key in ("params", "sd", "windows", "discovery", "residual_rms_mg", "misfit"):
        assert out[1][key] == out[2][key], key
    capsys.readouterr()
    assert main(["hindsight", str(files["cwa"]), "--json", str(tmp_path / "x.json"),
                 "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err
    assert main(["hindsight", str(tmp_path), "--out", str(tmp_path / "o"),
                 "--threads", "2"]) == 2
    assert "--threads" in capsys.readouterr().err


def test_low_rate_sums_are_the_interpolated_values_summed() -> None:
    """Against sums of the values interpolated sample by sample with exact (integer) time
    differences: windows before the first stamp, across stamps, from the last on, a stamp
    on a sample's time, two stamps with no sample between."""
    rng = np.random.default_rng(3)
    steps = rng.integers(9_000_000, 11_000_000, 5000)
    steps[rng.choice(5000, 60, replace=False)] = -4_000_000  # times that step back
    x = 1_700_000_000_000_000_000 + np.cumsum(steps)
    t = np.sort(rng.choice(np.arange(x[100], x[4800], 7_777), 40, replace=False))
    t[5] = x[1234]  # a stamp on a sample
    t = np.unique(np.append(t, [x[2000] + 1, x[2000] + 2]))  # two with no sample between
    back = np.flatnonzero(np.diff(x) < 0) + 1
    # stamps between a sample and the one that steps back behind it: np.interp puts the
    # latter (and any after it still behind) in the stretch before the stamp
    t = np.unique(np.append(t, (x[back - 1] + x[back]) // 2))
    f = rng.normal(25.0, 3.0, (len(t), 2))
    s = low_rate.Stretches.of(x, t, f, chunk=700)
    j = np.searchsorted(t, x, side="right") - 1  # each sample's stretch, exactly
    inner = (j >= 0) & (j < len(t) - 1)
    per = np.where(j[:, None] < 0, f[0], f[-1]).astype(np.float64)
    ji = j[inner]
    slope = (f[ji + 1] - f[ji]) / (t[ji + 1] - t[ji]).astype(np.float64)[:, None]
    per[inner] = f[ji] + slope * (x[inner] - t[ji]).astype(np.float64)[:, None]
    p0 = np.array([1200, 0, 50, 1990, 3000, 4700, 4990, 3920])  # out of order, one to the end
    n = np.array([300, 40, 120, 30, 900, 290, 10, 60])
    lo = 0
    got = low_rate.window_sums(s, x[lo:], lo, p0, n)
    want = np.array([per[a:a + k].sum(axis=0) for a, k in zip(p0, n, strict=True)])
    np.testing.assert_allclose(got, want, rtol=1e-13)
    # a span of the recording: indices stay the recording's
    got = low_rate.window_sums(s, x[1000:4000], 1000, p0[[0, 3, 4]], n[[0, 3, 4]])
    np.testing.assert_allclose(got, want[[0, 3, 4]], rtol=1e-13)
    # by blocks within which the times rise (where they step back, and elsewhere too): the same
    rises = np.unique(np.concatenate(([0], np.flatnonzero(np.diff(x) <= 0) + 1,
                                      rng.choice(5000, 30, replace=False))))
    by_blocks = low_rate.Stretches.of(x, t, f, rises=rises)
    np.testing.assert_array_equal(by_blocks.first, s.first)
    np.testing.assert_array_equal(by_blocks.behind, s.behind)
    assert len(s.behind) > 20  # the stepping back was exercised, across stamps too
    assert np.any(np.searchsorted(s.first, s.behind, side="right")
                  != np.searchsorted(t, x[s.behind], side="right"))
    assert low_rate.applies(t, f)
    assert not low_rate.applies(t[::-1], f)
    assert not low_rate.applies(t, np.where(f > 30, np.nan, f))
