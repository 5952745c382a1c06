"""The model's doubt while a candidate model waits: discovery found a model that may explain
more than the one in force, and it is neither adopted nor rejected yet (`PendingCandidate`).

Until then each calibrated sample is as uncertain as the two models disagree on it: the
vector difference d = a_candidate(v) - a_inforce(v) of the two corrections of the same raw
reading v (with the sample's covariates), in mg, enters the predicted error in quadrature,
sigma^2 = sigma_C^2 + misfit + |d|^2 (`doubt_mg2`). d is a vector, so the doubt is there
across gravity too, where a norm residual is blind; and it is per sample, so sigma widens
only where the models disagree: at the temperatures, supplies, times or orientations where
the candidate's extra terms correct something, not everywhere at once.

The candidate is evaluated at the parameters in force wherever the two models share a
parameter (by name, `bridged`): the estimate in force keeps moving after the discovery run,
and a candidate that extends the model by one effect then differs from it by that effect's
correction alone, at its own fitted values. A parameter the candidate lacks is simply not in
its correction (a candidate without an effect the model in force has).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from recal.core.effects import Covariates
from recal.core.model import SensorModel

__all__ = ["PendingCandidate", "bridged", "doubt_mg2"]


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


def bridged(pending: PendingCandidate, model: SensorModel, p: np.ndarray) -> np.ndarray:
    """The candidate's parameters with those it shares with the model in force (by name)
    taken from the parameters in force p (module doc)."""
    q = pending.p.copy()
    mine = {n: i for i, n in enumerate(model.names)}
    for j, name in enumerate(pending.model.names):
        i = mine.get(name)
        if i is not None:
            q[j] = p[i]
    return q


def doubt_mg2(pending: PendingCandidate, q: np.ndarray, v: np.ndarray, cov: Covariates,
              a_g: np.ndarray) -> np.ndarray:
    """|d|^2 (mg^2) per sample: the candidate's correction of the raw readings v (N, 3) at
    parameters q (`bridged`) against the correction in force a_g (N, 3, g)."""
    d = pending.model.correct(q, v, cov) - a_g
    return 1e6 * np.einsum("ij,ij->i", d, d)
