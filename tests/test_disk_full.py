"""A full disk under the live daemon: the recording is one consumer, not a gate.

Real parts only: a 4 MB tmpfs mounted for the test (root; the mount failing fails the test),
filled with a filler file and given back by deleting it; `python -m recal run` as a child
process reading a pseudo-terminal the test writes at 1000 samples/s; a Zenoh subscriber on
127.0.0.1 counting the calibrated messages; the recording read back with the mcap reader (and
`recal repair` for a file the daemon could not finish). Every wait is bounded in count and time.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from gateway_process import GatewayProcess
from polling import wait_for
from recal.cli import main as recal_main
from recal.commands.demo import free_port
from recal.config import ConfigError, parse_config
from recal.daemon import runtime
from recal.daemon.checkpoint_store import load_checkpoint, save_checkpoint
from recal.daemon.runtime import open_recording
from recal.errors import RecordingError
from recal.io import recording as rec
from recal.io.bus import Bus, key
from recal.io.bus_config import zenoh_config
from recal.io.messages import decode_calibrated
from recal.io.recording_writer import RecordingWriter
from recal.samples import RawBatch
from recal.sim.pty_device import PtyDevice
from test_gateway import get_json, sim_raw, stream

SID = "s1"
SEND_PER_S = 1000.0  # lines per second into the pty
CHUNK = 10  # samples per write
BACKLOG_MB = 0.25  # [mcap] backlog_mb: what may wait in memory while the disk is full
FULL_S = 32.0  # how long the disk stays full
ROTATE_MB = 0.3  # [mcap] rotate_mb: several parts, so samples are checked across parts too
STOPPED = re.compile(r"recording: cannot write")
RESUMED = re.compile(r"recording: writing again .* lost (\d+) raw samples \((\d+) messages\)")


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[Path]:
    """A 4 MB tmpfs of its own, always unmounted afterwards (lazily if a file is still open)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)],
                          capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        pytest.fail(f"cannot mount a 4 MB tmpfs at {mnt} (the test needs root): "
                    f"{done.stderr.strip()}")
    try:
        yield mnt
    finally:
        if subprocess.run(["umount", str(mnt)], capture_output=True, timeout=30).returncode:
            subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)


