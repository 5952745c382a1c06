"""First contact with a serial device, its clock, and who owns the port: `python -m recal run`
as a real process on a real pseudo-terminal (recal.sim.pty_device), its MCAP read back with
the mcap reader. Every wait is bounded in count and time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from gateway_process import GatewayProcess
from polling import wait_for
from recal.commands.replay import replay
from recal.core.effects import Ratiometric
from recal.core.model import SensorModel
from recal.io import recording as rec
from recal.io.ascii_lines import encode_ascii
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from recal.sim.wearer import SensorSpec, simulate

SID = "s1"
WRAP = 2**32


def config(tmp: Path) -> Path:
    """Zenoh off, the log flushed every 50 ms, checkpoints every 0.25 s; no sensors (ports
    and priors come from the command line)."""
    path = tmp / "gateway.toml"
    path.write_text(f"""[zenoh]
enabled = false

[mcap]
flush_interval_s = 0.05

[checkpoint]
dir = "{tmp / 'ck'}"
interval_s = 0.25
""")
    return path


def device_samples(n: int, rate_hz: float, t0_us: int = 1_000_000, seed: int = 4,
                   aux: tuple[str, ...] = ()) -> RawBatch:
    """``n`` samples of a simulated wearer in ADC counts (short lines: the pty buffers 13 kB),
    stamped from ``t0_us``; ``aux`` channels are a supply voltage."""
    raw = simulate(n / rate_hz / 3600 * 1.01, rate_hz, seed,
                   SensorSpec.random(np.random.default_rng(seed))).raw[:n]
    t = t0_us + np.round(np.arange(n) * 1e6 / rate_hz).astype(np.int64)
    extra = np.round(3.3 + 0.01 * np.random.default_rng(seed).standard_normal((n, len(aux))),
                     3)
    return RawBatch(t, raw.v, extra, aux)


def run_args(link: str, *more: str) -> list[str]:
    return ["--port", link, "--sensor-id", SID, "--counts-per-g", "1024", "--zero-g", "0",
            *more]


def stop(gp: GatewayProcess) -> None:
    gp.proc.send_signal(signal.SIGTERM)
    assert gp.proc.wait(30) == 0, gp.lines
    assert not any("Traceback" in ln for ln in gp.lines), gp.lines


def finished(path: Path) -> bool:
    """Whether the recording was closed properly (the mcap reader finds its summary)."""
    with open(path, "rb") as f:
        return make_reader(f).get_summary() is not None


def raw_logged(path: Path) -> RawBatch:
    assert finished(path)
    return rec.read_all_raw(path, SID)


def calibrated(path: Path) -> tuple[np.ndarray, np.ndarray]:
    cal = rec.read_all_calibrated(path, SID)
    assert np.isfinite(cal.a_g).all()  # no NaN published
    return cal.t_us, cal.a_g


def events(path: Path) -> list[dict]:
    return [obj for _, obj, _ in rec.iter_json(path, f"/{SID}/events")]


def assert_same(got: RawBatch, sent: RawBatch) -> None:
    np.testing.assert_array_equal(got.t_us, sent.t_us)
    np.testing.assert_array_equal(got.v, sent.v)
    np.testing.assert_array_equal(got.aux, sent.aux)


def one_error_line(args: list[str], cwd: Path) -> tuple[int, str, float]:
    """`python -m recal run ...` expected to fail at start: (status, its one stderr line, s)."""
    started = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "recal", "run", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"})
    lines = done.stderr.splitlines()
    assert "Traceback" not in done.stderr + done.stdout, done.stderr
    assert len(lines) == 1 and lines[0].startswith("recal: error: "), done.stderr
    return done.returncode, lines[0], time.monotonic() - started


# ---------------------------------------------------------------------------------------------


def test_a_device_that_talked_before_the_port_opened_loses_nothing(tmp_path: Path,
                                                                  children: list) -> None:
    """Header first (without '#'), then lines, all written before the daemon starts: every
    sample is logged once, under the header's channel name, and calibrated."""
    link = str(tmp_path / "tty0")
    sent = device_samples(700, 100.0, aux=("vdd",))
    with PtyDevice(link, header=True, header_prefix="") as dev:
        dev.write_batch(sent[:400])  # header + 400 lines, nobody reading yet
        assert dev.bytes_dropped == 0
        gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap",
                            run_args(link, "--rate", "100"))
        children.append(gp)
        dev.write_batch(sent[400:])
        assert dev.bytes_dropped == 0
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        time.sleep(0.5)
        stop(gp)
    got = raw_logged(gp.mcap)
    assert got.aux_names == ("vdd",)
    assert_same(got, sent)
    t_cal, _ = calibrated(gp.mcap)
    np.testing.assert_array_equal(t_cal, sent.t_us)
    assert "missing_channel" not in [e["kind"] for e in events(gp.mcap)]


