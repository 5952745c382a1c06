"""What sensor-model effects may depend on, sample for sample: time and named aux channels.

A covariate is an auxiliary channel by its recording name, or `TIME` (hours since the
pipeline's origin). See `effects` for the stages that read them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recal.errors import ModelError

__all__ = ["TIME", "Covariates"]

TIME = "time"


@dataclass(frozen=True, eq=False)
class Covariates:
    """What effects may depend on, sample for sample: time in hours and named aux channels."""

    t_h: np.ndarray
    aux: np.ndarray
    aux_names: tuple[str, ...] = ()

    def get(self, name: str) -> np.ndarray:
        if name == TIME:
            return self.t_h
        try:
            return self.aux[:, self.aux_names.index(name)]
        except ValueError:
            raise ModelError(f"model needs channel {name!r}; recording has "
                             f"{self.aux_names}") from None

    def __getitem__(self, index: slice | np.ndarray) -> Covariates:
        return Covariates(self.t_h[index], self.aux[index], self.aux_names)

    @classmethod
    def from_samples(cls, t_us: np.ndarray, aux: np.ndarray, aux_names: tuple[str, ...],
                     t0_us: int = 0) -> Covariates:
        t_h = (np.asarray(t_us, np.float64) - t0_us) / 3.6e9
        return cls(t_h, np.asarray(aux, np.float64).reshape(len(t_h), -1), tuple(aux_names))