def fill(disk: Path) -> Path:
    """Fill the disk to the last page with a filler file; returns its path."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
    try:
        for size in (65536, 4096, 512, 1):
            block = b"\xa5" * size
            for _ in range(4 * 2**20 // size + 2):  # bounded: more than the whole disk
                try:
                    os.write(fd, block)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC, exc
                    break
    finally:
        os.close(fd)
    probe = disk / "probe"
    with pytest.raises(OSError), open(probe, "wb", buffering=0) as f:
        f.write(b"x" * 4096)
    probe.unlink(missing_ok=True)
    return filler


def write_config(tmp: Path, disk: Path, link: str, zenoh_port: int) -> Path:
    path = tmp / "gateway.toml"
    path.write_text(f"""[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{zenoh_port}"]
connect = []

[mcap]
flush_interval_s = 0.05
backlog_mb = {BACKLOG_MB}
rotate_mb = {ROTATE_MB}

[checkpoint]
dir = "{disk / 'ck'}"
interval_s = 0.25

[[sensors]]
id = "{SID}"
port = "{link}"
aux_names = []
rate_hz = 100.0
prior = {{ counts_per_g = 1024.0, zero_g = 0 }}
""")
    return path


class ProcSampler:
    """RSS (MB) and CPU time (s, all threads) of a process every 0.25 s, on a thread."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.rows: list[tuple[float, float, float]] = []  # monotonic s, RSS MB, CPU s
        self._stop = threading.Event()
        self._tick = os.sysconf("SC_CLK_TCK")
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        for _ in range(4000):  # bounded: 1000 s
            with contextlib.suppress(OSError, ValueError, IndexError):
                rss = re.search(r"VmRSS:\s+(\d+)", Path(f"/proc/{self.pid}/status").read_text())
                if rss is None:  # the process has exited
                    return
                rss_kb = int(rss.group(1))
                stat = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
                cpu_s = (int(stat[11]) + int(stat[12])) / self._tick
                self.rows.append((time.monotonic(), rss_kb / 1024, cpu_s))
            if self._stop.wait(0.25):
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def phase(self, t0: float, t1: float) -> tuple[float, float, float]:
        """(median RSS, max RSS, CPU % of a core) between two monotonic times."""
        rows = np.array([r for r in self.rows if t0 <= r[0] <= t1])
        assert len(rows) >= 2, (t0, t1, len(self.rows))
        cpu = 100 * (rows[-1, 2] - rows[0, 2]) / (rows[-1, 0] - rows[0, 0])
        return float(np.median(rows[:, 1])), float(rows[:, 1].max()), float(cpu)


class Listener:
    """A Zenoh peer subscribed to the calibrated stream: arrival time and t_us per message."""

    def __init__(self, zenoh_port: int) -> None:
        self.arrivals: list[tuple[float, np.ndarray]] = []
        self.bus = Bus(zenoh_config("peer", ["tcp/127.0.0.1:0"],
                                    [f"tcp/127.0.0.1:{zenoh_port}"]))
        self.bus.subscribe(key(SID, "calibrated"), lambda m: self.arrivals.append(
            (time.monotonic(), decode_calibrated(m.payload)[1].t_us)))

    def per_second(self, t0: float, t1: float) -> list[int]:
        """Messages heard in each whole second of [t0, t1)."""
        times = np.array([a for a, _ in self.arrivals])
        return np.histogram(times, np.arange(t0, t1 + 1e-9, 1.0))[0].tolist()

    def t_us(self, t0: float, t1: float) -> np.ndarray:
        parts = [t for a, t in self.arrivals if t0 <= a < t1]
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def start_gateway(config: Path, mcap: Path, dev: PtyDevice,
                  children: list[GatewayProcess]) -> GatewayProcess:
    gw = GatewayProcess(config, mcap)
    children.append(gw)
    assert wait_for(lambda: gw.has_open(dev.slave_name), 20, 0.02), gw.lines
    time.sleep(0.2)  # pyserial flushes the input right after opening: write after that
    dev.write_header(())
    return gw


def send(dev: PtyDevice, raw: RawBatch, start: int, seconds: float) -> int:
    return stream(dev, raw[start:], SEND_PER_S, chunk=CHUNK, stop_after_s=seconds)[0]


def logged_raw(mcap: Path, tmp: Path) -> RawBatch:
    """Every raw sample of every part; a part the daemon could not finish is repaired first."""
    batches = []
    for k, part in enumerate(rec.recording_parts(mcap)):
        try:
            batches.append(rec.read_all_raw(part, SID))
        except RecordingError:
            fixed = tmp / f"repaired-{k}.mcap"
            assert recal_main(["repair", str(part), "--out", str(fixed)]) == 0
            batches.append(rec.read_all_raw(fixed, SID))
    return RawBatch.concat(batches)


def leftovers(disk: Path, mcap: Path) -> list[str]:
    """Files on the disk that are neither a recording part nor the checkpoint (its previous
    generation and its lock included)."""
    keep = {p.name for p in rec.recording_parts(mcap)} | {f"{SID}.json", f"{SID}.json.prev",
                                                          f"{SID}.lock"}
    return sorted(str(p.relative_to(disk)) for p in disk.rglob("*")
                  if p.is_file() and p.name not in keep)


def assert_in_order_once(got: RawBatch, raw: RawBatch) -> np.ndarray:
    """Every logged sample is one the device sent, bit for bit, each once and in order;
    returns their indices in ``raw``."""
    assert np.all(np.diff(got.t_us) > 0), "a sample twice or out of order"
    idx = np.searchsorted(raw.t_us, got.t_us)
    assert np.all(idx < len(raw)) and np.array_equal(raw.t_us[idx], got.t_us)
    np.testing.assert_array_equal(got.v, raw.v[idx])
    return idx


# --------------------------------------------------------------------------- the writer alone


def batches(n: int, first: int = 0, size: int = 100) -> list[RawBatch]:
    """``n`` raw batches of noise (not very compressible), time stamps 10 ms apart."""
    rng = np.random.default_rng(first)
    out = []
    for i in range(first, first + n):
        t_us = (i * size + np.arange(size)) * 10_000
        out.append(RawBatch(t_us, rng.integers(-2048, 2048, (size, 3)).astype(float),
                            np.zeros((size, 0))))
    return out


def test_writer_waits_within_its_budget_and_resumes_in_the_same_file(small_disk: Path) -> None:
    budget = 100_000
    w = RecordingWriter(small_disk / "w.mcap", background_flush=False,
                        flush_interval_s=1000.0, backlog_bytes=budget)
    sent = batches(2000)
    for b in sent[:50]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.flush()
    filler = fill(small_disk)
    k = 50
    for k in range(50, 1500):  # until the budget overflowed (bounded)
        b = sent[k]
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)  # never raises
        if k % 10 == 0:
            w.flush()  # tries the disk again: refused
        if w.health().dropped_messages >= 20:
            break
    h = w.health()
    assert h.failing and h.error and "space" in h.error, h
    assert h.waiting_bytes <= budget, h
    # whole messages, each of the batches joined since a flush (ten here)
    assert h.dropped_samples % 100 == 0 and h.dropped_samples >= 100 * h.dropped_messages > 0
    os.unlink(filler)
    w.flush()
    assert not w.health().failing and w.health().waiting_bytes == 0
    assert w.messages_flushed == w.messages_written - h.dropped_messages
    for b in sent[k + 1:k + 51]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.close()
    assert w.paths == [small_disk / "w.mcap"] and w.health().unfinished == ()
    got = rec.read_all_raw(w.paths, SID)  # an indexed, finished file
    written = RawBatch.concat(sent[:k + 51])
    idx = assert_in_order_once(got, written)
    assert len(written) - len(got) == h.dropped_samples
    kept = np.zeros(len(written), bool)
    kept[idx] = True
    assert kept[:50 * 100].all() and kept[-50 * 100:].all()  # before the fill, after resuming
    lost = np.flatnonzero(~kept)
    assert lost[0] >= 50 * 100 and np.all(np.diff(lost) == 1)  # the oldest waiting, at once


