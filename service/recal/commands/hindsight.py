"""`recal hindsight`: calibrate a recording on disk with hindsight (`core.hindsight`).

Three passes over the input, one batch at a time (a week-long file needs memory for its
windows, about 100 bytes each, not for its samples):

1. the sample rate and the median norm (the detector's first scale and the model's nominal
   sensitivity unless a model file gives one), from counts (`discovery_data.rate_and_scale`);
2. the quasi-static windows, and one fit of the model on all of them (when the windows show
   zero-g far from 0 or another scale, as an analog part on an unsigned ADC does, the windows
   once more by a detector centred there: `hindsight.calibrate`); without a model given, the
   effects first selected on those windows as `recal discover` selects them
   (`hindsight.discover_and_calibrate`), reported with the held-out error before and after;
3. every sample corrected with that fit and written out: an MCAP gets the raw topic copied as
   logged, a calibrated topic (with the detector's gate and output per sample, as the live
   node writes them) and the fit as a calibration message; a CSV gets t_us, x_g, y_g, z_g.
   Without an output file (``out=None``: the calibration alone, `recal hindsight --json`)
   this pass is not made.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from recal.commands.discover import misfit_dict, misfit_words, step_in_time_dict
from recal.commands.span_windows import span_windows
from recal.core import detector as det
from recal.core import hindsight
from recal.core.channels import usable
from recal.core.discovery import DiscoveryResult
from recal.core.discovery_data import rate_and_scale
from recal.core.effects import Covariates
from recal.core.model import SensorModel
from recal.core.pipeline import gain_reference
from recal.core.pipeline_config import PipelineConfig
from recal.core.status import UNPINNED_MG, Status, predicted_sigma_mg, sigma_form, unsettled
from recal.io.sources import Source, source_lines, string_metadata
from recal.samples import CalibratedBatch, RawBatch, batch_groups, rebatch

__all__ = ["Corrected", "Fitted", "calibrate_file", "fit_recording", "summary_lines"]


@dataclass(frozen=True)
class Fitted:
    """Passes 1 and 2 of a recording: the fit, what discovery chose (None: the model was
    given; a string: why it could not run), the settings the windows were found with, and
    the samples the windows were found in."""

    fit: hindsight.HindsightFit
    found: DiscoveryResult | str | None
    cfg: PipelineConfig
    rate_hz: float
    seconds: float
    samples: int = 0


def fit_recording(src: Source, model: SensorModel | None = None,
                  progress: Callable[[int], None] | None = None, threads: int = 1) -> Fitted:
    """Passes 1 and 2: the rate and scale, the quasi-static windows and one fit of ``model``
    on them; without a model, the one `recal discover`'s selection finds on the same windows
    (from offsets and gains in the input's units). Writes nothing.
    progress(n): called with the samples of each batch of each pass. threads: a device
    file's windows on that many threads (`span_windows`: the same windows)."""
    t0 = time.perf_counter()
    rate_hz, median_norm = _rate_and_scale(src, progress)
    cfg = PipelineConfig(rate_hz=rate_hz)

    read = [0]  # samples of the last pass over the input

    def count(n: int) -> None:
        read[0] += n
        if progress is not None:
            progress(n)

    def batches() -> Iterator[RawBatch]:
        read[0] = 0
        return _counted(src.batches(), count)

    windows_of = None
    if src.device is not None:  # in memory: in spans (on threads, or one: the same windows)
        spans = span_windows(src.device, threads, count)

        def windows_of(*args: Any) -> Any:
            read[0] = 0
            return spans(*args)

    found: DiscoveryResult | str | None = None
    # one BLAS thread: the fits solve hundreds of small least-squares problems, for which
    # OpenBLAS's threads cost more CPU (and here wall) time than they save
    with threadpool_limits(1, user_api="blas"), ThreadPoolExecutor(1) as pool:
        if model is None:
            # with threads, offsets and gains are fitted while discovery selects
            beside = ((lambda work: pool.submit(work).result) if threads > 1 else None)
            fit, found = hindsight.discover_and_calibrate(
                batches, median_norm, cfg, windows_of=windows_of, beside=beside)
        else:
            fit = hindsight.calibrate(batches, model, cfg, windows_of=windows_of)
    return Fitted(fit, found, cfg, rate_hz, time.perf_counter() - t0, read[0])


def calibrate_file(src: Source, out: str | Path | None, model: SensorModel | None = None,
                   overwrite: bool = False, progress: Callable[[int], None] | None = None,
                   fitted: Fitted | None = None, threads: int = 1) -> dict[str, Any]:
    """Fit ``model`` to the source with hindsight (`fit_recording`; or take ``fitted``, its
    result on this source) and write every sample corrected into ``out`` (None: the
    calibration alone, no third pass). Returns the summary (`summary_lines`). threads: as
    `fit_recording`'s."""
    t0 = time.perf_counter()
    if fitted is None:
        fitted = fit_recording(src, model, progress, threads)
    corrected = Corrected(fitted.fit, fitted.cfg)
    if out is None:
        samples = fitted.samples
    elif Path(out).suffix.lower() == ".csv":
        samples = _write_csv(src, corrected, out, progress)
    else:
        samples = _write_mcap(src, corrected, out, overwrite, progress)
    seconds = time.perf_counter() - t0
    return {"in": src.name, "out": None if out is None else str(out),
            "sensor_id": src.sensor_id, "samples": samples,
            "seconds": seconds, "samples_per_s": samples / seconds if seconds > 0 else None,
            "rate_hz": fitted.rate_hz, **fit_summary(fitted.fit),
            "discovery": discovery_summary(fitted.found),
            # pass 3 marks them: unknown when it is not made
            "samples_suspect": corrected.samples_suspect if out is not None else None,
            **({"device": src.metadata, "device_notes": src.notes} if src.device else {})}


def discovery_summary(found: DiscoveryResult | str | None) -> dict[str, Any] | None:
    """What discovery chose (None: the model was given): the effects found with their
    values, held-out error before -> after (mg), the steps, a step in time that stopped it;
    or why it could not run (``skipped``)."""
    if found is None:
        return None
    if isinstance(found, str):
        return {"skipped": found, "effects_found": []}
    return {"effects_found": [{"label": e.label, "kind": e.kind, "covariate": e.covariate,
                               "params": e.params} for e in found.selected],
            "heldout_error_mg": {"base": found.heldout_base_mg, "final": found.heldout_final_mg},
            "steps": [{"action": s.action,
                       "effect": " + ".join([s.effect.label, *(e.label for e in s.together)]),
                       "heldout_before_mg": s.heldout_before_mg,
                       "heldout_after_mg": s.heldout_after_mg, "gain": s.gain, "se": s.se}
                      for s in found.steps],
            "step_in_time": step_in_time_dict(found), "windows": len(found.data)}


def _discovery_lines(d: dict[str, Any] | None) -> list[str]:
    if d is None:
        return []
    if "skipped" in d:
        return [f"  no effect discovery ({d['skipped']}): offsets and gains"]
    err = d["heldout_error_mg"]
    found = ", ".join(e["label"] for e in d["effects_found"])
    lines = [f"  discovered on {d['windows']} windows as `recal discover`: "
             + (f"{found} (held-out error {err['base']:.3f} -> {err['final']:.3f} mg)" if found
                else f"nothing beyond offsets and gains (held-out error {err['base']:.3f} mg)")]
    st = d.get("step_in_time")
    if st is not None:
        lines.append(f"  a step in time at {st['t_h']:.2f} h explains the residual as well as "
                     f"{st['instead_of']}: a sensor swapped, knocked or re-mounted? not "
                     "taken for an effect")
    return lines


def _rate_and_scale(src: Source, progress: Callable[[int], None] | None
                    ) -> tuple[float, float]:
    """The rate and the nominal scale (raw units per g) the fit starts from: a device file's
    reader measured the rate between its block stamps (1 / the median step of interpolated
    stamps is off by their microsecond rounding) and gives g, so its scale is 1 (a recording
    that holds no pose twice keeps its gains there, not at a moving wearer's median norm);
    else both from counts in one pass."""
    if src.device is not None:
        return src.device.rate_hz, 1.0
    return rate_and_scale(_counted(src.batches(), progress))


def fit_summary(fit: hindsight.HindsightFit) -> dict[str, Any]:
    """The fit as JSON-able values: parameters by name and in physical units, their sd."""
    sd = np.sqrt(np.clip(np.diag(fit.cov), 0, None))
    ref = gain_reference(fit.model, fit.p, from_prior=False)  # no prior: the data's own scale
    return {"model": fit.model.to_dict(), "params": fit.model.params_dict(fit.p),
            "gain_reference": ref,
            "described": fit.model.describe(fit.p, ref["counts_per_g"]),
            "sd": dict(zip(fit.model.names, sd.tolist(), strict=True)),
            "held": list(fit.held), "unsettled": list(unsettled(fit.model, fit.cov)),
            "windows": fit.windows, "windows_dropped": fit.dropped,
            "residual_rms_mg": fit.residual_rms_mg, "misfit": misfit_dict(fit.misfit)}


def summary_lines(s: dict[str, Any]) -> list[str]:
    """`recal hindsight`'s report for a person (--json has it all)."""
    into = (f"into {s['out']}" if s.get("out") is not None
            else "(the calibration alone: no samples written)")
    lines = [f"{'calibrated' if s.get('out') is not None else 'fitted'} {s['samples']} samples "
             f"of {s['sensor_id']} with hindsight in {s['seconds']:.2f} s {into}: one fit on "
             f"{s['windows']} quasi-static windows ({s['windows_dropped']} dropped as "
             f"movement), residual {s['residual_rms_mg']:.2f} mg"]
    if "device" in s:
        lines += source_lines(Source(s["in"], s["sensor_id"], list, kind="device",
                                     metadata=s["device"], notes=s["device_notes"]))
    lines += _discovery_lines(s.get("discovery"))
    for effect, values in s["described"].items():
        lines.append(f"  {effect}: " + ", ".join(f"{k} {v:.4g}" for k, v in values.items()))
    ref = s.get("gain_reference")
    if ref is not None and "scale" in s["described"]:
        lines.append(f"  gains against {ref['counts_per_g']:.6g} raw units per g (the mean "
                     f"fitted scale: no prior)")
    if s["held"]:
        lines.append(f"  held at nominal (the recording's poses cannot determine them): "
                     f"{', '.join(s['held'])}")
    if s.get("unsettled"):
        lines.append(f"  every sample held, not calibrated: {', '.join(s['unsettled'])} known "
                     f"no better than {UNPINNED_MG:g} mg at 1 g (sigma carries it)")
    mis = s.get("misfit")
    if mis and mis["well_above_noise"]:
        suspect = s.get("samples_suspect", 0)
        where = (f"{suspect} samples where it exceeds" if suspect is not None
                 else "the samples where it exceeds")
        lines.append(
            f"  poor fit: it {misfit_words(mis)}. sigma carries it; {where} "
            f"{1e3 * hindsight.SUSPECT_EXCESS_G:g} mg are marked suspect. "
            + (f"No candidate effect explained it: `recal discover {s['in']} --json` lists "
               "how close each came" if "heldout_error_mg" in (s.get("discovery") or {}) else
               f"Next: `recal hindsight {s['in']}` without --model selects effects"))
    return lines


def _counted(batches: Iterable[RawBatch], progress: Callable[[int], None] | None
             ) -> Iterator[RawBatch]:
    for b in batches:
        if progress is not None:
            progress(len(b))
        yield b


class Corrected:
    """Pass 3: each batch corrected by the fit, with the detector's gate and output (its state
    carried from batch to batch, as live), status and predicted error (`HindsightFit.sigma_mg`:
    what the model cannot explain around each sample counts; suspect where that is far above
    the noise, `HindsightFit.suspect`)."""

    def __init__(self, fit: hindsight.HindsightFit, cfg: PipelineConfig) -> None:
        self.fit = fit
        self.det_cfg = cfg.detector(fit.model.s0)
        self.state = det.init_state(self.det_cfg)
        # one fit for the whole recording: calibrated where the poses determined a parameter
        # and every offset and scale is known to UNPINNED_MG (`status.unsettled`, as live),
        # else held; the predicted error from its covariance, as the live node's
        self.status = (Status.CALIBRATED if fit.free.any() and not unsettled(fit.model, fit.cov)
                       else Status.HELD)
        self.form = sigma_form(fit.model, fit.p, fit.cov)
        self.samples_suspect = 0

    def __call__(self, b: RawBatch) -> CalibratedBatch:
        self.state, d = det.detect(self.det_cfg, self.state, b.v)
        fit = self.fit
        cov = Covariates.from_samples(b.t_us, b.aux, b.aux_names, fit.t0_us)
        sigma = fit.sigma_mg(b.t_us, predicted_sigma_mg(fit.model, fit.p, fit.cov, b.v, cov,
                                                        self.form))
        status = np.full(len(b), self.status, np.uint8)
        suspect = fit.suspect(b.t_us)
        status[suspect] = Status.SUSPECT
        self.samples_suspect += int(suspect.sum())
        # no time base here: the output keeps the device's stamps, so t_dev is t_us
        return CalibratedBatch(b.t_us, fit.correct(b), usable(d.gate, b, fit.model),
                               d.detector_g, status, sigma, t_dev=b.t_us)


def _write_csv(src: Source, corrected: Corrected, out: str | Path,
               progress: Callable[[int], None] | None) -> int:
    from recal.io.csv_table import write_calibrated_csv

    return write_calibrated_csv(out, (corrected(b) for b in
                                      rebatch(_counted(src.batches(), progress))))


def _write_mcap(src: Source, corrected: Corrected, out: str | Path, overwrite: bool,
                progress: Callable[[int], None] | None) -> int:
    from recal.io.recording_writer import FILE_TO_FILE_FLUSH_S, RecordingWriter

    fit = corrected.fit
    samples, last_ns = 0, 0
    writer = RecordingWriter(out, chunk_size=1024 * 1024, background_flush=False,
                             flush_interval_s=FILE_TO_FILE_FLUSH_S, fsync=False,
                             overwrite=overwrite, background_compression=True,
                             metadata={"hindsight_of": Path(src.name).name,
                                       **string_metadata(src)})
    try:
        if src.logged is not None:
            for group in batch_groups(src.logged()):
                # corrected and logged together: the writer joins a topic's batches into
                # messages anyway, each logged at its first batch's time
                raw = RawBatch.concat([b for b, _ in group])
                if progress is not None:
                    progress(len(raw))
                log_ns = group[0][1].log_time_ns
                writer.log_raw(src.sensor_id, raw, log_ns)
                writer.log_calibrated(src.sensor_id, corrected(raw), log_ns)
                last_ns = max(last_ns, *(m.log_time_ns for _, m in group))
                samples += len(raw)
        else:  # a CSV: logged at each chunk's first sample's time
            for chunk in rebatch(_counted(src.batches(), progress)):
                t_ns = int(chunk.t_us[0]) * 1000
                writer.log_raw(src.sensor_id, chunk, t_ns)
                writer.log_calibrated(src.sensor_id, corrected(chunk), t_ns)
                samples += len(chunk)
                last_ns = max(last_ns, t_ns)
        writer.write_calibration(src.sensor_id, {"hindsight": True, **fit_summary(fit)},
                                 last_ns)
    finally:
        writer.close()
    return samples
