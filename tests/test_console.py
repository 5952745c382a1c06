"""Console floods: a device whose clock steps back on every sample gives one event per step in
the recording but a bounded number of console lines, with a count of those left out (a real
`python -m recal run` on a pty, its MCAP read back); the limiter and the logging filter on
their own, with a clock of the test's."""

from __future__ import annotations

import io
import logging
import os
import signal
from pathlib import Path

import numpy as np

from gateway_process import GatewayProcess
from polling import wait_for
from recal.console import BURST, LineLimiter, RateLimitFilter, install_logging
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from test_serial_first_contact import config, device_samples, events, run_args

STEPS_BACK = 400


def test_a_clock_stepping_back_every_sample_floods_no_console(tmp_path: Path,
                                                              children: list) -> None:
    link = str(tmp_path / "tty0")
    good = device_samples(200, 100.0, t0_us=30_000_000)  # 30 s after boot
    back = device_samples(STEPS_BACK, 100.0, seed=6)
    # every sample 10 ms before the one before it, under a minute: a "reboot" at each one
    t = good.t_us[-1] - 10_000 * (1 + np.arange(STEPS_BACK, dtype=np.int64))
    back = RawBatch(t, back.v, back.aux, back.aux_names)
    with PtyDevice(link, header=True) as dev:
        gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap", run_args(link))
        children.append(gp)
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        dev.write_batch(good)
        dev.write_batch(back)
        assert dev.join(20.0)
        mcap = tmp_path / "run.mcap"
        assert wait_for(lambda: sum("device time restarted" in ln for ln in gp.lines) >= BURST,
                        20), gp.lines
        gp.proc.send_signal(signal.SIGTERM)
        assert gp.proc.wait(30) == 0, gp.lines
    reboots = [e for e in events(mcap) if e["kind"] == "time_reboot"]
    said = [ln for ln in gp.lines if "device time restarted" in ln]
    summed = [ln for ln in gp.lines if "similar lines left out" in ln]
    print(f"\n{len(reboots)} reboot events, {len(said)} console lines, summary: {summed}")
    assert len(reboots) >= STEPS_BACK // 2  # the recording keeps every one
    assert len(said) <= BURST + len(summed)
    assert len(summed) == 1 and "device time restarted" in summed[0]
    left_out = int(summed[0].split("recal: ")[1].split()[0])
    assert left_out == len(reboots) - BURST


def test_line_limiter_bursts_then_sums_up_per_interval() -> None:
    now = [0.0]
    lines: list[str] = []
    limit = LineLimiter(lines.append, burst=3, interval_s=10.0, clock=lambda: now[0])
    for i in range(100):
        limit(f"x: device time restarted ({i} -> {i - 1} ms)")
        limit("other line") if i == 50 else None
    assert len(lines) == 4 and lines[-1] == "other line"
    now[0] = 10.5
    limit("x: device time restarted (7 -> 6 ms)")
    assert lines[4].startswith("recal: 97 similar lines left out in 10 s, the last: x: device "
                               "time restarted (99 -> 98 ms)"), lines
    assert lines[5] == "x: device time restarted (7 -> 6 ms)"
    limit.flush()
    assert len(lines) == 6  # nothing left out since


def test_the_logging_filter_limits_by_logger_and_template() -> None:
    now = [0.0]
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.addFilter(RateLimitFilter(burst=2, interval_s=5.0, clock=lambda: now[0]))
    log = logging.getLogger("recal.test_console")
    log.addHandler(handler)
    log.propagate = False
    try:
        for i in range(50):
            log.warning("node %s failed on batch %d", "s1", i)
        now[0] = 6.0
        log.warning("node %s failed on batch %d", "s1", 99)
    finally:
        log.removeHandler(handler)
        log.propagate = True
    out = stream.getvalue().splitlines()
    assert out[:2] == ["node s1 failed on batch 0", "node s1 failed on batch 1"]
    assert out[2].startswith("recal: 48 similar lines left out in 6 s, the last: node s1 "
                             "failed on batch 49"), out
    assert out[3] == "node s1 failed on batch 99" and len(out) == 4
    handler = install_logging()
    try:
        assert install_logging() is handler  # once per process
    finally:
        logging.getLogger().removeHandler(handler)
