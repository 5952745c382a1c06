"""Correcting a batch's samples with the parameters in force when each arrived: an update at
sample j applies from sample j on; so do the status and the predicted error it brings.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from recal.core.effects import Covariates
from recal.core.model import SensorModel
from recal.core.pending import PendingCandidate, doubt_mg2
from recal.core.sigma import floor_mg2, predicted_sigma_mg, sigma_one_mg
from recal.core.status import Status
from recal.samples import RawBatch

__all__ = ["Segment", "calibrate"]


@dataclass(frozen=True, eq=False)
class Segment:
    """From sample `index` of the batch on: the model and parameters in force, the status and
    how to predict each sample's error (`core.sigma.sigma_form`, or None: the covariance
    sample by sample)."""

    index: int
    model: SensorModel
    p: np.ndarray
    cov: np.ndarray
    form: np.ndarray | None
    status: Status
    extra_mg2: float = 0.0  # what the model cannot explain, added to sigma^2 (`status.Misfit`)
    #: ``form`` as nested lists (`status.sigma_one_mg`), made once per estimate, not per sample
    form_rows: list[list[float]] | None = None
    #: a candidate model waiting (`core.pending`): |its correction - this one's|^2 joins
    #: sigma^2 per sample
    pending: PendingCandidate | None = None
    #: W of the floor a^T W a (`misfit.unseen_cross_form`) where ``form`` is None (with a
    #: form, the form holds it: `sigma.with_floor`); None: no floor
    floor_w: np.ndarray | None = None


def calibrate(segs: list[Segment], b: RawBatch,
              covariates: Callable[[np.ndarray, np.ndarray], Covariates]
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each sample corrected with the segment in force when it arrived (segs: in index order,
    the first at 0); its status and predicted error (`status.predicted_sigma_mg`, widened by
    the misfit then) as they were then."""
    if len(b) == 1:  # one sample per arrival: the last segment is in force (all start at 0)
        return _calibrate_one(segs[-1], b, covariates)
    out = np.empty_like(b.v)
    status = np.empty(len(b), np.uint8)
    sigma = np.empty(len(b))
    cuts = [*[g.index for g in segs], len(b)]
    for s, e, g in zip(cuts[:-1], cuts[1:], segs, strict=True):
        if e > s:
            cov = covariates(b.t_us[s:e], b.aux[s:e])
            out[s:e] = g.model.correct(g.p, b.v[s:e], cov)
            status[s:e] = g.status
            sigma[s:e] = predicted_sigma_mg(g.model, g.p, g.cov, b.v[s:e], cov, g.form)
            if g.extra_mg2 > 0:
                sigma[s:e] = np.sqrt(sigma[s:e] ** 2 + g.extra_mg2)
            if g.floor_w is not None:
                sigma[s:e] = np.sqrt(sigma[s:e] ** 2 + floor_mg2(out[s:e], g.floor_w))
            if g.pending is not None:
                sigma[s:e] = _with_doubt(g, b.v[s:e], cov, out[s:e], sigma[s:e])
    return out, status, sigma


def _with_doubt(g: Segment, v: np.ndarray, cov: Covariates, a_g: np.ndarray,
                sigma_mg: np.ndarray) -> np.ndarray:
    """sigma_mg with the pending candidate's disagreement added in quadrature
    (`pending.doubt_mg2`)."""
    assert g.pending is not None
    return np.sqrt(sigma_mg ** 2 + doubt_mg2(g.pending, v, cov, a_g))


#: what a model that reads no covariate is handed for one sample (`_calibrate_one`)
_NO_COVARIATES = Covariates(np.zeros(1), np.zeros((1, 0)))


def _calibrate_one(g: Segment, b: RawBatch,
                   covariates: Callable[[np.ndarray, np.ndarray], Covariates]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`calibrate` of a one-sample batch: the same calls on the same arrays, without the
    segment bookkeeping."""
    # a model that reads no covariate (time, aux) corrects without them, and its sigma comes
    # from the form: no per-sample covariates to make then
    reads = g.form_rows is None or g.model.covariates or g.pending is not None
    cov = covariates(b.t_us, b.aux) if reads else _NO_COVARIATES
    out = g.model.correct(g.p, b.v, cov)
    if out is b.v:  # a model without stages hands the reading back: never share it
        out = out.copy()
    if g.form_rows is None or g.pending is not None:
        sigma = predicted_sigma_mg(g.model, g.p, g.cov, b.v, cov, g.form)
        if g.extra_mg2 > 0:
            sigma = np.sqrt(sigma ** 2 + g.extra_mg2)
        if g.floor_w is not None:
            sigma = np.sqrt(sigma ** 2 + floor_mg2(out, g.floor_w))
        if g.pending is not None:
            sigma = _with_doubt(g, b.v, cov, out, sigma)
        return out, np.array([g.status], np.uint8), sigma
    # predicted_sigma_mg's few-sample path on this sample's floats, and the misfit's widening
    # as Python floats: the same operations (x ** 2 of an array is x * x), so the same bits
    x, y, z = b.v[0].tolist()
    s = sigma_one_mg(g.form_rows, x, y, z)
    if g.extra_mg2 > 0:
        s = math.sqrt(s * s + g.extra_mg2)
    return out, np.array([g.status], np.uint8), np.array([s])