def test_a_model_needing_a_channel_the_stream_lacks_is_one_error(tmp_path: Path,
                                                                 children: list) -> None:
    """A model with a supply term on 'vdd' and a device whose header-less lines give
    positional names: one error line, exit 2, the MCAP finished with what was logged; the
    same with --aux-names that lack it, refused before anything starts."""
    model = SensorModel.diagonal(1024.0).with_effect(Ratiometric("vdd", 3.3), 0.5)
    model_file = tmp_path / "vdd-model.json"
    model_file.write_text(json.dumps(model.to_dict()))
    link = str(tmp_path / "tty0")
    sent = device_samples(300, 100.0, aux=("vdd",))
    mcap = tmp_path / "run.mcap"
    with PtyDevice(link, header=False) as dev:
        proc = subprocess.Popen(
            [sys.executable, "-m", "recal", "run", "--config", str(config(tmp_path)),
             "--mcap", str(mcap), *run_args(link, "--rate", "100", "--model", str(model_file))],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"})
        try:
            assert wait_for(lambda: dev.write_batch(sent[:10]) > 0 and proc.poll() is not None,
                            30, 0.2)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert proc.returncode == 2, err
    assert "Traceback" not in out + err, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("recal: error: sensor s1: the model needs "
                                                   "channel 'vdd'"), err
    assert "aux0" in lines[0]
    got = raw_logged(mcap)  # finished, and what was read is in it
    assert len(got) >= 2 and np.isin(got.t_us, sent.t_us).all()
    assert [e["kind"] for e in events(mcap)].count("missing_channel") == 1

    status, line, _ = one_error_line(
        ["--config", str(config(tmp_path)), "--mcap", str(tmp_path / "b.mcap"),
         *run_args(str(tmp_path / "absent"), "--aux-names", "temp", "--model", str(model_file))],
        tmp_path)
    assert status == 2 and "needs channel 'vdd'" in line and "['temp']" in line
    assert not (tmp_path / "b.mcap").exists()


def test_sigterm_and_restart_while_the_device_writes_loses_nothing(tmp_path: Path,
                                                                  children: list) -> None:
    """What the kernel buffered while the daemon was down (2 s and the restart) is read after
    the re-open: the two logs together hold every sample the device wrote, once, in order."""
    link = str(tmp_path / "tty0")
    sent = device_samples(450, 50.0)  # 9 s at 50 Hz
    cfg = config(tmp_path)
    with PtyDevice(link, header=True) as dev:
        first = GatewayProcess(cfg, tmp_path / "a.mcap", run_args(link, "--rate", "50"))
        children.append(first)
        dev.start_streaming(sent, rate_hz=50.0)
        time.sleep(2.5)
        stop(first)
        time.sleep(2.2)  # the device goes on writing; nobody reads
        second = GatewayProcess(cfg, tmp_path / "b.mcap", run_args(link, "--rate", "50"))
        children.append(second)
        assert dev.join(20.0)
        assert dev.bytes_dropped == 0
        time.sleep(0.5)
        stop(second)
    a, b = raw_logged(first.mcap), raw_logged(second.mcap)
    print(f"\nsent {len(sent)}: first run logged {len(a)}, second {len(b)}")
    assert len(a) > 50 and len(b) > 150
    assert_same(RawBatch.concat([a, b]), sent)
    assert "start: checkpoint" in " ".join(second.lines) or \
        "'s1': 'checkpoint'" in (second.ready_line or "")


def test_a_second_daemon_on_a_held_port_exits_at_once_naming_the_holder(
        tmp_path: Path, children: list) -> None:
    link = str(tmp_path / "tty0")
    sent = device_samples(300, 100.0)
    with PtyDevice(link, header=True) as dev:
        first = GatewayProcess(config(tmp_path), tmp_path / "a.mcap", run_args(link))
        children.append(first)
        assert wait_for(lambda: first.has_open(os.path.realpath(link)), 10)
        dev.start_streaming(sent, rate_hz=100.0)
        (tmp_path / "other").mkdir()
        status, line, took_s = one_error_line(
            ["--config", str(config(tmp_path / "other")), "--mcap", str(tmp_path / "b.mcap"),
             *run_args(link)], tmp_path)
        assert status != 0 and took_s < 15
        assert f"port {link} is in use by process {first.proc.pid}" in line, line
        assert not (tmp_path / "b.mcap").exists()
        assert dev.join(10.0) and dev.bytes_dropped == 0
        time.sleep(0.3)
        stop(first)
    assert_same(raw_logged(first.mcap), sent)  # the first kept every sample


def test_bad_port_values_are_one_error_line_quickly(tmp_path: Path) -> None:
    (tmp_path / "file.txt").write_text("not a device\n")
    cases = {str(tmp_path / "file.txt"): "is not a character device",
             str(tmp_path): "is a directory",
             "/dev/null": "is a character device but not a terminal",
             "bogus://device": "invalid URL"}
    for port, fragment in cases.items():
        status, line, took_s = one_error_line(
            ["--config", str(config(tmp_path)), "--mcap", str(tmp_path / "x.mcap"),
             *run_args(port)], tmp_path)
        assert status == 2 and took_s < 15, (port, status, took_s)
        assert f"port {port}" in line and fragment in line, line
    assert not (tmp_path / "x.mcap").exists()


def test_a_missing_port_is_waited_for_and_picked_up(tmp_path: Path, children: list) -> None:
    link = str(tmp_path / "ttyLATER")
    gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap", run_args(link))
    children.append(gp)
    waiting = f"{SID}: port missing {link}"
    assert wait_for(lambda: any(waiting in ln and "waiting for it" in ln for ln in gp.lines),
                    10), gp.lines
    sent = device_samples(100, 100.0, aux=("vdd",))
    with PtyDevice(link, header=True) as dev:
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10), gp.lines
        dev.write_batch(sent)
        time.sleep(0.5)
        stop(gp)
    assert any(f"{SID}: port opened {link}" in ln for ln in gp.lines), gp.lines
    got = raw_logged(gp.mcap)
    assert got.aux_names == ("vdd",)
    assert_same(got, sent)


