"""Replay a recording through the calibration node, without Zenoh.

``replay(in_mcap, out_mcap)`` reads every ``/<sensor>/raw`` batch of a recording (rotated parts
included), runs each sensor's :class:`recal.node.node.CalibrationNode` (the code path the gateway
runs live) and writes raw + calibrated + body + calibration + plot + events + setup to a new
recording, with the original log times.

Speed: consecutive arrivals of a sensor (the raw messages, or the arrivals a joined message
keeps) go through the pipeline together (``JOIN_SAMPLES`` at a time, via
``CalibrationNode.process_many``), which changes nothing in the output, still as of each
arrival's end (the pipeline is batch-size invariant and reports its state at each arrival's
end); the raw samples are logged again in the compact form and every batch topic is joined
into messages of up to 8192 samples; the output is written in 1 MiB chunks compressed on a
second thread.

How each sensor's pipeline starts, first match wins:
1. ``model`` or a ``config`` whose sensor entry has a prior: a fresh pipeline from them;
2. the recording's ``/<sensor>/setup`` message (written by the live node): the pipeline's exact
   starting state, so the replay reproduces the live calibration bit for bit, also for a run
   that had resumed from a checkpoint;
3. nothing known: bootstrap (prior None). The sample rate comes from the config, else from the
   setup, else it is measured from the time stamps.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from recal.config import (
    AlignmentConfig,
    SensorConfig,
    ServiceConfig,
    load_config,
    load_model_file,
    model_and_prior,
)
from recal.core.alignment import Alignment
from recal.core.pipeline import Pipeline
from recal.core.status import status_line
from recal.core.timebase import TimebaseState
from recal.io import recording as rec
from recal.io.messages import Arrivals
from recal.io.recording_writer import FILE_TO_FILE_FLUSH_S, RecordingWriter
from recal.io.sources import (
    Source,
    open_recording,
    recording_kind,
    source_lines,
    string_metadata,
)
from recal.node.node import CalibrationNode, NodeSettings, model_name, node_settings
from recal.node.sinks import RecordingSink
from recal.samples import CalibratedBatch, RawBatch

__all__ = ["replay", "replay_lines"]


#: Raw samples of consecutive messages handed to the node together (one pipeline step; the
#: output is still one of each per message). Bigger saves little more and holds more memory.
JOIN_SAMPLES = 8192


class _JoiningSink(RecordingSink):
    """A RecordingSink that holds a step's calibrated, body and plot batches (one per
    arrival) and hands them to the writer at `flush` (after each pipeline step) in a call
    per topic instead of one per arrival: the same messages (the batches still join into
    messages arrival by arrival; the plot's log times stay per arrival)."""

    def __init__(self, writer: RecordingWriter) -> None:
        super().__init__(writer)
        self.writer: RecordingWriter = writer
        self._batches: dict[tuple[str, str], list[tuple[CalibratedBatch, int]]] = {}
        self._plots: dict[str, list[tuple[CalibratedBatch, int, int]]] = {}
        self._bodies: dict[str, list[tuple[CalibratedBatch, np.ndarray | None, int]]] = {}

    def calibrated(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
                   suffix: str = "calibrated") -> None:
        if suffix == "body":  # times and the rotation if they say it, else the values
            found = self.body.of(sensor_id, batch)
            self._bodies.setdefault(sensor_id, []).append(
                (batch, None, log_time_ns) if found is None else (found[0], found[1],
                                                                   log_time_ns))
            return
        if suffix == "calibrated":
            self.body.note_calibrated(sensor_id, batch)
        elif not self.keeps(suffix):  # (the registry's: unknown raises, unlogged is skipped)
            return
        self._batches.setdefault((sensor_id, suffix), []).append((batch, log_time_ns))

    def plot(self, sensor_id: str, batch: CalibratedBatch, log_time_ns: int,
             every_n: int) -> None:
        self._plots.setdefault(sensor_id, []).append((batch, log_time_ns, every_n))

    def flush(self) -> None:
        for (sid, suffix), held in self._batches.items():
            self.writer.log_calibrated_many(sid, [b for b, _ in held], [t for _, t in held],
                                            suffix)
        for sid, bodies in self._bodies.items():
            self.writer.log_body_many(sid, bodies)
        for sid, plots in self._plots.items():
            start = 0
            for i in range(1, len(plots) + 1):  # runs of one decimation
                if i == len(plots) or plots[i][2] != plots[start][2]:
                    run = plots[start:i]
                    self.writer.write_plot(
                        sid, _joined(run), run[-1][1], run[0][2],
                        arrivals=(np.array([len(b) for b, *_ in run], np.int64),
                                  np.array([t for _, t, _ in run], np.int64)))
                    start = i
        self._batches, self._plots, self._bodies = {}, {}, {}


def _joined(items: list[Any]) -> CalibratedBatch:
    return items[0][0] if len(items) == 1 else CalibratedBatch.concat([it[0] for it in items])


@dataclass
class _SensorRun:
    node: CalibrationNode
    sink: _JoiningSink
    samples: int = 0
    batches: int = 0
    last_log_ns: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    waiting: list[tuple[RawBatch, int]] = field(default_factory=list)
    waiting_samples: int = 0
    reopens_ns: list[int] = field(default_factory=list)  # log times, latest first

    def add(self, batch: RawBatch, log_ns: int) -> None:
        if self.reopens_ns and log_ns > self.reopens_ns[-1]:
            # the port reopened before this arrival: the live node doubted there
            self.drain()
            while self.reopens_ns and log_ns > self.reopens_ns[-1]:
                self.reopens_ns.pop()
            self.node.port_reopened()
        self.waiting.append((batch, log_ns))
        self.waiting_samples += len(batch)
        if self.waiting_samples >= JOIN_SAMPLES:
            self.drain()

    def drain(self) -> None:
        if self.waiting:
            self.node.process_many(self.waiting)
            self.sink.flush()
        self.waiting, self.waiting_samples = [], 0


def _arrivals(batch: RawBatch, logged: rec.LoggedMessage, found: Arrivals | None
              ) -> list[tuple[RawBatch, int]]:
    """The batches as they arrived live, with their log times: a joined message's arrivals
    (the live node stepped once per arrival, and the calibration states fall at step ends),
    or the message itself."""
    if found is None:
        return [(batch, logged.log_time_ns)]
    sizes, log_us = found
    ends = np.cumsum(sizes)
    starts = ends - sizes
    log_ns = (logged.log_time_ns + 1000 * log_us if log_us is not None
              else np.full(len(sizes), logged.log_time_ns))
    return [(batch[a:b], t) for a, b, t in zip(starts.tolist(), ends.tolist(),
                                               log_ns.tolist(), strict=True)]


def _raw_message_count(paths: list[Path]) -> int | None:
    """Raw messages in the recording, from the MCAP summaries (no decoding); None if unknown."""
    from mcap.reader import make_reader

    total = 0
    try:
        for p in paths:
            with open(p, "rb") as f:
                summ = make_reader(f).get_summary()
            if summ is None or summ.statistics is None:
                return None
            for cid, ch in summ.channels.items():
                if rec.split_topic(ch.topic)[1] == "raw":
                    total += summ.statistics.channel_message_counts.get(cid, 0)
    except Exception:  # a progress bar without a total is fine; reading reports real damage
        return None
    return total


def _reopens(paths: list[Path]) -> dict[str, list[int]]:
    """Per sensor, the log times at which its port opened again (each open after its first,
    as the gateway calls `CalibrationNode.port_reopened`), latest first."""
    opens: dict[str, list[int]] = {}
    for topic, obj, log_ns in rec.iter_json(paths, "/*/events"):
        if isinstance(obj, dict) and obj.get("kind") in ("port_opened", "port_found"):
            opens.setdefault(rec.split_topic(topic)[0], []).append(log_ns)
    return {sid: sorted(times[1:], reverse=True) for sid, times in opens.items()}


def _setups(paths: list[Path]) -> dict[str, dict[str, Any]]:
    """The first setup message of each sensor."""
    found: dict[str, dict[str, Any]] = {}
    for topic, obj, _ in rec.iter_json(paths, "/*/setup"):
        sid = rec.split_topic(topic)[0]
        if isinstance(obj, dict) and isinstance(obj.get("pipeline_state_json"), str):
            found.setdefault(sid, obj)
    return found


def _node_for(sid: str, cfg: ServiceConfig, model: str | Path | None,
              setup: dict[str, Any] | None, sink: RecordingSink) -> tuple[CalibrationNode, str]:
    sensor = cfg.sensor(sid) or SensorConfig(id=sid)
    if model is not None or sensor.prior.known:
        return CalibrationNode(node_settings(sensor, cfg, model), sink), "config"
    if setup is not None:
        pipe = Pipeline.from_state_dict(json.loads(setup["pipeline_state_json"]))
        ali_cfg = setup.get("alignment_settings")
        settings = NodeSettings(sid, cfg.pipeline, pipe.model, pipe.prior, pipe.cfg.rate_hz,
                                pipe.cfg.full_scale_g,
                                AlignmentConfig(**ali_cfg) if ali_cfg else cfg.alignment,
                                rediscovery=cfg.discovery)
        ali = setup.get("alignment")
        tbd = setup.get("timebase")  # the device clock's time base as the live node began
        node = CalibrationNode(settings, sink, pipeline=pipe, start="recording",
                               alignment=Alignment.from_dict(ali) if ali else None,
                               timebase=TimebaseState.from_dict(tbd) if tbd else None)
        if isinstance(setup.get("discovery_json"), str):  # absent in older recordings
            node.discovery.resume(json.loads(setup["discovery_json"]))
        return node, "recording"
    m, prior = model_and_prior(sensor, cfg.pipeline)  # no prior known: bootstrap
    settings = NodeSettings(sid, cfg.pipeline, m, prior, sensor.rate_hz, sensor.full_scale_g,
                            cfg.alignment, rediscovery=cfg.discovery)
    return CalibrationNode(settings, sink), "bootstrap"


def replay(in_mcap: str | Path, out_mcap: str | Path, model: str | Path | None = None,
           config: ServiceConfig | str | Path | None = None, progress: bool = True, *,
           sensor_ids: list[str] | None = None, overwrite: bool = False) -> dict[str, Any]:
    """Recalibrate a recording; returns a summary dict.

    Args:
        in_mcap: a finished recording (its rotated parts are read too). A crashed one must be
            repaired first (``recal.io.repair.repair``).
        out_mcap: the new recording (an existing file is an error unless ``overwrite``).
        model: a model file for every sensor (see ``recal.config.model_prior.load_model_file``).
        config: a ServiceConfig or TOML path: per-sensor priors, rates, pipeline settings.
        progress: show a tqdm progress bar (in raw messages) on stderr.
        sensor_ids: only these sensors (default: all with a raw topic).
    Returns ``{"in", "out", "seconds", "samples", "samples_per_s", "samples_not_calibrated",
    "sensors": {id: {...}}}`` with per sensor the start (config | recording | bootstrap), rate,
    sample and update counts, the samples published per status (``samples_by_status``), how
    many with a status other than calibrated (``samples_not_calibrated``, as `recal export`
    counts it) and how many were not finite (published zeroed, ``samples_not_finite``), and
    the final parameters.
    """
    from tqdm import tqdm

    cfg = config if isinstance(config, ServiceConfig) else load_config(config)
    if model is not None:
        load_model_file(model)  # a bad model file fails now, before any output exists
    rec.refuse_input_as_output(out_mcap, in_mcap)
    # a device file streams its samples as arrivals; anything else is read as MCAP
    device = open_recording(in_mcap) if recording_kind(in_mcap) == "device" else None
    if device is not None and "gap_doubt_s" not in cfg.pipeline.options:
        # one device recorded every sample of its file: a gap is the device asleep (idle
        # sleep is declared stillness) or off, never another sensor come back; a sensor that
        # changed meanwhile still meets the self-watch at its first still window
        cfg = replace(cfg, pipeline=replace(cfg.pipeline,
                                            options={**cfg.pipeline.options, "gap_doubt_s": 0.0}))
    paths = rec.recording_parts(in_mcap) if device is None else []
    setups = _setups(paths)
    reopens = _reopens(paths)
    t0 = time.perf_counter()
    runs: dict[str, _SensorRun] = {}
    # Big chunks, compressed on a thread beside the calibration: a replay can be redone, so
    # it needs no crash-sized chunks or fsyncs; chunks end by size alone, never by the wall
    # clock, so the same input gives the same bytes.
    writer = RecordingWriter(out_mcap, chunk_size=1024 * 1024, background_flush=False,
                             flush_interval_s=FILE_TO_FILE_FLUSH_S, fsync=False,
                             overwrite=overwrite, background_compression=True,
                             metadata={"replay_of": str(Path(in_mcap).name),
                                       **(string_metadata(device) if device else {})})
    sink = _JoiningSink(writer)
    bar = tqdm(total=_raw_message_count(paths) if device is None else len(device.device or ()),
               unit="msg" if device is None else "sample", unit_scale=device is not None,
               desc="replay", disable=not progress, leave=False)
    try:
        messages = rec.iter_raw_logged(paths) if device is None else _device_messages(device)
        for sid, batch, logged, found in messages:
            bar.update(1 if device is None else len(batch))
            if sensor_ids is not None and sid not in sensor_ids:
                continue
            run = runs.get(sid)
            if run is None:
                node, start = _node_for(sid, cfg, model, setups.get(sid), sink)
                run = runs[sid] = _SensorRun(node, sink, extra={"start": start},
                                             reopens_ns=reopens.get(sid, []))
            # the raw topic is logged again in the compact form, the message at once with its
            # arrivals (the same values; an older recording's float64 batches get joined and
            # shrunk like a live log's)
            writer.log_raw(sid, batch, logged.log_time_ns, found)
            for piece, log_ns in _arrivals(batch, logged, found):
                run.add(piece, log_ns)  # several per pipeline step, output per arrival
                run.batches += 1
                run.last_log_ns = log_ns
            run.samples += len(batch)
        for run in runs.values():
            run.drain()
            run.node.flush(run.last_log_ns)
            sink.flush()
    finally:
        bar.close()
        writer.close()
    seconds = time.perf_counter() - t0
    total = sum(r.samples for r in runs.values())
    out = {"in": str(in_mcap), "out": str(writer.paths[0]), "seconds": seconds,
           "samples": total, "samples_per_s": total / seconds if seconds > 0 else None,
           "samples_not_calibrated": sum(r.node.samples_not_calibrated for r in runs.values()),
           "sensors": {sid: _sensor_summary(r) for sid, r in runs.items()}}
    if device is not None:
        out.update(device=device.metadata, device_notes=device.notes)
    return out


#: samples per arrival of a device file's replay (the size `recal import` writes messages of)
DEVICE_ARRIVAL_SAMPLES = 1000


class _DeviceMessage(NamedTuple):
    log_time_ns: int


def _device_messages(src: Source) -> Iterator[tuple[str, RawBatch, _DeviceMessage, None]]:
    """A device file's samples as arrivals of DEVICE_ARRIVAL_SAMPLES, each logged at its first
    sample's time (as `recal import` writes them)."""
    for batch in src.batches():
        for i in range(0, len(batch), DEVICE_ARRIVAL_SAMPLES):
            piece = batch[i:i + DEVICE_ARRIVAL_SAMPLES]
            yield src.sensor_id, piece, _DeviceMessage(int(piece.t_us[0]) * 1000), None


def _sensor_summary(run: _SensorRun) -> dict[str, Any]:
    node = run.node
    out: dict[str, Any] = {**run.extra, "samples": run.samples, "batches": run.batches,
                           "rate_hz": node.rate_hz,
                           "samples_by_status": node.samples_by_status(),
                           "samples_not_calibrated": node.samples_not_calibrated,
                           "samples_not_finite": node.samples_not_finite,
                           "discoveries": list(node.discovery.runs)}
    if node.pipeline is not None:
        s = node.pipeline.summary()
        out.update({"model": model_name(node.pipeline.model), "params": s["params"],
                    "described": s["described"], "residual_rms_mg": s["residual_rms_mg"],
                    "counts": s["counts"], "bootstrapped": s["bootstrapped"],
                    "phase": s["phase"], "gain_reference": s["gain_reference"],
                    "status": s["status"], "unobserved": s["unobserved"],
                    "misfit_mg": s["misfit_mg"], "t0_us": node.pipeline.t0_us,
                    "last_update_reason": (s["last_update"] or {}).get("reason", ""),
                    "alignment": node.alignment.to_dict() if node.alignment else None})
    return out


def _why_not_calibrated(counts: dict, reason: str) -> str:
    """Why a sensor without a prior ended with no calibration: its updates were rejected
    (the data reached a fit the estimator would not take: say which gate), or it never
    covered enough orientations for one."""
    rejected = counts.get("updates_rejected", 0)
    if rejected:
        return (f"not calibrated: {rejected} updates rejected (last: {reason or 'no reason'}); "
                "give a prior with --config or --model")
    return ("not calibrated: without a prior the recording must first cover enough "
            "orientations (5 half-axes); give one with --config or --model")


def _discovery_lines(runs: list[dict], t0_us: int | None) -> list[str]:
    """One line per discovery run that changed the model, and one for the runs that did
    not."""
    lines = []
    for d in runs:
        if not d["adopted"]:
            continue
        what = ", ".join([f"added {e}" for e in d["added"]] + [f"dropped {e}" for e in
                                                               d["dropped"]])
        at = (f"{(d['t_us'] - t0_us) / 3.6e9:.2f} h in" if t0_us is not None
              else f"t_us {d['t_us']}")
        err = d["heldout_error_mg"]
        lines.append(f"    discovery {at}: {what} (held-out error {err['base']:.2f} -> "
                     f"{err['final']:.2f} mg on {d['windows']} windows)")
    kept = sum(not d["adopted"] for d in runs)
    if kept:
        lines.append(f"    discovery: {kept} more run(s) found nothing to change")
    return lines


def replay_lines(summary: dict) -> list[str]:
    """`recal replay`'s summary for a person: one block per sensor (--json has it all)."""
    sensors = summary["sensors"]
    lines = [f"replayed {summary['samples']} samples of {len(sensors)} sensor(s) in "
             f"{summary['seconds']:.2f} s ({summary['samples_per_s'] / 1e6:.2f} M samples/s) "
             f"into {summary['out']}"]
    if "device" in summary:
        lines += source_lines(Source(summary["in"], "", list, kind="device",
                                     metadata=summary["device"], notes=summary["device_notes"]))
    for sid, info in sensors.items():
        c = info["counts"]
        rms = info.get("residual_rms_mg")
        lines.append(f"  {sid}: started from {info['start']}, model {info['model']}; "
                     f"{c['quasi_static']} quasi-static samples, {c['windows']} windows, "
                     f"{c['updates']} updates ({c['updates_rejected']} rejected)"
                     + (f"; residual {rms:.2f} mg" if rms is not None else ""))
        if "samples_by_status" in info:
            lines.append(f"    {status_line(info)}"
                         + (f"; {info['samples_not_finite']} not finite, published zeroed"
                            if info.get("samples_not_finite") else ""))
        if not info["bootstrapped"]:
            lines.append(f"    {_why_not_calibrated(c, info.get('last_update_reason', ''))}")
            continue
        ref = info.get("gain_reference")
        if ref:
            lines.append(f"    gains against {ref['counts_per_g']:.6g} counts per g "
                         f"(from the {ref['source']}); status at the end: {info.get('status')}")
        if info.get("unobserved"):
            lines.append(f"    not observed by the data: {', '.join(info['unobserved'])} (status "
                         "held; sigma carries the prior's uncertainty on it)")
        if (info.get("misfit_mg") or 0.0) >= 0.5:
            lines.append(f"    the model misses {info['misfit_mg']:.2f} mg the data show (sigma "
                         "widened by it); `recal discover` may find the effect")
        lines += _discovery_lines(info.get("discoveries") or [], info.get("t0_us"))
        for effect, values in info["described"].items():
            lines.append(f"    {effect}: " + ", ".join(f"{k} {v:.4g}" for k, v in
                                                        values.items()))
        al = info.get("alignment")
        if al:
            moved = al.get("moved_deg")
            lines.append(f"    mounting tilt {al['tilt_deg']:.1f} deg at the reference; "
                         + (f"tilt alarm: moved {moved:.1f} deg since (limit {al['limit_deg']:g} "
                            "deg)" if moved is not None else "no slip beyond "
                            f"{al['limit_deg']:g} deg"))
    return lines