def test_writer_closed_while_full_leaves_a_repairable_file(small_disk: Path,
                                                            tmp_path: Path) -> None:
    w = RecordingWriter(small_disk / "c.mcap", flush_interval_s=0.02, backlog_bytes=50_000)
    sent = batches(200)
    for b in sent[:30]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.flush()
    fill(small_disk)
    for b in sent[30:]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.close()  # does not raise
    h = w.health()
    assert h.unfinished == (small_disk / "c.mcap",) and h.dropped_messages > 0, h
    with pytest.raises(RecordingError):
        rec.read_all_raw(w.paths, SID)
    fixed = tmp_path / "fixed.mcap"
    assert recal_main(["repair", str(w.paths[0]), "--out", str(fixed)]) == 0
    got = rec.read_all_raw(fixed, SID)
    idx = assert_in_order_once(got, RawBatch.concat(sent))
    assert np.array_equal(idx[:3000], np.arange(3000))
    assert len(got) + h.dropped_samples == 200 * 100


def test_flush_thread_outlives_the_full_disk_and_writes_when_space_returns(
        small_disk: Path) -> None:
    w = RecordingWriter(small_disk / "t.mcap", flush_interval_s=0.02, backlog_bytes=10**6)
    try:
        filler = fill(small_disk)
        for b in batches(30):
            w.write_raw(SID, b, int(b.t_us[0]) * 1000)
        assert wait_for(lambda: w.health().failing, 30)
        time.sleep(0.2)  # several refused flushes on the thread
        os.unlink(filler)
        # only the flush thread writes now: the owner makes no call
        # (the batches are joined into messages: every message written is in the file)
        assert wait_for(lambda: w.messages_flushed == w.messages_written > 0, 30), \
            (w.messages_flushed, w.health())
        assert not w.health().failing
    finally:
        w.close()
    assert len(rec.read_all_raw(w.paths, SID)) == 30 * 100


def test_a_checkpoint_the_disk_refuses_leaves_the_old_one_and_no_temporary_file(
        small_disk: Path) -> None:
    path = small_disk / "ck" / f"{SID}.json"
    save_checkpoint(path, {"n": 1})
    fill(small_disk)
    with pytest.raises(OSError):
        save_checkpoint(path, {"n": 2, "pad": "x" * 100_000})
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert json.loads(path.read_text()) == {"n": 1}


