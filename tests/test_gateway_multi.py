"""Several sensors on one gateway: one ASCII and one COBS device, each on its own real pty.

Each sensor's samples must land in the MCAP exactly once under its own id, and each sensor's
calibration must be exactly what the core pipeline computes on that sensor's samples alone.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from polling import wait_for
from recal.config import model_and_prior
from recal.core.pipeline import Pipeline
from recal.daemon.gateway import Gateway, run_gateway
from recal.io import recording as rec
from recal.samples import CalibratedBatch
from recal.sim.pty_device import PtyDevice
from test_gateway import RATE_HZ, service_config, sim_raw


def test_two_sensors_two_wire_formats_each_exactly_once(tmp_path: Path) -> None:
    raws = {"wrist": sim_raw(2.0, seed=21), "hip": sim_raw(2.0, seed=22)}
    links = {"wrist": str(tmp_path / "ttyA"), "hip": str(tmp_path / "ttyB")}
    fmts = {"wrist": "ascii", "hip": "cobs"}
    sensors = [{"id": sid, "port": links[sid], "format": fmts[sid], "aux_names": [],
                "rate_hz": RATE_HZ, "prior": {"counts_per_g": 1024.0}} for sid in raws]
    cfg = service_config(tmp_path, links["wrist"], None, sensors=sensors)
    mcap = tmp_path / "two.mcap"
    stop = threading.Event()
    ready: list[Gateway] = []
    lines: list[str] = []
    with PtyDevice(links["wrist"], "ascii") as dev_a, PtyDevice(links["hip"], "cobs") as dev_b:
        devs = {"wrist": dev_a, "hip": dev_b}
        th = threading.Thread(target=run_gateway, args=(cfg,), daemon=True, kwargs={
            "mcap_out": mcap, "stop_event": stop, "on_ready": ready.append, "out": lines.append})
        th.start()
        try:
            assert wait_for(lambda: bool(ready), 20), lines
            gw = ready[0]
            assert wait_for(lambda: all(gw.ports[s].is_open for s in raws), 10)
            for sid, dev in devs.items():
                dev.start_streaming(raws[sid], rate_hz=RATE_HZ, speedup=40.0)
            assert all(dev.join(30) for dev in devs.values())

            def logged_all() -> bool:
                return all(gw.status(s)["gateway"]["samples_logged"] == len(raws[s])
                           for s in raws)
            assert wait_for(logged_all, 20, 0.1), {s: gw.status(s)["gateway"] for s in raws}
        finally:
            stop.set()
            th.join(30)
    assert not th.is_alive()

    assert set(rec.sensors(mcap)) == set(raws)
    for sid, raw in raws.items():
        logged = rec.read_all_raw(mcap, sid)
        np.testing.assert_array_equal(logged.t_us, raw.t_us)
        np.testing.assert_array_equal(logged.v, raw.v)
        model, prior = model_and_prior(cfg.sensor(sid), cfg.pipeline)
        pipe = Pipeline(cfg.pipeline.pipeline_config(RATE_HZ), model, prior, ())
        ref = CalibratedBatch.concat([pipe.step(raw[i:i + 1000]).calibrated
                                      for i in range(0, len(raw), 1000)])
        cal = rec.read_all_calibrated(mcap, sid)
        np.testing.assert_array_equal(cal.t_us, ref.t_us)
        assert np.max(np.abs(cal.a_g - ref.a_g)) <= 0.5e-6 + 1e-9  # (logged to the micro-g)
