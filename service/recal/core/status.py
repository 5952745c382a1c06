"""What a calibrated sample is worth: its status, its predicted error, and the self-watch.

Statuses (one per sample, `Status`; the numbers are the wire values of ``recal.Status``):

* ``uncalibrated`` (1): no estimate at all and nothing collected toward one (no prior, no
  quasi-static window yet); and, set by the shell, a sample whose calibrated value was not
  finite (published zeroed, `NOT_FINITE_SIGMA_MG`).
* ``bootstrapping`` (2): no estimate yet; quasi-static windows are being collected for the
  first fit. The output is the raw reading over a provisional scale.
* ``calibrated`` (3): an estimate informed by data (an accepted update in which the windows,
  not the prior, determined at least one parameter) and the self-watch has no objection.
* ``held`` (4): an estimate exists but no data informed it yet: the pre-calibration as given
  (a configured prior), or the prior again after a self-watch reset, until an accepted update
  observes a parameter.
* ``suspect`` (5): the self-watch's alarm (`Watch`): the estimator fitted an offset jump (a
  knock, or another sensor now under this id: held for JUMP_REPEAT_S), or the still windows
  contradicted the estimate beyond its uncertainty for a sustained time (a second jump
  within JUMP_REPEAT_S, or windows failing the norm gate for SUSPECT_AFTER_S) and the
  pipeline reset it: back to the prior with a buffer of the recent windows only (those since
  the first jump, or since the contradiction began), re-fitted at once; if the prior does
  not fit them either, no estimate and a bootstrap from them. It clears when the windows
  agree again (CLEAR_GOOD_WINDOWS in a row, after the alarm's hold).

Precedence: no estimate (uncalibrated, bootstrapping) before suspect before held.

0 (``not_recorded``) is the protobuf default: a recording made before statuses existed.

The predicted error (`predicted_sigma_mg`) is the 1-sigma length of the error of the
calibrated vector that the parameters' uncertainty causes: the estimate's covariance C_e
(Lötters eq. 11b) through the correction's Jacobian J = da/dp at each sample,
sigma^2 = trace(J C_e J^T). The sensor's own noise on the sample is not in it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from recal.core.buffer import WindowBuffer, Windows, cell_of
from recal.core.effects import Covariates
from recal.core.model import SensorModel
from recal.core.triaxial import norm3

__all__ = ["CLEAR_AFTER_S", "CLEAR_GOOD_WINDOWS", "JUMP_REPEAT_S", "NOT_FINITE_SIGMA_MG",
           "SUSPECT_AFTER_S", "Status", "Watch",
           "correction_jacobian", "predicted_sigma_mg", "refill", "sigma_form", "status_line"]


class Status(IntEnum):
    """Per-sample status of the calibrated output (module doc); values are the wire's."""

    NOT_RECORDED = 0
    UNCALIBRATED = 1
    BOOTSTRAPPING = 2
    CALIBRATED = 3
    HELD = 4
    SUSPECT = 5

    @property
    def label(self) -> str:
        return self.name.lower()


#: sigma of a sample published zeroed because its calibrated value was not finite: nothing
#: is known of it (a weight 1/sigma^2 of 0).
NOT_FINITE_SIGMA_MG = float("inf")

#: Two ways the still windows contradict the estimate beyond its uncertainty:
#: 1. The estimator fits an offset jump (`estimator._jump`: the newest windows each beyond 7
#:    sigma, Lötters eq. 14 over C_mu + B C_e B^T) and another within JUMP_REPEAT_S: a knock
#:    is one jump, after which the windows agree; a sensor whose gains differ too jumps again
#:    at a new posture (how soon: docs/performance.md, bench/status_watch.py). The status
#:    stays suspect that long after a first jump: until then the estimate may be a compromise
#:    between two sensors that fits the norms of the postures seen since.
JUMP_REPEAT_S = 1800.0
#: 2. The windows fail the norm gate (calibrated norm further than norm_tol_g from 1 g, or not
#:    finite), so they never reach the estimator: for SUSPECT_AFTER_S of device time, at least
#:    SUSPECT_MIN_BAD of them and at least half of the windows since the first.
SUSPECT_AFTER_S = 180.0
SUSPECT_MIN_BAD = 10
#: A contradiction ends after this many agreeing windows in a row (passing the norm gate);
#: a suspect status clears then, once its alarm's hold passed: JUMP_REPEAT_S after a first
#: jump, CLEAR_AFTER_S after a reset (the estimate is then this sensor's windows alone: long
#: enough for the wearer to show it new postures).
CLEAR_GOOD_WINDOWS = 10
CLEAR_AFTER_S = 600.0
#: Most windows the watch keeps from a contradiction, to re-fit them after a reset (bounded).
RECENT_MAX = 256


