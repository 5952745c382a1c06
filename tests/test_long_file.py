"""Long files: the calibration alone (`recal hindsight --json` without --out), discovery's
selection on a bounded number of windows, and a device file's batches made without a search
per sample (block times) or per channel (low-rate channels)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from device_writers import DeviceRun, device_signal, write_cwa
from recal.cli import main
from recal.core import discovery as dc
from recal.core import discovery_data as dd
from recal.core.buffer import Windows
from recal.io.device_files import open_device
from recal.samples import RawBatch


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory):
    """An AX3 file of 18 min at 50 Hz with a gap and a stretch on a table."""
    run = DeviceRun(hours=0.3, nominal_hz=50, real_hz=50.15, gap_s=(300.0, 40.0),
                    table_s=(500.0, 120.0))
    return write_cwa(tmp_path_factory.mktemp("cwa") / "gap.cwa", device_signal(run))


@pytest.fixture
def cwa(tmp_path: Path, written) -> Path:
    path = tmp_path / "wrist.cwa"
    shutil.copyfile(written.path, path)
    return path


def test_hindsight_with_json_alone_writes_the_calibration_and_no_samples(
        tmp_path: Path, cwa: Path, written, capsys: pytest.CaptureFixture[str]) -> None:
    n = len(written.signal)
    alone, full = tmp_path / "alone.json", tmp_path / "full.json"
    assert main(["hindsight", str(cwa), "--json", str(alone), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert said.startswith(f"fitted {n} samples") and "no samples written" in said
    assert sorted(p.name for p in tmp_path.iterdir()) == ["alone.json", "wrist.cwa"]
    assert main(["hindsight", str(cwa), "--json", str(full), "--out",
                 str(tmp_path / "out.csv"), "--quiet"]) == 0
    a, f = json.loads(alone.read_text()), json.loads(full.read_text())
    assert a["out"] is None and f["out"] == str(tmp_path / "out.csv")
    assert a["samples"] == f["samples"] == n
    assert a["params"] == f["params"] and a["windows"] == f["windows"]  # the same fit
    assert a["samples_suspect"] is None and f["samples_suspect"] is not None


def test_hindsight_without_out_or_json_is_one_line(tmp_path: Path, cwa: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hindsight", str(cwa), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out" in err and "--json" in err


def _windows(m: int) -> tuple[Windows, np.ndarray]:
    rng = np.random.default_rng(3)
    u = rng.normal(size=(m, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    t_us = np.arange(m, dtype=np.int64) * 7_000_000
    return Windows(u + rng.normal(0, 3e-4, (m, 3)), np.zeros((m, 0)), t_us,
                   np.full(m, 200, np.int64), np.full(m, 1e-4)), t_us


@pytest.mark.parametrize(("m", "most"), [(100, 4096), (4096, 4096), (4097, 4096),
                                         (10_000, 1000), (999, 10)])
def test_thinned_keeps_every_kth_window_in_time_and_no_more_than_asked(m: int,
                                                                       most: int) -> None:
    w, _ = _windows(m)
    data = dd.data_from_windows(w, (), 0)
    thin = dd.thinned(data, most)
    step = -(-len(data) // most)
    assert len(thin) <= most and len(thin) == len(range(0, len(data), step))
    assert np.array_equal(thin.windows.t_us, data.windows.t_us[::step])
    assert np.array_equal(thin.cov.t_h, data.cov.t_h[::step])
    assert thin.windows.t_us[-1] >= data.windows.t_us[-1] - step * 7_000_000  # to the end


def test_discovery_selects_on_at_most_max_windows() -> None:
    w, _ = _windows(3000)
    data = dd.data_from_windows(w, (), 0)
    cfg = dc.DiscoveryConfig(max_windows=500, bootstrap=50, kinds=("offset",), time=False)
    result = dc.discover(data, cfg=cfg)
    assert len(result.data) == len(dd.thinned(data, 500)) <= 500
    assert len(dc.discover(data.subset(np.arange(400)), cfg=cfg).data) == 400  # under: all


@pytest.mark.parametrize("size", [1, 77, 120, 4096, 65_536])
def test_device_batches_are_the_same_in_any_size_and_interpolate_as_numpy(written,
                                                                          size: int) -> None:
    """Times: each sample's block found by position, not searched, gives what the search
    gives; low-rate channels (their stamps converted once per file) are np.interp's values,
    to the bit."""
    rec = open_device(written.path)
    whole = next(rec.batches(len(rec)))
    if size < 100:  # the first thousands of samples: enough boundaries, few batches
        parts = [b for _, b in zip(range(4000 // size), rec.batches(size), strict=False)]
        got = RawBatch.concat(parts)
        whole = whole[:len(got)]
    else:
        got = RawBatch.concat(list(rec.batches(size)))
    assert np.array_equal(got.t_us, whole.t_us) and np.array_equal(got.aux, whole.aux)
    blocks = rec._blocks
    j = np.arange(len(whole), dtype=np.int64)
    b = np.searchsorted(blocks.start, j, side="right") - 1
    t_ns = blocks.anchor_ns[b] + np.rint((j - blocks.start[b]) * blocks.period_ns[b]).astype(
        np.int64)
    assert np.array_equal(whole.t_us, (t_ns - rec._shift_ns) // 1000)
    file_t = rec._p.file_t_ns[:len(whole)].astype(np.float64)
    assert rec._p.low_rate
    for k, lr in enumerate(rec._p.low_rate):
        ref = np.interp(file_t, lr.t_ns.astype(np.float64), lr.values)
        assert np.array_equal(got.aux[:, k], ref), lr.name
