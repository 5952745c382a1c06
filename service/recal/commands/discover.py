"""What `recal discover` shows and writes: the step table, the JSON report, the figures and
the model file the daemon starts from.

The algebra is in `recal.core.discovery`; this module reads the input (MCAP raw topic, a CSV
time series, or the rows of a static table), formats the result and writes files.

JSON report (``--json``), at least::

    {"effects_selected": [{"kind", "covariate", "params": {...}, ...}],
     "heldout_error_mg": {"base", "final"}, "steps": [...]}

plus ``held_at_start`` (parameters the poses cannot determine, left at their start),
``reference``, ``values``/``sd`` (raw units) and ``observable`` per selected effect,
``axis_angles_deg`` for cross-axis, every candidate's score per step (``candidates``) and in
the round that stopped the search (``last_round``), the in-sample errors, the residual
analysis before and after, the criterion and the input. NaN (a correlation with a constant)
is written as null.

Model file (``--write-model``): ``{"model": SensorModel dict, "params": {name: value},
"prior": {"mean", "info"}, "discovery": {...}}``, read by `recal.config.model_prior.load_model_file`
(``recal run --model``, ``recal replay --model``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from recal.core import discovery as dc
from recal.core.discovery_data import DiscoveryData, data_from_batches
from recal.core.effects import TIME
from recal.core.hindsight import SUSPECT_EXCESS_G
from recal.core.model import SensorModel
from recal.core.pipeline import gain_reference
from recal.core.residuals import (
    ORIENTATION_FEATURES,
    MisfitProfile,
    ResidualAnalysis,
    orientation_features,
)
from recal.errors import RecordingError, UsageError
from recal.io.sources import Source
from recal.samples import RawBatch

__all__ = [
    "csv_has_time",
    "data_from_csv",
    "data_from_recording",
    "data_from_source",
    "format_table",
    "model_file_dict",
    "report_dict",
    "run",
    "write_plots",
]


# ---------------------------------------------------------------------------------------------
# Input
# ---------------------------------------------------------------------------------------------

def data_from_recording(path: str | Path, sensor_id: str | None = None,
                        window_s: float | None = None) -> tuple[DiscoveryData, str]:
    """Quasi-static windows of one sensor's raw topic in an MCAP recording (all its parts),
    read message by message (`core.discovery_data.data_from_batches`: bounded memory)."""
    from recal.io import recording

    parts = recording.recording_parts(path)
    found = recording.sensors(parts)
    sensor_id = recording.pick_sensor(path, found, sensor_id)
    if not any(len(b) for _, b, _ in recording.iter_raw(parts, sensor_id)):
        raise RecordingError(f"{path}: no raw samples for sensor {sensor_id!r} (sensors: "
                             f"{', '.join(found) or 'none'})")
    data = data_from_batches(lambda: (b for _, b, _ in recording.iter_raw(parts, sensor_id)),
                             window_s=window_s)
    return data, sensor_id


def data_from_source(src: Source, window_s: float | None = None,
                     progress: Callable[[int], None] | None = None) -> DiscoveryData:
    """Quasi-static windows of a CSV time series or a device file opened by
    `recal.io.sources.open_recording` (a pass at a time: bounded memory beyond the file's
    reader); progress(n) with the samples of each batch of each pass."""
    def batches() -> Iterator[RawBatch]:
        for b in src.batches():
            if progress is not None:
                progress(len(b))
            yield b

    return data_from_batches(batches, window_s=window_s)


def csv_has_time(path: str | Path) -> bool:
    """Whether a CSV's header names a time column (t_us, t_ms, t_s): a recording, not a
    static table of one still row per pose."""
    from recal.io.csv_table import TIME_COLUMNS

    with open(path, encoding="utf-8-sig") as f:
        for line in f:
            if line.strip() and not line.lstrip().startswith("#"):
                names = {h.strip().lower() for h in line.split(",")}
                return bool(names & set(TIME_COLUMNS))
    return False


def data_from_csv(path: str | Path, rate_hz: float | None = None, units: str | None = None,
                  window_s: float | None = None) -> DiscoveryData:
    """Quasi-static windows of a CSV time series (see `recal.io.csv_table.read_csv`)."""
    from recal.io.csv_table import iter_csv

    def batches() -> Iterator[RawBatch]:  # a chunk of lines at a time: bounded memory
        chunks = iter_csv(path, units=units, rate_hz=rate_hz)  # type: ignore[arg-type]
        return (t.batch for t in chunks)

    return data_from_batches(batches, window_s=window_s)


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------

def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _clean(obj: Any) -> Any:
    """NaN and inf become null (JSON has no NaN); numpy scalars become Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return _num(float(obj))
    return obj