def correction_jacobian(model: SensorModel, p: np.ndarray, v: np.ndarray,
                        cov: Covariates) -> np.ndarray:
    """J = da/dp (N, 3, P) of the corrected readings a = f(v; p), by the chain rule through
    the model's stages (each stage's vector-Jacobian product with the unit rows of da/da)."""
    stages = [(e, model.slice(e)) for e in model.effects]
    xs = [np.asarray(v, np.float64)]
    for e, sl in stages:
        xs.append(e.apply(xs[-1], cov, p[sl]))
    n = len(xs[0])
    J = np.empty((n, 3, model.size))
    for j in range(3):
        g = np.zeros((n, 3))
        g[:, j] = 1.0
        for k in range(len(stages) - 1, -1, -1):
            e, sl = stages[k]
            J[:, j, sl], g_in = e.vjp(g, xs[k], cov, p[sl], k > 0)
            g = g_in if k else g
    return J


_BASIS = np.vstack([np.zeros(3), np.eye(3)])  # v = 0, then each axis
_NO_COVARIATES = Covariates(np.zeros(4), np.zeros((4, 0)))


def _quadratic_form(model: SensorModel, p: np.ndarray, cov_p: np.ndarray) -> np.ndarray:
    """Q (4, 4) with sigma^2(v) = [1, v] Q [1, v]^T, for a model whose correction is affine in
    v and reads no covariate: J(v) = G_0 + sum_k v_k G_k then, exactly."""
    J = correction_jacobian(model, p, _BASIS, _NO_COVARIATES)
    G = np.concatenate([J[:1], J[1:] - J[:1]]).reshape(4, -1)  # G_0, G_1..G_3, flattened
    # Q_mn = trace(G_m C G_n^T): the (3, P) blocks' rows against C
    C = np.kron(np.eye(3), cov_p)
    return G @ C @ G.T


def predicted_sigma_mg(model: SensorModel, p: np.ndarray, cov_p: np.ndarray, v: np.ndarray,
                       cov: Covariates, form: np.ndarray | None = None) -> np.ndarray:
    """The predicted 1-sigma error (mg) of each corrected reading: sqrt(trace(J C_e J^T)),
    J = da/dp at the sample, C_e the parameters' covariance (Lötters eq. 11b).

    ``form``: `sigma_form(model, p, cov_p)` when the caller has it (it depends only on the
    estimate); None computes it, or, for a model that reads covariates, uses the full
    per-sample Jacobian."""
    v = np.asarray(v, np.float64)
    if form is None:
        form = sigma_form(model, p, cov_p)
    with np.errstate(invalid="ignore", over="ignore"):  # a NaN reading: NaN (the shell's)
        if form is not None:
            # element by element, in a fixed order: each sample's sigma is the same bits
            # whatever batch it came in (a matrix product's rounding depends on its size);
            # a few samples (a live sensor's) as Python floats, the same operations
            q = form.tolist()
            if len(v) <= SMALL_BATCH:
                return np.array([1e3 * math.sqrt(max(_s2(q, x, y, z), 0.0))
                                 for x, y, z in v.tolist()], np.float64).reshape(-1)
            s2 = _s2(q, v[:, 0], v[:, 1], v[:, 2])
        else:
            J = correction_jacobian(model, p, v, cov)
            s2 = np.einsum("nip,nip->n", np.matmul(J, cov_p), J)
        return 1e3 * np.sqrt(np.maximum(s2, 0.0))


#: Up to this many samples `predicted_sigma_mg` works in Python floats (fewer calls).
SMALL_BATCH = 32


