"""The estimator's records: the pre-calibration (`Prior`, information form), the settings
(`EstimatorConfig`), the parameters and their covariance an update leaves (`Estimate`, Lötters
eq. 11b) and what an update did (`UpdateReport`). The fit that makes them is `core.estimator`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from recal.core.model import SensorModel
from recal.errors import ConfigError

__all__ = ["Estimate", "EstimatorConfig", "Prior", "UpdateReport"]


@dataclass(frozen=True, eq=False)
class Prior:
    """Prior mean p_0 and information Lambda_0 = C_0^-1 (information form)."""

    mean: np.ndarray
    info: np.ndarray

    @classmethod
    def from_sd(cls, mean: np.ndarray, sd: np.ndarray) -> Prior:
        sd = np.asarray(sd, np.float64)
        return cls(np.asarray(mean, np.float64).copy(), np.diag(1.0 / sd**2))

    @classmethod
    def default(cls, model: SensorModel, mean: np.ndarray | None = None) -> Prior:
        return cls.from_sd(model.nominal() if mean is None else mean, model.prior_sd())

    @property
    def sd(self) -> np.ndarray:
        return 1.0 / np.sqrt(np.diag(self.info))

    def to_dict(self) -> dict:
        return {"mean": self.mean.tolist(), "info": self.info.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Prior:
        return cls(np.asarray(d["mean"], np.float64), np.asarray(d["info"], np.float64))


@dataclass(frozen=True)
class EstimatorConfig:
    """Estimator settings.

    Attributes:
        mode: "all" parameters, or "offsets" only (Lötters' two modes).
        sigma_floor_g: C_mu floor: how far from 1 g a quasi-static window mean may be for
            reasons other than sensor noise (sway, slow movement), in g.
        max_iter: Gauss-Newton iterations per update.
        tol: stop when every step is below tol x its prior standard deviation.
        observable_ratio: a parameter is observed (and estimated) when the data shrink its
            standard deviation below this fraction of the prior's; 1/sqrt(2): the data inform
            it at least as much as the pre-calibration.
        min_windows: fewer windows than this and no update is attempted.
        process_scale: multiplies every effect's random-walk process noise (0 = none).
        offset_rate_sd_g_per_h: prior sd of the offsets' rate of change, g per hour (0 = the
            offsets only random-walk, and a steady drift is followed with a lag).
    """

    mode: str = "all"
    sigma_floor_g: float = 0.001
    max_iter: int = 15
    tol: float = 1e-3
    observable_ratio: float = 0.5**0.5
    min_windows: int = 4
    process_scale: float = 1.0
    offset_rate_sd_g_per_h: float = 0.02

    def __post_init__(self) -> None:
        if self.mode not in ("all", "offsets"):
            raise ConfigError(f"estimator mode must be 'all' or 'offsets', not {self.mode!r}")
        if self.offset_rate_sd_g_per_h < 0 or self.process_scale < 0:
            raise ConfigError("offset_rate_sd_g_per_h and process_scale must be >= 0")
        if not (self.sigma_floor_g > 0 and self.tol > 0 and 0 < self.observable_ratio <= 1):
            raise ConfigError("sigma_floor_g and tol must be positive, observable_ratio in (0, 1]")
        if self.max_iter < 1 or self.min_windows < 1:
            raise ConfigError("max_iter and min_windows must be at least 1")


@dataclass(frozen=True, eq=False)
class Estimate:
    """The current parameters p, their error covariance C_e (Lötters eq. 11b), the device time
    of the update that produced them (None: the pre-calibration), and the estimator's offset
    nuisances (raw units; not model parameters, see the module doc): the rate of change per
    hour, and the jump the offsets made at `step_us` (windows before it saw o - step; after
    more than one jump, the windows from `drop_us`, the first, to the latest are not used)."""

    p: np.ndarray
    cov: np.ndarray
    t_us: int | None = None
    rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    step: np.ndarray = field(default_factory=lambda: np.zeros(3))
    step_us: int | None = None
    drop_us: int | None = None

    @classmethod
    def from_prior(cls, prior: Prior) -> Estimate:
        return cls(prior.mean.copy(), np.linalg.inv(prior.info))

    def to_dict(self) -> dict:
        return {"p": self.p.tolist(), "cov": self.cov.tolist(), "t_us": self.t_us,
                "rate": np.asarray(self.rate).tolist(), "step": np.asarray(self.step).tolist(),
                "step_us": self.step_us, "drop_us": self.drop_us}

    @classmethod
    def from_dict(cls, d: dict) -> Estimate:
        def us(k: str) -> int | None:
            return None if d.get(k) is None else int(d[k])

        return cls(np.asarray(d["p"], np.float64), np.asarray(d["cov"], np.float64), us("t_us"),
                   np.asarray(d.get("rate", [0.0] * 3), float),
                   np.asarray(d.get("step", [0.0] * 3), float), us("step_us"), us("drop_us"))


@dataclass(frozen=True)
class UpdateReport:
    """What one update did, for the calibration state and the log."""

    accepted: bool
    reason: str
    n_windows: int
    iterations: int = 0
    residual_rms_before_g: float = float("nan")
    residual_rms_after_g: float = float("nan")
    condition: float = float("nan")
    observable: tuple[bool, ...] = ()
    free: tuple[bool, ...] = field(default=())

    def record(self) -> dict:
        """Every field, JSON-able (a checkpoint's "last_report"; `to_dict` is for people)."""
        return asdict(self)

    @classmethod
    def from_record(cls, d: dict) -> UpdateReport:
        return cls(**{**d, "observable": tuple(d["observable"]), "free": tuple(d["free"])})

    def to_dict(self, names: tuple[str, ...]) -> dict:
        return {"accepted": self.accepted, "reason": self.reason, "n_windows": self.n_windows,
                "iterations": self.iterations,
                "residual_rms_before_mg": 1e3 * self.residual_rms_before_g,
                "residual_rms_after_mg": 1e3 * self.residual_rms_after_g,
                "condition": self.condition,
                "observable": {n: bool(o) for n, o in zip(names, self.observable, strict=False)}}