def _effect_dict(e: dc.SelectedEffect) -> dict[str, Any]:
    d: dict[str, Any] = {"kind": e.kind, "covariate": e.covariate, "label": e.label,
                         "params": e.params, "values": e.values, "sd": e.sd,
                         "observable": e.observable}
    if e.reference is not None:
        d["reference"] = e.reference
    if e.extra:
        d["axis_angles_deg"] = e.extra
    return d


def _candidate_dict(c: dc.CandidateScore) -> dict[str, Any]:
    return {"label": c.label, "kind": c.kind, "covariate": c.covariate,
            "reference": c.reference, "n_params": c.n_params, "n_observed": c.n_observed,
            "heldout_rms_mg": c.heldout_rms_mg, "gain": c.gain, "se": c.se,
            "explained": c.explained, "passed": c.passed}


def _analysis_dict(a: ResidualAnalysis) -> dict[str, Any]:
    return {"rms_mg": a.rms_mg, "correlation": a.correlation, "orientation": a.orientation,
            "explained": a.explained}


def criterion_text(cfg: dc.DiscoveryConfig, n_blocks: int) -> str:
    return (f"add the candidate whose held-out sum of squares of |a|-1g falls by R > "
            f"max({100 * cfg.min_gain:g} %, {dc.n_se_for(cfg, n_blocks):.2f} bootstrap SE); "
            f"{n_blocks} contiguous time blocks, each predicted by a fit on the others; "
            + ("a simpler passing candidate wins unless the best beats it by the same test; "
               if cfg.prefer_simpler else "")
            + (f"if none passes alone, pairs of the top {cfg.pairs} by score test; "
               if cfg.pairs > 1 else "")
            + "an earlier effect a later one made redundant is removed by the same test")


def misfit_dict(mis: MisfitProfile | None) -> dict[str, Any] | None:
    """What a fit leaves beyond the noise (`residuals.MisfitProfile`), in mg, for the reports."""
    if mis is None:
        return None
    return {"excess_mg": 1e3 * mis.overall_g, "max_local_excess_mg": 1e3 * mis.max_excess_g,
            "noise_mg": 1e3 * mis.noise_g, "chi2": mis.chi2,
            "well_above_noise": mis.well_above_noise}


def misfit_words(d: dict[str, Any]) -> str:
    """How much a fit leaves beyond the noise, for a person (``d``: `misfit_dict`'s)."""
    return (f"leaves {d['excess_mg']:.2f} mg beyond the sensor noise ({d['noise_mg']:.2f} mg "
            f"per window, reduced chi-square {d['chi2']:.3g}; {d['max_local_excess_mg']:.2f} "
            "mg where it is worst): the model lacks an effect")


def misfit_line(mis: MisfitProfile | None, found: str) -> str | None:
    """A person's line when the residual is well above the noise (None: it is not): how
    much, and what to do next (``found``: what discover found, or what to run)."""
    d = misfit_dict(mis)
    if d is None or not d["well_above_noise"]:
        return None
    return f"the fit {misfit_words(d)}; {found}"