def _s2(q: list[list[float]], x: Any, y: Any, z: Any) -> Any:
    """[1, v] Q [1, v]^T for floats or arrays alike (the same operations in the same order)."""
    return (q[0][0] + 2.0 * (x * q[0][1] + y * q[0][2] + z * q[0][3])
            + x * x * q[1][1] + y * y * q[2][2] + z * z * q[3][3]
            + 2.0 * (x * y * q[1][2] + x * z * q[1][3] + y * z * q[2][3]))


def sigma_form(model: SensorModel, p: np.ndarray, cov_p: np.ndarray) -> np.ndarray | None:
    """`_quadratic_form` when the model's correction is affine in v without covariates
    (offsets, scales, cross-axis terms), else None (`predicted_sigma_mg` then goes sample by
    sample)."""
    # what `SensorModel.affine` accepts without divisors, asked of the stages (cheaper)
    if model.covariates or not all(e.affine and not e.divides_rows for e in model.effects):
        return None
    return _quadratic_form(model, p, cov_p)


@dataclass
class Watch:
    """The self-watch's state: is the current contradiction (if any) sustained?

    Attributes:
        onset_us: device time of the first contradicting window of the current stretch
            (None: no contradiction going on).
        n_all, n_bad: windows since the onset, and how many of them contradicted.
        good_run: agreeing windows in a row (a stretch ends at CLEAR_GOOD_WINDOWS).
        suspect: the output is marked suspect (set at a trigger, cleared when windows agree).
        triggers: how many times the watch fired (each fires a reset).
        jump_us: when the estimator last fitted a new offset jump (None: none since a reset).
        alarm_us: device time until which an alarm holds the suspect status at least.
        recent: the windows since the onset (v, aux, t_us, n, var), at most RECENT_MAX,
            whatever the norm gate said of them: a reset re-fits them.
    """

    onset_us: int | None = None
    n_all: int = 0
    n_bad: int = 0
    good_run: int = 0
    suspect: bool = False
    triggers: int = 0
    recent: list[tuple] | None = None
    jump_us: int | None = None
    alarm_us: int | None = None

    def see(self, bad: bool, window: tuple) -> str | None:
        """One window in order; returns "trigger" when the contradiction became sustained,
        "clear" when a suspect status ends, else None."""
        t_us = int(window[2])
        if bad:
            self.good_run = 0
            if self.onset_us is None:
                self.onset_us, self.n_all, self.n_bad, self.recent = t_us, 0, 0, []
        else:
            self.good_run += 1
        if self.onset_us is not None:
            self.n_all += 1
            self.n_bad += bad
            assert self.recent is not None
            self.recent.append(window)
            if len(self.recent) > RECENT_MAX:
                del self.recent[0]
            if (t_us - self.onset_us >= SUSPECT_AFTER_S * 1e6 and self.n_bad >= SUSPECT_MIN_BAD
                    and 2 * self.n_bad >= self.n_all):
                return "trigger"
        if self.good_run >= CLEAR_GOOD_WINDOWS:
            self.onset_us, self.n_all, self.n_bad, self.recent = None, 0, 0, None
            if self.suspect and (self.alarm_us is None or t_us >= self.alarm_us):
                self.suspect = False
                return "clear"
        return None

    def alarm(self, t_us: int, hold_s: float = CLEAR_AFTER_S) -> bool:
        """Suspect from device time t_us on, for hold_s at least; True if it was not."""
        was, self.suspect = self.suspect, True
        self.alarm_us = max(self.alarm_us or 0, int(t_us + hold_s * 1e6))
        return not was

    def fired(self, t_us: int) -> list[tuple]:
        """A reset at t_us: suspect from now, a new stretch; the windows to re-fit."""
        recent = self.recent or []
        self.suspect, self.alarm_us = True, int(t_us + CLEAR_AFTER_S * 1e6)  # a fresh start
        self.triggers += 1
        self.onset_us, self.n_all, self.n_bad, self.recent, self.good_run = None, 0, 0, None, 0
        self.jump_us = None
        return recent

    def jumped(self, step_us: int, now_us: int) -> str | None:
        """The estimator fitted a new offset jump at step_us (an accepted update at now_us):
        "reset" if it is a second one within JUMP_REPEAT_S of the first (another sensor under
        this id, another sensor's checkpoint: its gains differ too, so it jumps again at a new
        posture), "suspect" if the status becomes suspect now (held JUMP_REPEAT_S at least),
        else None (already suspect)."""
        first = self.jump_us
        if first is not None and step_us - first <= JUMP_REPEAT_S * 1e6:
            return "reset"
        self.jump_us = step_us
        return "suspect" if self.alarm(now_us, JUMP_REPEAT_S) else None

    def to_refit(self, buffered: Windows, now_us: int) -> list[tuple]:
        """A reset at now_us (`fired`): the windows to re-fit, each once: the contradiction's,
        and after a jump the buffer's (``buffered``) since the first jump."""
        since = self.jump_us
        recent = self.fired(now_us)
        if since is not None:
            keep = buffered.t_us >= since
            recent = [(buffered.v[i], buffered.aux[i], int(buffered.t_us[i]),
                       int(buffered.n[i]), float(buffered.var[i]))
                      for i in np.flatnonzero(keep).tolist()] + recent
            recent = list({int(r[2]): r for r in recent}.values())  # each window once
        return recent

    def to_dict(self) -> dict:
        return {"onset_us": self.onset_us, "jump_us": self.jump_us, "alarm_us": self.alarm_us,
                "n_all": self.n_all, "n_bad": self.n_bad, "good_run": self.good_run,
                "suspect": self.suspect, "triggers": self.triggers,
                "recent": None if self.recent is None else [
                    [list(map(float, w[0])), list(map(float, w[1])), int(w[2]), int(w[3]),
                     float(w[4])] for w in self.recent]}

    @classmethod
    def from_dict(cls, d: dict | None) -> Watch:
        if not d:
            return cls()
        recent = d.get("recent")
        return cls(None if d.get("onset_us") is None else int(d["onset_us"]), int(d["n_all"]),
                   int(d["n_bad"]), int(d["good_run"]), bool(d["suspect"]), int(d["triggers"]),
                   None if recent is None else [_window(w) for w in recent],
                   None if d.get("jump_us") is None else int(d["jump_us"]),
                   None if d.get("alarm_us") is None else int(d["alarm_us"]))


