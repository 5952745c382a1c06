"""Run one batch calibration tool on one case, inside that tool's own virtual environment.

Started by bench/compare_tools.py as ``<tool venv>/bin/python compare_tools_runner.py TOOL CASE
[--out OUT.npy]``. It needs only numpy and the tool (never recal, which is not installed there).

CASE is a directory with ``v_g.npy`` (N,3 float64 readings in g, the same array every tool and the
recal core get), ``t_us.npy`` (N int64 Unix time stamps in microseconds) and ``meta.json``
(``rate_hz``). Converting the arrays into the tool's input type (pandas DataFrame, polars series)
and the tool's output back into an (N,3) array are not timed; only the calibration call is.
One JSON line goes to stdout:

    {"tool", "version", "seconds", "status": "calibrated" | "refused", "reason", "params"}

A tool that refuses returns its input unchanged (actipy does, wristpy's pipeline does with
``return_input_on_error``), so the saved output is then the uncalibrated readings.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import warnings
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

import numpy as np

#: The shortest recording skdh and wristpy's GGIR calibrator accept (their default is 72 h,
#: which refuses a 24 h recording outright); both round to 12 h blocks.
MIN_HOURS = 12

#: what a tool's call returns: its calibrated output as an (N,3) array in g (a function, run
#: after the timer stops), status, reason, parameters
Result = tuple[Callable[[], np.ndarray], str, str, dict]


def _actipy_reason(info: dict) -> str:
    """Why calibrate_gravity kept the input (it only sets CalibOK = 0)."""
    if info.get("CalibNumSamples", 0) < 50:  # its calib_min_samples default
        return f"only {info.get('CalibNumSamples')} still windows"
    if info.get("CalibNumIters") == 0:  # returned before iterating: the cube criterion
        return "sphere not covered beyond +-0.3 g on every axis"
    return "fit error stayed above 10 mg"


def _actipy(v: np.ndarray, t_us: np.ndarray, rate_hz: float) -> tuple[Callable[[], Result], str]:
    import pandas as pd
    from actipy.processing import calibrate_gravity

    frame = pd.DataFrame(v, columns=["x", "y", "z"],
                         index=pd.DatetimeIndex(pd.to_datetime(t_us, unit="us"), name="time"))

    def call() -> Result:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out, info = calibrate_gravity(frame, calib_cube=0.3)
        ok = bool(info.get("CalibOK", 0))
        reason = _actipy_reason(info) if not ok else ""
        params = {k: (float(x) if isinstance(x, int | float | np.floating) else str(x))
                  for k, x in info.items()}
        return (lambda: out[["x", "y", "z"]].to_numpy(np.float64),
                "calibrated" if ok else "refused", reason, params)

    return call, metadata.version("actipy")


def _skdh(v: np.ndarray, t_us: np.ndarray, rate_hz: float) -> tuple[Callable[[], Result], str]:
    from skdh.preprocessing import CalibrateAccelerometer

    t_s = t_us / 1e6
    accel = v.copy()  # its own copy (the call is made once), so `v` stays the input

    def call() -> Result:
        cal = CalibrateAccelerometer(min_hours=MIN_HOURS)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = cal.predict(time=t_s, accel=accel, fs=rate_hz)
        msgs = [str(w.message) for w in caught
                if "No Calibration" in str(w.message) or "not done" in str(w.message)]
        if msgs or "offset" not in res:
            return lambda: v, "refused", (msgs or ["no result"])[0], {}
        return (lambda: np.asarray(res["accel"], np.float64), "calibrated", "",
                {"offset_g": np.asarray(res["offset"]).tolist(),
                 "scale": np.asarray(res["scale"]).tolist()})

    return call, metadata.version("scikit-digital-health")


def _wristpy(which: str) -> Callable[..., tuple[Callable[[], Result], str]]:
    def make(v: np.ndarray, t_us: np.ndarray,
             rate_hz: float) -> tuple[Callable[[], Result], str]:
        import polars as pl
        from wristpy.core import exceptions, models
        from wristpy.processing import calibration

        logging.disable(logging.CRITICAL)  # wristpy logs every refusal as an error
        accel = models.Measurement(measurements=v,
                                   time=pl.Series("time", t_us).cast(pl.Datetime("us")))
        refusals = (exceptions.CalibrationError, exceptions.SphereCriteriaError,
                    exceptions.NoMotionError)

        def call() -> Result:
            if which == "ggir":
                cal = calibration.GgirCalibration(min_calibration_hours=MIN_HOURS)
            else:
                cal = calibration.ConstrainedMinimizationCalibration()
            try:
                out = cal.run_calibration(accel)
            except refusals as exc:
                return lambda: v, "refused", f"{type(exc).__name__}: {exc}", {}
            return lambda: np.asarray(out.measurements, np.float64), "calibrated", "", {}

        return call, metadata.version("wristpy")

    return make


TOOLS: dict[str, Callable[..., tuple[Callable[[], Result], str]]] = {
    "actipy": _actipy,
    "skdh": _skdh,
    "wristpy-gradient": _wristpy("gradient"),
    "wristpy-ggir": _wristpy("ggir"),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tool", choices=sorted(TOOLS))
    ap.add_argument("case", type=Path)
    ap.add_argument("--out", type=Path, help="save the calibrated (N,3) array here")
    a = ap.parse_args(argv)
    v = np.load(a.case / "v_g.npy")
    t_us = np.load(a.case / "t_us.npy")
    rate_hz = float(json.loads((a.case / "meta.json").read_text())["rate_hz"])
    call, version = TOOLS[a.tool](v, t_us, rate_hz)
    t0 = time.perf_counter()
    out, status, reason, params = call()
    seconds = time.perf_counter() - t0
    if a.out is not None:
        np.save(a.out, np.ascontiguousarray(out(), np.float64))
    print(json.dumps({"tool": a.tool, "version": version, "seconds": seconds, "status": status,
                      "reason": reason, "params": params}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
