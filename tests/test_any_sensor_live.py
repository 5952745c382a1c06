"""An analog accelerometer on a 12-bit ADC, as people wire one to a gateway, through a real
pseudo-terminal into `python -m recal run`: unsigned counts, zero-g near mid-scale, about 370
counts per g, no prior, and a device that printed its header and its first lines before the
daemon opened the port. Accuracy is the 1 s vector RMS of |calibrated - true| after 30 min
against the simulator's truth (4 mg noise at 50 Hz: a floor of about 1 mg). Every wait is
bounded in count and time."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np

from gateway_process import GatewayProcess
from polling import wait_for
from recal.core.status import Status
from recal.io import recording as rec
from recal.samples import RawBatch
from recal.sim import wearer as sim
from recal.sim.pty_device import PtyDevice

SID = "analog"
RATE_HZ = 50.0
MINUTES = 40.0
SCORED_FROM_S = 30 * 60
LIMIT_MG = 1.5
BEFORE_OPEN = 300  # lines the device writes before the port is opened (the pty holds ~13 kB)
WEARER = sim.WearerSpec(still_s=(8.0, 40.0), move_s=(2.0, 8.0), p_upright=0.2, p_lying=0.3,
                        p_any=0.5, always_aux=True)


def _config(tmp: Path) -> Path:
    """Zenoh off, no sensors and no prior in the file: everything from the command line."""
    path = tmp / "gateway.toml"
    path.write_text(f"""[zenoh]
enabled = false

[mcap]
flush_interval_s = 0.1

[checkpoint]
dir = "{tmp / 'state'}"
interval_s = 1.0
""")
    return path


def _stream(dev: PtyDevice, batch: RawBatch, chunk: int, deadline_s: float) -> int:
    """Write ``batch`` as fast as the daemon reads it (the device's own time stamps carry the
    rate); returns the samples written before the deadline."""
    sent = 0
    while sent < len(batch) and time.monotonic() < deadline_s:
        part = batch[sent:sent + chunk]
        dev.write_batch(part)
        assert dev.bytes_dropped == 0, "the daemon stopped reading"
        sent += len(part)
    return sent


def test_analog_unsigned_sensor_without_prior_through_a_pty_into_recal_run(
        tmp_path: Path, children: list) -> None:
    spec = sim.sensor_type("adxl335-adc12", np.random.default_rng(7), offset_mg=40.0,
                           gain_pct=3.0)
    s = sim.simulate(MINUTES / 60.0, RATE_HZ, 7, spec, WEARER)
    raw = s.raw
    assert raw.v.min() >= 0 and abs(np.median(raw.v) - 2048) < 400  # unsigned, mid-scale
    assert raw.aux_names  # the header names channels
    link = str(tmp_path / "ttyADC")
    with PtyDevice(link, "ascii", header=True, header_prefix="", write_timeout_s=10.0) as dev:
        dev.write_batch(raw[:BEFORE_OPEN])  # header + lines, nobody reading yet
        assert dev.bytes_dropped == 0
        gp = GatewayProcess(_config(tmp_path), tmp_path / "run.mcap",
                            ["--port", link, "--sensor-id", SID, "--rate", str(RATE_HZ)])
        children.append(gp)
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        sent = BEFORE_OPEN + _stream(dev, raw[BEFORE_OPEN:], 250, time.monotonic() + 240)
        assert sent == len(raw)
        time.sleep(1.0)
        gp.proc.send_signal(signal.SIGTERM)
        assert gp.proc.wait(60) == 0, gp.lines
    assert not any("Traceback" in ln for ln in gp.lines), gp.lines
    got = rec.read_all_raw(gp.mcap, SID)
    assert got.aux_names == raw.aux_names  # the header's names, not aux0, aux1
    np.testing.assert_array_equal(got.t_us, raw.t_us)  # every sample, once, in order
    np.testing.assert_array_equal(got.v, raw.v)
    cal = rec.read_all_calibrated(gp.mcap, SID)
    np.testing.assert_array_equal(cal.t_us, raw.t_us)
    assert np.isfinite(cal.a_g).all()
    # no prior: the output says it is not calibrated until the bootstrap (held after it while
    # a gain is not yet observed), and is after that
    first = int(np.argmax(cal.status == Status.CALIBRATED))
    assert first > 0 and np.isin(cal.status[:first], [Status.UNCALIBRATED,
                                                      Status.BOOTSTRAPPING, Status.HELD]).all()
    assert np.all(cal.status[first:] == Status.CALIBRATED)
    k = int(SCORED_FROM_S * RATE_HZ)
    err = sim.error_1s_mg(cal.a_g[k:], s.truth.a_true_g[k:], RATE_HZ)
    print(f"\nanalog 12-bit, no prior, through recal run: {err:.2f} mg after 30 min")
    assert err <= LIMIT_MG, err