def _window(w: Sequence) -> tuple:
    return (list(map(float, w[0])), list(map(float, w[1])), int(w[2]), int(w[3]), float(w[4]))


def refill(buffer: WindowBuffer, n_aux: int, model: SensorModel, p: np.ndarray,
           covariates: Callable[[np.ndarray, np.ndarray], Covariates], recent: list[tuple],
           norm_tol_g: float | None, grid: int) -> int:
    """After a reset: the recent windows whose calibrated norm (parameters p) is within
    norm_tol_g of 1 g (None: all finite ones) into the buffer, each a slot of its own, oldest
    first; returns how many."""
    if not recent:
        return 0
    recent = sorted(recent, key=lambda r: r[2])
    m, k = len(recent), n_aux
    w = Windows(np.array([r[0] for r in recent], float).reshape(m, 3),
                np.array([r[1] for r in recent], float).reshape(m, k),
                np.array([r[2] for r in recent], np.int64),
                np.array([r[3] for r in recent], np.int64),
                np.array([r[4] for r in recent], float))
    a = model.correct(p, w.v, covariates(w.t_us, w.aux))
    norm = norm3(a)
    ok = np.abs(norm - 1.0) <= norm_tol_g if norm_tol_g is not None else np.isfinite(norm)
    dirs = a / np.where(norm > 0, norm, 1.0)[:, None]
    cells = cell_of(dirs, grid)
    for i in np.flatnonzero(ok).tolist():
        buffer.add(w.v[i].tolist(), w.aux[i].tolist(), int(w.t_us[i]), int(w.n[i]),
                   float(w.var[i]), dirs[i].tolist(), None, int(cells[i]))
    return int(ok.sum())


def status_line(d: dict) -> str:
    """How many samples went out with a status other than calibrated, said for a person."""
    by = d.get("samples_by_status") or {}
    others = ", ".join(f"{k} {v}" for k, v in by.items() if k not in ("calibrated",
                                                                        "not_recorded"))
    text = (f"{by.get('calibrated', 0)} samples out calibrated, {d['samples_uncalibrated']} "
            "with another status" + (f" ({others})" if others else ""))
    if d.get("samples_status_not_recorded"):
        text += (f"; {d['samples_status_not_recorded']} without a status (recorded before "
                 "statuses existed)")
    return text