def _misfit_next(result: dc.DiscoveryResult) -> str:
    """What to do about a residual the final model leaves (`misfit_line`)."""
    best = max(result.last_round, key=lambda c: c.gain) if result.last_round else None
    closest = (f"; the closest, {best.label}, took {100 * best.gain:.1f} % off the held-out "
               f"error but not reliably (SE {100 * best.se:.1f} %): a longer recording, with "
               f"more postures, may show it" if best is not None and best.gain > 0 else "")
    further = "further " if result.steps else ""
    return (f"no {further}candidate passed the held-out test (an effect recal does not model, "
            f"or movement in the still windows){closest}. `recal hindsight` with this model "
            f"widens sigma by it and marks samples suspect where it exceeds "
            f"{1e3 * SUSPECT_EXCESS_G:g} mg")


def report_dict(result: dc.DiscoveryResult, source: str | None = None,
                device: dict[str, Any] | None = None) -> dict[str, Any]:
    """The JSON report (keys in the module docstring)."""
    cfg, data = result.config, result.data
    n_blocks = int(result.blocks.max()) + 1
    ref = gain_reference(result.model, result.p, from_prior=False)  # the data's own scale
    t_h = data.cov.t_h
    steps = [{"step": i + 1, "action": s.action,
              "effect": " + ".join([s.effect.label, *(e.label for e in s.together)]),
              **_effect_dict(s.effect), "together": [_effect_dict(e) for e in s.together],
              "heldout_before_mg": s.heldout_before_mg,
              "heldout_after_mg": s.heldout_after_mg, "gain": s.gain, "se": s.se,
              "candidates": [_candidate_dict(c) for c in s.candidates]}
             for i, s in enumerate(result.steps)]
    mis = result.misfit()
    report = {
        "source": source,
        **({"device": device} if device else {}),
        "misfit": misfit_dict(mis),
        "held_at_start": list(result.held_at_start()),
        "input": {"kind": data.source, "windows": len(data), "dropped_moving": data.dropped,
                  "aux_names": list(data.aux_names), "s0": data.s0,
                  "zero_g": [float(x) for x in data.zero],
                  "span_h": float(np.ptp(t_h)) if data.has_time and len(t_h) else None,
                  "blocks": int(result.blocks.max()) + 1},
        "criterion": {"text": criterion_text(cfg, n_blocks), "min_gain": cfg.min_gain,
                      "n_se": dc.n_se_for(cfg, n_blocks),
                      "prefer_simpler": cfg.prefer_simpler, "pairs": cfg.pairs,
                      "blocks": cfg.blocks, "bootstrap": cfg.bootstrap,
                      "seed": cfg.seed},
        "effects_selected": [_effect_dict(e) for e in result.selected],
        "heldout_error_mg": {"base": result.heldout_base_mg, "final": result.heldout_final_mg},
        "fit_error_mg": {"base": result.fit_base_mg, "final": result.fit_final_mg},
        "steps": steps,
        "last_round": [_candidate_dict(c) for c in result.last_round],
        "residual_analysis": {"before": _analysis_dict(result.analysis_base),
                              "after": _analysis_dict(result.analysis_final)},
        "model": {"base": result.base_model.to_dict(), "final": result.model.to_dict(),
                  "params": result.model.params_dict(result.p),
                  "gain_reference": ref,
                  "described": result.model.describe(result.p, ref["counts_per_g"])},
    }
    return _clean(report)


def model_file_dict(result: dc.DiscoveryResult) -> dict[str, Any]:
    """What `--write-model` writes: the extended model and the live estimator's prior. Its
    s0, the nominal sensitivity gains are reported against once it is a prior, is the gain
    reference of the discovery report (the mean fitted scale), so replay --model reports the
    gains discover did."""
    ref = gain_reference(result.model, result.p, from_prior=False)["counts_per_g"]
    return _clean({
        "model": {**result.model.to_dict(), "s0": ref},
        "params": result.model.params_dict(result.p),
        "sd": result.model.params_dict(result.prior.sd),
        "prior": result.prior.to_dict(),
        "discovery": {"effects_selected": [e.label for e in result.selected],
                      "heldout_error_mg": {"base": result.heldout_base_mg,
                                           "final": result.heldout_final_mg}}})