@pytest.mark.parametrize("clock", ["us32", "ms", "none"])
def test_device_clocks_through_the_daemon(tmp_path: Path, children: list, clock: str) -> None:
    """The raw log keeps what the device wrote; the calibrated output is on the time base:
    a wrapping micros() unwrapped, millis() read as ms (an event and a console line), lines
    without time stamped 1/rate apart from their arrival (--rate 50)."""
    link = str(tmp_path / "tty0")
    rate = 50.0 if clock == "none" else 100.0
    t0 = WRAP - 2_000_000 if clock == "us32" else 5_000_000
    sent = device_samples(400, rate, t0_us=t0, aux=("vdd",))
    more = ("--rate", "50") if clock == "none" else ()
    with PtyDevice(link, header=True, clock=clock) as dev:
        gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap", run_args(link, *more))
        children.append(gp)
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        for i in range(0, len(sent), 50):
            dev.write_batch(sent[i:i + 50])
            time.sleep(0.02)
        assert dev.bytes_dropped == 0
        time.sleep(0.5)
        stop(gp)
    got = raw_logged(gp.mcap)
    assert got.aux_names == ("vdd",)
    np.testing.assert_array_equal(got.v, sent.v)  # every line logged, once
    t_cal, _ = calibrated(gp.mcap)
    assert np.all(np.diff(t_cal) > 0)
    # replay of the raw log applies the same time base (the node's, with its setup)
    replay(gp.mcap, tmp_path / "replayed.mcap", progress=False)
    np.testing.assert_array_equal(calibrated(tmp_path / "replayed.mcap")[0], t_cal)
    kinds = [e["kind"] for e in events(gp.mcap)]
    if clock == "us32":
        np.testing.assert_array_equal(got.t_us, sent.t_us % WRAP)  # as the device wrote it
        np.testing.assert_array_equal(t_cal, sent.t_us)  # unwrapped
        assert kinds.count("time_wrap") == 1
    elif clock == "ms":
        np.testing.assert_array_equal(got.t_us, sent.t_us // 1000)
        np.testing.assert_array_equal(t_cal, (sent.t_us // 1000) * 1000)
        assert kinds.count("time_units") == 1
        assert any("device time is in ms" in ln for ln in gp.lines), gp.lines
    else:
        np.testing.assert_array_equal(np.diff(got.t_us), 20_000)
        np.testing.assert_array_equal(t_cal, got.t_us)
        assert abs(got.t_us[0] / 1e6 - time.time()) < 60  # stamped from its arrival


TIOCGEXCL = 0x80045440  # Linux _IOR('T', 0x40, int): is the tty in exclusive mode


def _exclusive(fd: int) -> bool:
    import array
    import fcntl

    flag = array.array("i", [0])
    fcntl.ioctl(fd, TIOCGEXCL, flag)
    return bool(flag[0])


def test_the_port_is_held_exclusively_while_open_and_released_at_close(tmp_path: Path) -> None:
    """In process: TIOCEXCL set while a source holds the tty and cleared when it closes (the
    pty's device side keeps it open: a flag left set would lock out the next non-root run);
    a second source gets port_busy naming this PID, then opens once the first closed."""
    from recal.io.ascii_lines import AsciiLineParser
    from recal.io.serial_source import SerialSource

    link = str(tmp_path / "tty0")
    with PtyDevice(link, header=True) as dev:
        slave = dev._slave
        assert slave is not None and not _exclusive(slave)
        first = SerialSource(link, AsciiLineParser(), backoff_initial_s=0.02)
        second = SerialSource(link, AsciiLineParser(), backoff_initial_s=0.02)
        try:
            _, ev = first.poll()
            assert [e.kind for e in ev] == ["port_opened"] and _exclusive(slave)
            _, ev = second.poll()
            assert [e.kind for e in ev] == ["port_busy"]
            assert ev[0].detail["holder_pid"] == os.getpid()
            assert ev[0].detail["error"] == f"in use by process {os.getpid()}"
            first.close()
            assert not _exclusive(slave)
            assert wait_for(lambda: "port_opened" in [e.kind for e in second.poll()[1]], 30)
            assert _exclusive(slave)
        finally:
            first.close()
            second.close()
        assert not _exclusive(slave)


# --------------------------------------------------------------------------- the first line


def _parse_after_break(stream: bytes, **kwargs: object) -> tuple[RawBatch, dict]:
    from recal.io.ascii_lines import AsciiLineParser

    parser = AsciiLineParser(**kwargs)  # type: ignore[arg-type]
    parser.reset(resync=True)  # as at an open: the first bytes may be any line's tail
    parts = [parser.feed(stream[i:i + 37]) for i in range(0, len(stream), 37)]
    parts.append(parser.flush())
    names = parts[-1].aux_names
    return RawBatch.concat([RawBatch(p.t_us, p.v, p.aux, names) for p in parts]), \
        parser.errors.nonzero()


def test_a_stream_cut_anywhere_gives_exactly_the_lines_after_the_cut() -> None:
    """Cut at every byte of its first lines, a stream gives every line that starts at or after
    the cut (the first one too, when whole) and nothing else: no tail taken for a sample."""
    sent = device_samples(12, 100.0, t0_us=5_000_000, aux=("vdd",))
    lines = encode_ascii(sent).splitlines(keepends=True)
    stream = b"".join(lines)
    starts = np.cumsum([0] + [len(ln) for ln in lines])
    for cut in range(int(starts[4])):
        got, errors = _parse_after_break(stream[cut:])
        first = int(np.searchsorted(starts, cut))  # the first line that starts at or after
        assert_same(got, sent[first:])
        tail = stream[cut:starts[first]].strip()  # (a lone newline is an empty line)
        assert errors.get("resync_dropped", 0) == (tail != b""), (cut, errors)


@pytest.mark.parametrize(("head", "names"), [(b"t_us,x,y,z,vdd\n", ("vdd",)),
                                             (b"#t_us,x,y,z,vdd\n", ("vdd",)),
                                             (b"us,x,y,z,vdd\n", ("vdd",)),  # cut in a name
                                             (b"x,y,z,vdd\n", ("aux0",)),  # a field short
                                             (b",z,vdd\n", ("aux0",))])
def test_a_header_first_is_a_header_unless_it_is_a_tail(head: bytes,
                                                        names: tuple[str, ...]) -> None:
    sent = device_samples(5, 100.0, t0_us=5_000_000, aux=("vdd",))
    got, _ = _parse_after_break(head + encode_ascii(sent))
    assert got.aux_names == names
    np.testing.assert_array_equal(got.t_us, sent.t_us)


def test_lines_without_time_after_a_break() -> None:
    """Without a header the first line cannot be vouched for (a cut x looks like an x); with
    an x,y,z header every line is kept, stamped 1/rate apart from the anchor."""
    sent = device_samples(6, 50.0, aux=("vdd",))
    body = encode_ascii(sent, time_column=False)
    # (x,y,z,vdd or t,x,y,z? the configured channel names say: 3 + 1 fields, no time)
    got, errors = _parse_after_break(body, rate_hz=50.0, aux_names=("vdd",))
    np.testing.assert_array_equal(got.v, sent.v[1:])
    assert errors["resync_dropped"] == 1
    got, errors = _parse_after_break(encode_ascii(sent, header=True, time_column=False,
                                                  header_prefix=""), rate_hz=50.0)
    np.testing.assert_array_equal(got.v, sent.v)
    np.testing.assert_array_equal(np.diff(got.t_us), 20_000)
    assert got.aux_names == ("vdd",) and "resync_dropped" not in errors
    # x,y,z and no rate: nothing to stamp them with, counted (the daemon's line hints --rate)
    xyz = RawBatch(sent.t_us, sent.v, np.zeros((len(sent), 0)), ())
    got, errors = _parse_after_break(encode_ascii(xyz, time_column=False))
    assert len(got) == 0 and errors == {"resync_dropped": 1, "wrong_columns": 5}


def test_run_options_set_what_the_config_would(tmp_path: Path) -> None:
    """--rate, --aux-names, --prior NAME (the config's priors, else the shipped ones),
    --counts-per-g and --zero-g, for every sensor served; an unknown name is one error."""
    from recal.config import ConfigError, SensorConfig, ServiceConfig, load_config
    from recal.config.sensor_options import SensorOptions, with_options

    cfg = ServiceConfig(sensors=(SensorConfig("a", port="x"), SensorConfig("b", port="y")))
    got = with_options(cfg, SensorOptions(rate_hz=50.0, aux_names=("vdd",),
                                          prior="adxl345-10bit-4mg"))
    assert all(s.rate_hz == 50.0 and s.aux_names == ("vdd",) for s in got.sensors)
    assert all(s.prior.counts_per_g == 256.0 and s.prior.sd["o_z"] == 15.0
               for s in got.sensors)
    got = with_options(cfg, SensorOptions(counts_per_g=2185.0, zero_g=4096.0))
    assert got.sensors[1].prior.counts_per_g == 2185.0
    assert got.sensors[1].prior.zero_g == (4096.0, 4096.0, 4096.0)
    (tmp_path / "p.toml").write_text("[priors.mine]\ncounts_per_g = 512.0\nzero_g = 7\n")
    (tmp_path / "g.toml").write_text('priors_file = "p.toml"\n[zenoh]\nenabled = false\n')
    own = load_config(tmp_path / "g.toml").with_sensors(cfg.sensors)
    assert with_options(own, SensorOptions(prior="mine")).sensors[0].prior.zero_g == (7.0,) * 3
    with pytest.raises(ConfigError, match="--prior adxl345-10bit-4mg: no prior named"):
        with_options(own, SensorOptions(prior="adxl345-10bit-4mg"))  # not among the config's
    status, line, _ = one_error_line(
        ["--config", str(config(tmp_path)), "--mcap", str(tmp_path / "x.mcap"), "--port",
         str(tmp_path / "absent"), "--prior", "nosuch"], tmp_path)
    assert status == 2 and "--prior nosuch: no prior named 'nosuch'" in line


def test_a_device_reboot_is_an_event_and_a_console_line(tmp_path: Path,
                                                        children: list) -> None:
    """The device restarts (its clock from 0, its header again) while the daemon runs: the
    raw log keeps both clocks, the calibrated time goes on, an event and one console line."""
    link = str(tmp_path / "tty0")
    before = device_samples(200, 100.0, t0_us=3_600_000_000)  # an hour after boot
    after = device_samples(200, 100.0, t0_us=1_500_000, seed=5)  # 1.5 s after a reboot
    with PtyDevice(link, header=True) as dev:
        gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap", run_args(link))
        children.append(gp)
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        dev.write_batch(before)
        time.sleep(0.3)
        dev.write_header(())  # it boots, says who it is
        dev.write_batch(after)
        assert wait_for(lambda: any("device time restarted" in ln for ln in gp.lines), 10), \
            gp.lines
        stop(gp)
    got = raw_logged(gp.mcap)
    assert_same(got, RawBatch.concat([before, after]))
    t_cal, _ = calibrated(gp.mcap)
    assert np.all(np.diff(t_cal) > 0)
    np.testing.assert_array_equal(t_cal[:200], before.t_us)
    assert t_cal[200] - t_cal[199] == 10_000  # one nominal step on
    assert [e["kind"] for e in events(gp.mcap)].count("time_reboot") == 1
    assert sum("device time restarted" in ln for ln in gp.lines) == 1


def test_xyz_lines_without_a_rate_are_counted_and_the_console_says_what_is_missing(
        tmp_path: Path, children: list) -> None:
    link = str(tmp_path / "tty0")
    sent = device_samples(100, 50.0)
    with PtyDevice(link, header=False, clock="none") as dev:
        gp = GatewayProcess(config(tmp_path), tmp_path / "run.mcap", run_args(link))
        children.append(gp)
        assert wait_for(lambda: gp.has_open(os.path.realpath(link)), 10)
        dev.write_batch(sent)
        assert wait_for(lambda: any("need the rate: --rate" in ln for ln in gp.lines), 10), \
            gp.lines
        stop(gp)
    assert len(raw_logged(gp.mcap)) == 0
    totals = [e["detail"]["total"] for e in events(gp.mcap) if e["kind"] == "parse_errors"]
    # every line counted (the first after the open as resync_dropped: it cannot be vouched)
    assert totals[-1] == {"wrong_columns": 99, "resync_dropped": 1}
