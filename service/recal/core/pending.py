"""The model's doubt while a candidate model waits: discovery found a model that may explain
more than the one in force, and it is neither adopted nor rejected yet (`PendingCandidate`).

Until then each calibrated sample is as uncertain as the two models disagree on it: the
vector difference d = a_candidate(v) - a_inforce(v) of the two corrections of the same raw
reading v (with the sample's covariates), in mg, enters the predicted error in quadrature,
sigma^2 = sigma_C^2 + misfit + |d|^2 (`doubt_mg2`). d is a vector, so the doubt is there
across gravity too, where a norm residual is blind; and it is per sample, so sigma widens
only where the models disagree: at the temperatures, supplies, times or orientations where
the candidate's extra terms correct something, not everywhere at once.

Each model at its own parameters: the estimate in force keeps tracking after the run (its
offsets follow a temperature it lacks, for one), the candidate explains the same with its
fitted terms; where the two agree (at the temperature the estimate in force has caught up
with) nothing widens. Their parameters of the same name need not mean the same (an offset at
the temperature now, an offset at the candidate's reference temperature), so none is shared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from recal.core.effects import Covariates
from recal.core.model import SensorModel

__all__ = ["PendingCandidate", "doubt_mg2"]


@dataclass(frozen=True, eq=False)
class PendingCandidate:
    """A candidate model discovery proposed and nobody adopted or rejected yet.

    Attributes:
        model: the candidate's model (same s0 and raw units as the model in force).
        p: its parameters from the discovery run's fit.
        cov: their covariance (kept for the adoption that may follow; the doubt reads p).
        label: what it adds, for a person (e.g. "offset[temp_c]").
    """

    model: SensorModel
    p: np.ndarray
    cov: np.ndarray
    label: str = ""

    @classmethod
    def of_result(cls, result: Any) -> PendingCandidate | None:
        """The candidate of a discovery run (`discovery.DiscoveryResult`): its final model,
        fit and covariance; None when the run added nothing to the model it started from."""
        if not result.steps:
            return None
        return cls(result.model, np.asarray(result.p, np.float64),
                   np.asarray(result.cov, np.float64),
                   "+".join(s.effect.label for s in result.steps))

    def to_dict(self) -> dict:
        return {"model": self.model.to_dict(), "p": self.p.tolist(), "cov": self.cov.tolist(),
                "label": self.label}

    @classmethod
    def from_dict(cls, d: dict | None) -> PendingCandidate | None:
        if not d:
            return None
        return cls(SensorModel.from_dict(d["model"]), np.asarray(d["p"], np.float64),
                   np.asarray(d["cov"], np.float64), str(d.get("label", "")))


def doubt_mg2(pending: PendingCandidate, v: np.ndarray, cov: Covariates,
              a_g: np.ndarray) -> np.ndarray:
    """|d|^2 (mg^2) per sample: the candidate's correction of the raw readings v (N, 3)
    against the correction in force a_g (N, 3, g)."""
    with np.errstate(invalid="ignore", over="ignore"):
        d = pending.model.correct(pending.p, v, cov) - a_g
        d2 = 1e6 * np.einsum("ij,ij->i", d, d)
    # a sample the candidate cannot correct (a channel it reads missing there, where the
    # model in force reads none) gets no doubt from it: the candidate says nothing of it
    return np.where(np.isfinite(d2) | ~np.isfinite(a_g).all(axis=1), d2, 0.0)
