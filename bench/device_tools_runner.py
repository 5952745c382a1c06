"""Fit one calibrator on part of a device recording and correct all of it, in a process of its own.

Started by bench/device_tools.py as ``PYTHON device_tools_runner.py TOOL CASE FOLD``: actipy in
its own virtual environment (bench/.venvs/actipy, built by bench/compare_tools.py; recal is not
installed there), recal in the project's. Only numpy is imported at the top; each tool imports
its own packages.

CASE is a directory with ``v_g.npy`` (N,3 float64 readings in g, as the device file gives them),
``t_us.npy`` (N int64 time stamps), ``aux.npy`` (N,K: the file's other channels at each
sample, named in ``meta.json`` with ``rate_hz``), ``temp_c.npy`` (N float64, the device's
temperature: what actipy gets) when the file has one, and ``train_FOLD.npy`` (N bool: the
samples the tool may fit on). Every sample is corrected with that fit and saved as
``out_TOOL_FOLD.npy``. Timed: the fit and the correction of all samples (loading and saving are
not). One JSON line goes to stdout:

    {"tool", "version", "seconds", "status", "detail", "rss_before_mb", "peak_mb",
     "calibrated_fraction" (recal: the share of samples hindsight marks calibrated)}

peak_mb is the process's VmHWM (its highest resident memory: the arrays, the interpreter, the
tool's imports and its work); rss_before_mb what it held just before the timed call.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import numpy as np

from child_process import status_mb  # this directory is on sys.path: the script's own

BATCH = 100_000  # samples per RawBatch handed to recal, as a device reader yields them


def _actipy(cube_g: float) -> Callable[..., tuple[Callable[[], tuple], str]]:
    """van Hees et al. 2014 as actipy has it (with temperature when the file has it), fitted on
    the training samples; its coefficients then correct every sample
    (intercept + slope * x + slopeT * T, actipy's own formula). cube_g: its sphere criterion
    (still windows beyond +-cube_g on every axis, else it refuses); 0 turns it off."""
    return lambda *args: _actipy_call(cube_g, *args)


def _actipy_call(cube_g: float, v: np.ndarray, t_us: np.ndarray, temp: np.ndarray | None,
                 train: np.ndarray, aux: tuple[np.ndarray, tuple[str, ...]]
                 ) -> tuple[Callable[[], tuple], str]:
    import pandas as pd
    from actipy.processing import calibrate_gravity

    cols = {"x": v[train, 0], "y": v[train, 1], "z": v[train, 2]}
    if temp is not None:
        cols["temperature"] = temp[train]
    frame = pd.DataFrame(cols, index=pd.DatetimeIndex(pd.to_datetime(t_us[train], unit="us"),
                                                      name="time"))

    def call() -> tuple[np.ndarray, str, str, float | None]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, info = calibrate_gravity(frame, calib_cube=cube_g)
        if not info.get("CalibOK", 0):
            why = (f"{info.get('CalibNumSamples')} still windows, iterations "
                   f"{info.get('CalibNumIters')}, error after {info.get('CalibErrorAfter(mg)')}")
            return v, "refused (input kept)", why, None
        out = np.empty_like(v)
        for k, ax in enumerate("xyz"):
            out[:, k] = (info.get(f"Calib{ax}Intercept", 0.0)
                         + info.get(f"Calib{ax}Slope", 1.0) * v[:, k])
            if temp is not None:
                out[:, k] += info.get(f"Calib{ax}SlopeT", 0.0) * temp
        detail = ", ".join(f"{k[5:]} {float(x):.4g}" for k, x in info.items()
                           if k.startswith("Calib") and k != "CalibOK")
        return out, "calibrated", detail, None

    return call, metadata.version("actipy")


def _recal(how: str) -> Callable[..., tuple[Callable[[], tuple], str]]:
    """How recal fits, on batches of the training samples, then every sample corrected:
    "hindsight" (`recal hindsight` as it runs without --model: the effects discover's rule
    selects, one fit), "diagonal" (`recal hindsight --model` of offsets and gains alone), or
    "discover" (`recal discover`, then `recal hindsight --model` with the model file discover
    writes): the functions those commands call. A device file's values are in g: the fit starts
    at 1 raw unit per g, as the commands start it."""

    def make(v: np.ndarray, t_us: np.ndarray, temp: np.ndarray | None, train: np.ndarray,
             channels: tuple[np.ndarray, tuple[str, ...]]) -> tuple[Callable[[], tuple], str]:
        from recal.commands import discover as dr
        from recal.commands.hindsight import Corrected
        from recal.config import load_model_file
        from recal.core import discovery as dc
        from recal.core import hindsight
        from recal.core.discovery_data import data_from_batches, rate_and_scale
        from recal.core.model import SensorModel
        from recal.core.pipeline_config import PipelineConfig
        from recal.core.status import Status
        from recal.samples import RawBatch

        aux, names = channels

        def batches(mask: np.ndarray | None) -> Callable[[], list[RawBatch]]:
            idx = np.flatnonzero(mask) if mask is not None else None

            def gen() -> list[RawBatch]:
                if idx is None:
                    return [RawBatch(t_us[i:i + BATCH], v[i:i + BATCH], aux[i:i + BATCH], names)
                            for i in range(0, len(v), BATCH)]
                return [RawBatch(t_us[j], v[j], aux[j], names)
                        for j in (idx[i:i + BATCH] for i in range(0, len(idx), BATCH))]
            return gen

        fit_on, every = batches(None if train.all() else train), batches(None)

        def call() -> tuple[np.ndarray, str, str, Callable[[], float]]:
            rate, _ = rate_and_scale(fit_on())
            model = SensorModel.diagonal(1.0)
            cfg = PipelineConfig(rate_hz=rate)
            if how == "discover":
                result = dc.discover(data_from_batches(fit_on, rate_hz=rate, s0=1.0), None,
                                     None, dc.DiscoveryConfig())
                with tempfile.TemporaryDirectory() as d:  # the model file, as the CLI passes it
                    path = Path(d) / "model.json"
                    path.write_text(json.dumps(dr.model_file_dict(result)))
                    model = load_model_file(path)[0]
            if how == "hindsight":
                fit, _ = hindsight.discover_and_calibrate(fit_on, 1.0, cfg)
                model = fit.model
            else:
                fit = hindsight.calibrate(fit_on, model, cfg)
            label = "+".join(e.label for e in model.effects)
            out = np.empty_like(v)
            for i, b in zip(range(0, len(v), BATCH), every(), strict=True):
                fit.correct(b, out[i:i + len(b)])
            held = f"; held: {', '.join(fit.held)}" if fit.held else ""
            detail = (f"model {label}; {fit.windows} windows ({fit.dropped} dropped), residual "
                      f"{fit.residual_rms_mg:.2f} mg{held}")

            def calibrated_fraction() -> float:
                corr, n = Corrected(fit, cfg), 0
                for b in every():
                    n += int(np.count_nonzero(corr(b).status == Status.CALIBRATED))
                return n / len(v)

            return out, "calibrated", detail, calibrated_fraction

        return call, metadata.version("recal") if _installed("recal") else "source"

    return make


def _installed(name: str) -> bool:
    try:
        metadata.version(name)
    except metadata.PackageNotFoundError:
        return False
    return True


TOOLS = {"actipy": _actipy(0.3), "actipy-nocube": _actipy(0.0),
         "recal-diagonal": _recal("diagonal"), "recal-hindsight": _recal("hindsight"),
         "recal-discover": _recal("discover")}


def main(argv: list[str]) -> int:
    tool, case, fold = argv[0], Path(argv[1]), argv[2]
    v = np.load(case / "v_g.npy")
    t_us = np.load(case / "t_us.npy")
    temp = np.load(case / "temp_c.npy") if (case / "temp_c.npy").exists() else None
    train = np.load(case / f"train_{fold}.npy")
    names = tuple(json.loads((case / "meta.json").read_text())["aux_names"])
    call, version = TOOLS[tool](v, t_us, temp, train, (np.load(case / "aux.npy"), names))
    before = status_mb("self", "VmRSS")["VmRSS"]
    t0 = time.perf_counter()
    out, status, detail, fraction = call()
    seconds = time.perf_counter() - t0
    peak = status_mb("self", "VmHWM")["VmHWM"]
    np.save(case / f"out_{tool}_{fold}.npy", np.ascontiguousarray(out, np.float64))
    print(json.dumps({"tool": tool, "version": version, "seconds": seconds, "status": status,
                      "detail": detail, "rss_before_mb": before, "peak_mb": peak,
                      "calibrated_fraction": fraction() if fraction is not None else None}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