def test_the_operator_hears_of_each_outage_once_with_what_it_lost(
        small_disk: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    w = RecordingWriter(small_disk / "o.mcap", background_flush=False,
                        flush_interval_s=1000.0, backlog_bytes=30_000)
    lines: list[str] = []
    events: list[tuple[str, dict]] = []
    watch = runtime.RecordingWatch(w, lines.append, 0.03)

    def check() -> None:
        watch.check(time.time_ns(), lambda kind, detail: events.append((kind, detail)))

    sent = batches(400)
    for b in sent[:20]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.flush()
    check()
    assert lines == [] and events == []
    # an outage that lasts: a line when it begins, a reminder, a line when it ends
    filler = fill(small_disk)
    for b in sent[20:200]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.flush()
    check()
    check()  # nothing new to say
    assert len(lines) == 1 and "cannot write" in lines[0] and "No space left" in lines[0]
    monkeypatch.setattr(runtime, "WRITE_NOTE_S", 0.0)
    check()
    assert len(lines) == 2 and "still cannot write" in lines[1], lines
    monkeypatch.setattr(runtime, "WRITE_NOTE_S", 60.0)
    os.unlink(filler)
    w.flush()
    check()
    check()
    h = w.health()
    assert h.dropped_samples > 0 and len(lines) == 3, lines
    assert lines[2].endswith(f"lost {h.dropped_samples} raw samples "
                             f"({h.dropped_messages} messages)"), lines[2]
    assert [k for k, _ in events] == ["write_failed", "write_resumed"]
    assert events[1][1]["lost_samples"] == h.dropped_samples
    # one over before anyone looked: both lines at once, with only its own loss
    filler = fill(small_disk)
    for b in sent[200:400]:
        w.write_raw(SID, b, int(b.t_us[0]) * 1000)
    w.flush()
    os.unlink(filler)
    w.flush()
    check()
    second = w.health().dropped_samples - h.dropped_samples
    assert second > 0 and len(lines) == 5 and "cannot write" in lines[3], lines
    assert lines[4].endswith(f"lost {second} raw samples "
                             f"({w.health().dropped_messages - h.dropped_messages} messages)")
    w.close()
    watch.closed()  # finished: nothing to say
    assert len(lines) == 5 and w.health().unfinished == ()


def test_the_budget_is_the_mcap_backlog_mb_key(tmp_path: Path) -> None:
    assert parse_config({}, tmp_path, "test").mcap.backlog_mb == 4.0
    cfg = parse_config({"mcap": {"backlog_mb": 2.5}}, tmp_path, "test")
    writer = open_recording(cfg, tmp_path / "b.mcap")
    writer.close()
    assert writer.backlog_bytes == 2_500_000
    for bad in (0, -1, "big"):
        with pytest.raises(ConfigError, match="backlog_mb"):
            parse_config({"mcap": {"backlog_mb": bad}}, tmp_path, "test")


# --------------------------------------------------------------------------- the daemon


def test_full_disk_for_30_s_calibration_goes_on_and_logging_resumes(
        tmp_path: Path, small_disk: Path, children: list[GatewayProcess]) -> None:
    raw = sim_raw(10.0, seed=21)
    zport = free_port()
    link = str(tmp_path / "ttyFULL")
    config = write_config(tmp_path, small_disk, link, zport)
    listener = Listener(zport)
    sampler = None
    try:
        with PtyDevice(link, "ascii", header=False, write_timeout_s=5.0) as dev:
            gw = start_gateway(config, small_disk / "live.mcap", dev, children)
            sampler = ProcSampler(gw.proc.pid)
            # before: until the subscriber hears the stream, then 6 s more
            sent = 0
            for _ in range(50):  # bounded: up to ~10 s of 0.2 s bursts
                sent += send(dev, raw, sent, 0.2)
                if listener.arrivals:
                    break
            assert listener.arrivals, "the subscriber never heard the gateway"
            t_before = time.monotonic()
            sent += send(dev, raw, sent, 6.0)
            time.sleep(0.3)  # the last samples before the fill reach the disk (flush 0.05 s)
            before_fill = sent

            filler = fill(small_disk)
            t_full = time.monotonic()
            states = []  # the gateway's own account of its recording, every ~4 s
            for _ in range(20):  # bounded: FULL_S in bursts of up to 4 s
                left = t_full + FULL_S - time.monotonic()
                if left <= 0:
                    break
                sent += send(dev, raw, sent, min(4.0, left))
                states.append(get_json(listener.bus, key(SID, "status"))["gateway"][
                    "recording"])
            full_sent = (before_fill, sent)
            os.unlink(filler)  # space comes back
            t_back = time.monotonic()
            resumed = None
            for _ in range(100):  # bounded: up to ~20 s of 0.2 s bursts
                sent += send(dev, raw, sent, 0.2)
                resumed = next((m for ln in gw.lines if (m := RESUMED.search(ln))), None)
                if resumed:
                    break
            assert resumed, gw.lines
            t_resumed = time.monotonic()
            after_resume = sent
            sent += send(dev, raw, sent, 6.0)
            time.sleep(0.5)
            t_end = time.monotonic()
            gw.proc.send_signal(signal.SIGTERM)
            assert gw.proc.wait(60) == 0, gw.lines
            assert dev.bytes_dropped == 0
    finally:
        listener.bus.close()
        if sampler is not None:
            sampler.stop()

    # the console said when writing stopped and when it resumed, with what was lost
    stopped = [ln for ln in gw.lines if STOPPED.search(ln)]
    assert len(stopped) == 1, gw.lines
    lost_samples, lost_messages = int(resumed.group(1)), int(resumed.group(2))
    assert lost_samples > 0 and lost_messages > 0  # 32 s did not fit the budget
    # what waits for the disk stays within the budget (the gateway's status says so)
    print(f"recording status while full: {states}")
    assert all(not st["writing"] and st["waiting_bytes"] <= BACKLOG_MB * 1e6
               for st in states), states
    assert states[-1]["waiting_bytes"] > 0 and states[-1]["dropped_samples"] > 0

    # calibrated messages kept coming, every second the disk was full
    counts = listener.per_second(t_full, t_full + FULL_S)
    heard = listener.t_us(t_full, t_back + 1.0)
    want = raw.t_us[full_sent[0]:full_sent[1]]
    print(f"\ncalibrated messages per second while full: {counts}")
    assert min(counts) > 0, counts
    assert np.isin(want, heard).mean() >= 0.95, np.isin(want, heard).mean()

    # the log: in order, once each; all sent before the fill and after the resume; what is
    # missing is exactly what the console said was dropped
    got = logged_raw(gw.mcap, tmp_path)
    idx = assert_in_order_once(got, raw)
    kept = np.zeros(sent, bool)
    kept[idx] = True
    assert kept[:before_fill].all(), np.flatnonzero(~kept[:before_fill])[:10]
    assert kept[after_resume:sent].all(), np.flatnonzero(~kept[after_resume:sent])[:10]
    assert sent - len(got) == lost_samples, (sent, len(got), lost_samples)
    kinds = [obj["kind"] for _, obj, _ in rec.iter_json(
        [p for p in rec.recording_parts(gw.mcap)], "/gateway/events")]
    assert "write_resumed" in kinds and kinds[-1] == "stop", kinds
    assert leftovers(small_disk, gw.mcap) == []

    # memory stayed bounded; figures for the report
    rows = {name: sampler.phase(a, b) for name, a, b in (
        ("before", t_before, t_full), ("full", t_full + 2, t_back),
        ("after", t_resumed, t_end))}
    jumps = [(round(t - t_full, 2), round(r, 1)) for (t, r, _), (_, r0, _) in zip(
        sampler.rows[1:], sampler.rows[:-1], strict=True) if abs(r - r0) > 1.0]
    print(f"RSS steps over 1 MB (s from the fill, MB): {jumps}")
    print("phase   RSS median MB  RSS max MB  CPU %")
    for name, (med, top, cpu) in rows.items():
        print(f"{name:7s} {med:13.1f} {top:11.1f} {cpu:6.1f}")
    print(f"lost {lost_samples} samples ({lost_messages} messages) of "
          f"{full_sent[1] - full_sent[0]} sent while full; resumed "
          f"{t_resumed - t_back:.2f} s after space came back")
    # The daemon's RSS moves in steps of up to ~30 MB of its own (seen without a full disk:
    # +28 MB, then -15 MB); what the full disk may add is the budget. Unbounded growth (the
    # backlog before it had a budget: +34 MB) would add to those steps.
    assert rows["full"][1] - rows["before"][0] < 4 * BACKLOG_MB + 40, rows


def test_sigterm_while_the_disk_is_full_exits_0_and_leaves_no_temporary_file(
        tmp_path: Path, small_disk: Path, children: list[GatewayProcess]) -> None:
    raw = sim_raw(2.0, seed=22)
    link = str(tmp_path / "ttyTERM")
    config = write_config(tmp_path, small_disk, link, free_port())
    with PtyDevice(link, "ascii", header=False, write_timeout_s=5.0) as dev:
        gw = start_gateway(config, small_disk / "term.mcap", dev, children)
        sent = send(dev, raw, 0, 2.0)
        assert wait_for(lambda: (small_disk / "ck" / f"{SID}.json").exists(), 30)
        time.sleep(0.3)  # flushed every 0.05 s
        before_fill = sent
        fill(small_disk)
        sent += send(dev, raw, sent, 3.0)
        assert wait_for(lambda: any(STOPPED.search(ln) for ln in gw.lines), 30), gw.lines
        gw.proc.send_signal(signal.SIGTERM)
        assert gw.proc.wait(60) == 0, gw.lines
    print("\n" + "\n".join(gw.lines))
    assert any("not finished" in ln and "recal repair" in ln for ln in gw.lines), gw.lines
    assert sum("checkpoint not saved" in ln for ln in gw.lines) == 1, gw.lines  # rate-limited
    assert leftovers(small_disk, gw.mcap) == ["filler"]
    assert load_checkpoint(small_disk / "ck" / f"{SID}.json") is not None
    got = logged_raw(gw.mcap, tmp_path)
    idx = assert_in_order_once(got, raw)
    assert np.array_equal(idx[:before_fill], np.arange(before_fill)), "lost before the fill"