def _short(params: dict[str, float], limit: int = 4) -> str:
    items = list(params.items())[:limit]
    return ", ".join(f"{k} {v:.3g}" for k, v in items)


def format_table(result: dc.DiscoveryResult) -> str:
    """The steps as a table: effect, its parameters, held-out error before -> after."""
    data = result.data
    head = (f"{len(data)} {'rows' if data.source == 'table' else 'quasi-static windows'}"
            + (f" ({data.dropped} moving windows dropped)" if data.dropped else "")
            + f", {int(result.blocks.max()) + 1} held-out blocks")
    rows = [head, f"{'step':>4}  {'action':<7} {'effect':<32} {'held-out mg':>16}  "
                  f"{'R (SE)':>14}  params"]
    rows.append(f"{0:>4}  {'base':<7} {'+'.join(e.label for e in result.base_model.effects):<32}"
                f" {result.heldout_base_mg:>16.3f}")
    for i, s in enumerate(result.steps, 1):
        change = f"{s.heldout_before_mg:.3f} -> {s.heldout_after_mg:.3f}"
        label = " + ".join([s.effect.label, *(e.label for e in s.together)])
        rows.append(f"{i:>4}  {s.action:<7} {label:<32} {change:>16}  "
                    f"{100 * s.gain:>6.1f}% ({100 * s.se:.1f})  {_short(s.effect.params)}")
    if result.last_round:
        best = max(result.last_round, key=lambda c: c.gain)
        k = dc.n_se_for(result.config, int(result.blocks.max()) + 1)
        rows.append(f"stop: no candidate passes; best {best.label}: R {100 * best.gain:.1f} % "
                    f"(SE {100 * best.se:.1f} %; needs > {100 * result.config.min_gain:g} % "
                    f"and > {k:.2f} SE)")
    rows.append(f"held-out error: {result.heldout_base_mg:.3f} mg -> "
                f"{result.heldout_final_mg:.3f} mg; in-sample {result.fit_base_mg:.3f} -> "
                f"{result.fit_final_mg:.3f} mg")
    held = result.held_at_start()
    if held:
        rows.append(f"held at their start, the poses cannot determine them: {', '.join(held)}")
    line = misfit_line(result.misfit(), _misfit_next(result))
    if line:
        rows.append(line)
    for e in result.selected:
        unseen = [k for k, v in e.observable.items() if not v]
        rows.append(f"  {e.label}: {_short(e.params, 6)}"
                    + (f" (not observed: {', '.join(unseen)})" if unseen else ""))
        if e.extra:
            rows.append("    angles between sensing axes: "
                        + ", ".join(f"{k} {v:.3f}" for k, v in e.extra.items()))
    return "\n".join(rows)


# ---------------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------------

def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise UsageError("--plots needs matplotlib: pip install 'recal[plots]'") from None
    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt

    return plt


def _covariate_axis(result: dc.DiscoveryResult) -> list[tuple[str, np.ndarray]]:
    """What to plot the residual against: each chosen covariate; for orientation effects the
    orientation feature the residual correlated with most; else the channel it did."""
    data = result.data
    out: list[tuple[str, np.ndarray]] = []
    for e in result.selected:
        for ch in ([e.covariate] if e.covariate else []) + ([e.reference] if e.reference else []):
            label = "time (h)" if ch == TIME else ch
            if label not in [n for n, _ in out]:
                out.append((label, data.cov.get(ch)))
    if any(e.covariate is None for e in result.selected) or not out:
        a = result.corrected(final=False)
        feats = orientation_features(a)
        corr = result.analysis_base.orientation
        name = max(corr, key=lambda k: abs(corr[k]) if math.isfinite(corr[k]) else -1)
        out.append((f"gravity direction u_{name}", feats[:, ORIENTATION_FEATURES.index(name)]))
    return out


def write_plots(result: dc.DiscoveryResult, out_dir: str | Path) -> list[Path]:
    """PNG figures: held-out residual against the chosen covariate(s) before and after, the
    residual over time, and the orientation coverage. Returns the files written."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = result.data
    before, after = 1e3 * result.heldout_xi_base, 1e3 * result.heldout_xi_final
    written = []

    axes_list = _covariate_axis(result)
    fig, axs = plt.subplots(1, len(axes_list), figsize=(5.5 * len(axes_list), 4), squeeze=False)
    for ax, (name, x) in zip(axs[0], axes_list, strict=True):
        ax.scatter(x, before, s=8, alpha=0.6, label=f"before ({result.heldout_base_mg:.2f} mg)")
        ax.scatter(x, after, s=8, alpha=0.6, label=f"after ({result.heldout_final_mg:.2f} mg)")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(name)
        ax.set_ylabel("held-out |a| - 1 g (mg)")
        ax.legend(fontsize=8)
    fig.suptitle("residual against the chosen covariate: "
                 + (", ".join(e.label for e in result.selected) or "nothing selected"))
    fig.tight_layout()
    written.append(out / "residual_vs_covariate.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 3.5))
    x = data.cov.t_h if data.has_time else np.arange(len(data))
    ax.plot(x, before, ".", ms=3, label="before")
    ax.plot(x, after, ".", ms=3, label="after")
    blocks = result.blocks
    for k in range(1, int(blocks.max()) + 1):  # where the held-out blocks change
        ax.axvline(float(np.min(x[blocks == k])), color="0.8", lw=0.5)
    ax.set_xlabel("time (h)" if data.has_time else "row")
    ax.set_ylabel("held-out |a| - 1 g (mg)")
    ax.legend(fontsize=8)
    ax.set_title("residual over time (grey lines: held-out block boundaries)")
    fig.tight_layout()
    written.append(out / "residual_over_time.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    a = result.corrected()
    u = a / np.linalg.norm(a, axis=1, keepdims=True)
    fig, axs = plt.subplots(1, 3, figsize=(13, 4.4), layout="constrained")
    circle = np.linspace(0, 2 * np.pi, 200)
    for ax, (i, j) in zip(axs, ((0, 1), (0, 2), (1, 2)), strict=True):
        ax.plot(np.cos(circle), np.sin(circle), color="0.7", lw=0.5)
        sc = ax.scatter(u[:, i], u[:, j], c=after, s=10, cmap="coolwarm",
                        vmin=-np.max(np.abs(after)), vmax=np.max(np.abs(after)))
        ax.set_xlabel(f"u_{'xyz'[i]}")
        ax.set_ylabel(f"u_{'xyz'[j]}")
        ax.set_aspect("equal")
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-1.05, 1.05)
    fig.colorbar(sc, ax=axs, label="held-out residual after (mg)", shrink=0.8)
    fig.suptitle(f"orientation coverage: gravity direction of {len(data)} windows")
    written.append(out / "orientation_coverage.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)
    return written


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------

def run(data: DiscoveryData, *, model: SensorModel | None = None,
        p: np.ndarray | None = None, cfg: dc.DiscoveryConfig | None = None,
        json_path: str | Path | None = None, plots_dir: str | Path | None = None,
        model_path: str | Path | None = None, source: str | None = None,
        device: dict[str, Any] | None = None,
        out: Callable[[str], None] = print) -> dc.DiscoveryResult:
    """Discover, print the table, write what was asked for."""
    if plots_dir is not None:
        _pyplot()  # fail before the work if matplotlib is missing
    result = dc.discover(data, model, p, cfg or dc.DiscoveryConfig())
    out(format_table(result))
    if json_path is not None:
        Path(json_path).write_text(json.dumps(report_dict(result, source, device), indent=2,
                                                default=str))
        out(f"wrote {json_path}")
    if model_path is not None:
        Path(model_path).write_text(json.dumps(model_file_dict(result), indent=2))
        out(f"wrote {model_path} (model {'+'.join(e.label for e in result.model.effects)})")
    if plots_dir is not None:
        for f in write_plots(result, plots_dir):
            out(f"wrote {f}")
    return result
