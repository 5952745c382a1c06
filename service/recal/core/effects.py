"""Registry of sensor-model effects: each one named stage of the correction raw -> g.

The correction is a chain of stages applied to the raw reading v (Lötters eq. 3 inverted and
extended). Each effect owns a few named parameters and knows three things: how it transforms its
input (`apply`), the derivative of its output with respect to its parameters (`d_theta`) and with
respect to its input (`d_x`). `model.SensorModel` chains them, so the Jacobian of |a| that
Lötters eq. 13a writes out for the diagonal model comes out of the chain rule for any set of
effects. An effect also says which forms of it `discover` proposes and how simple it is
(`proposed`, a `Proposals`), and the options by which `recal simulate` gives a simulated
sensor the same effect (`simulated`, `SimOption`s). A new effect is one new class here and one
entry in `EFFECT_KINDS` (and its forward-model line in `recal.sim.sensor`); discovery's
candidates (`candidates`), the core's public names and `recal simulate` read the registry.

Stages, in the order they are applied (raw unit = whatever the sensor sends, e.g. counts):

  1. ratiometric   x = v / (1 + rho (c - c_ref))          supply-scaled output (Zheng et al.)
  2. offset        x = x - o - beta (c - c_ref)           o: Lötters o_dir; beta: per covariate
  3. scale / gain  x = x / (s (1 + gamma (c - c_ref)))    s: Lötters s_dir (raw per g)
  4. cross_axis    a = M x, M unit upper-triangular        Bragge/Georgieva with the rotation fixed
  5. nonlinearity  a = a + q a^2 per axis

A covariate `c` is an auxiliary channel by its recording name, or "time" (hours). See
docs/design.md ("The core, module by module").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from recal.core.covariates import TIME, Covariates
from recal.core.effect_specs import Proposals, SimOption
from recal.core.triaxial import per_axis, per_row
from recal.errors import ConfigError

__all__ = [
    "EFFECT_KINDS",
    "TIME",
    "Covariates",
    "CrossAxis",
    "Effect",
    "Gain",
    "Nonlinearity",
    "Offset",
    "Proposals",
    "Ratiometric",
    "Scale",
    "SimOption",
    "make_effect",
    "sim_options",
]

AXES = ("x", "y", "z")
#: Random walk of the zero-g offsets, g per sqrt(hour) (see Offset.process_sd_per_sqrt_h).
OFFSET_WALK_G_PER_SQRT_H = 0.0025
#: Random walk of the sensitivities, fraction of nominal per sqrt(hour).
SCALE_WALK_PER_SQRT_H = 0.00025


def _eye(n: int) -> np.ndarray:
    return np.broadcast_to(np.eye(3), (n, 3, 3))


def _diag(d: np.ndarray) -> np.ndarray:
    """(N,3) -> (N,3,3) diagonal matrices."""
    out = np.zeros((*d.shape, 3))
    idx = np.arange(3)
    out[..., idx, idx] = d
    return out


@dataclass(frozen=True)
class Effect:
    """One stage of the correction. Subclasses implement apply, d_theta and d_x.

    Attributes:
        covariate: aux channel name, TIME, or None for effects that need none.
        ref: covariate value where the effect is zero (c_ref).
    """

    covariate: str | None = None
    ref: float = 0.0
    kind: str = field(default="", init=False)
    stage: int = field(default=0, init=False)

    # --- identity and parameters -------------------------------------------------------------
    @property
    def key(self) -> tuple[str, str | None]:
        return (self.kind, self.covariate)

    @property
    def label(self) -> str:
        return self.kind if self.covariate is None else f"{self.kind}[{self.covariate}]"

    @property
    def channels(self) -> tuple[str, ...]:
        """Every covariate the stage reads (aux channel names, or TIME)."""
        return () if self.covariate is None else (self.covariate,)

    def spec(self) -> dict:
        """What a model file stores to rebuild the stage with `make_effect`."""
        return {"kind": self.kind, "covariate": self.covariate, "ref": self.ref}

    @property
    def param_names(self) -> tuple[str, ...]:
        suffix = "" if self.covariate is None else f"_{self.covariate}"
        return tuple(f"{self.symbol}{suffix}_{ax}" for ax in AXES)

    symbol = "p"
    #: which forms of it discovery proposes (None: never a candidate, e.g. the scale)
    proposed: ClassVar[Proposals | None] = None
    #: the options of `recal simulate` that give the simulated sensor this effect
    simulated: ClassVar[tuple[SimOption, ...]] = ()
    #: apply is x -> x A + c, the same A and c for every sample, unless it reads a covariate
    linear_in_x = False
    #: apply divides every reading by one factor per sample (`row_divisor`)
    divides_rows = False

    def row_divisor(self, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        """For a stage that divides_rows: the factor it divides each reading by."""
        raise NotImplementedError(f"{self.label} does not divide whole readings")

    @property
    def affine(self) -> bool:
        """Whether the stage is one affine map for every sample (`SensorModel.affine`)."""
        return self.linear_in_x and not self.channels

    @property
    def size(self) -> int:
        return len(self.param_names)

    def nominal(self, s0: float) -> np.ndarray:
        """Parameter values at which the stage does nothing (s0: nominal raw units per g)."""
        return np.zeros(self.size)

    def prior_sd(self, s0: float, spread: float) -> np.ndarray:
        """Default prior standard deviation; `spread` is the covariate's typical range."""
        raise NotImplementedError

    def process_sd_per_sqrt_h(self, s0: float, spread: float) -> np.ndarray:
        """Random-walk process noise of each parameter, per square-root hour."""
        return np.zeros(self.size)

    def bounds(self, s0: float, spread: float) -> tuple[np.ndarray, np.ndarray]:
        """Physical bounds; an update that leaves them is rejected."""
        sd = self.prior_sd(s0, spread)
        return -20 * sd, 20 * sd

    def observable_with(self, axes_covered: tuple[bool, bool, bool]) -> np.ndarray:
        """Which parameters the data can move, given which axes gravity has been seen on from
        both sides. Offsets are always observable; a gain needs its axis covered."""
        return np.ones(self.size, bool)

    def delta(self, cov: Covariates) -> np.ndarray:
        return cov.get(self.covariate) - self.ref  # type: ignore[arg-type]

    # --- the stage ---------------------------------------------------------------------------
    def apply(self, x: np.ndarray, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def d_theta(self, x: np.ndarray, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        """(N, 3, P): derivative of the stage output with respect to its parameters."""
        raise NotImplementedError

    def d_x(self, x: np.ndarray, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        """(N, 3, 3): derivative of the stage output with respect to its input."""
        raise NotImplementedError

    def vjp(self, g: np.ndarray, x: np.ndarray, cov: Covariates, theta: np.ndarray,
            want_x: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """One chain-rule step of Lötters eq. 13a: g (N,3) = d|a|/d(stage output) times
        d_theta (N,P) and times d_x (N,3; None unless want_x). Stages with diagonal
        derivatives override it with the same products without the (N,3,3) arrays."""
        b = np.einsum("ni,nip->np", g, self.d_theta(x, cov, theta))
        return b, np.einsum("ni,nij->nj", g, self.d_x(x, cov, theta)) if want_x else None

    #: `unit_vjp` returns one column of d_theta per axis (None: a whole row of the block)
    per_axis_params = False

    def unit_vjp(self, j: int, s: float | np.ndarray, x: np.ndarray, cov: Covariates,
                 theta: np.ndarray, want_x: bool = True
                 ) -> tuple[np.ndarray, float | np.ndarray] | None:
        """`vjp` for g = s e_j (s: a number or one per row, every other entry 0), the case of
        `status.correction_jacobian` (da/dp, row j of it): the only nonzero part of b, and the
        s of the next g = s' e_j (None where want_x is False). The same products as `vjp`, to
        the bit, without the zero columns. None: this stage mixes the axes (the full `vjp`)."""
        return None

    def describe(self, theta: np.ndarray, s0: float) -> dict:
        """Parameters in physical units for reports (g, mg per unit, %, deg)."""
        return dict(zip(self.param_names, map(float, theta), strict=True))


@dataclass(frozen=True)
class Ratiometric(Effect):
    """Whole output scaled by a supply channel: v = (1 + rho (c - c_ref)) v_0 (Zheng et al. 2015,
    eq. 1 compensates the same dependence linearly; ADXL335-type parts are ratiometric).

    With a `reference` channel r (2 parameters) the scaling is 1 + rho (c - c_ref) +
    rho_r (r - r_ref): a ratiometric part read by an ADC whose reference rail r is measured
    too, v ~ V_supply / V_ref, linearized (rho_r < 0 for a pure ratio). A fitted c_ref instead
    would be no second parameter: its overall factor is the same as offsets and scales.
    """

    kind: str = field(default="ratiometric", init=False)
    stage: int = field(default=1, init=False)
    divides_rows = True
    symbol = "rho"
    proposed = Proposals(order=3, per_channel=True, channel_pairs=True)
    simulated = (SimOption("--ratiometric-pct-per-v",
                           "whole output scaled by the supply (ratiometric parts)",
                           "ratiometric_per_v", 100, per_axis=False, channel="supply", place=2),)
    reference: str | None = None
    reference_ref: float = 0.0

    @property
    def param_names(self) -> tuple[str, ...]:
        if self.reference is None:
            return (f"rho_{self.covariate}",)
        return (f"rho_{self.covariate}", f"rho_{self.reference}")

    @property
    def label(self) -> str:
        if self.reference is None:
            return super().label
        return f"{self.kind}[{self.covariate},{self.reference}]"

    @property
    def channels(self) -> tuple[str, ...]:
        return super().channels + (() if self.reference is None else (self.reference,))

    def spec(self) -> dict:
        extra = ({} if self.reference is None
                 else {"reference": self.reference, "reference_ref": self.reference_ref})
        return super().spec() | extra

    def prior_sd(self, s0: float, spread: float) -> np.ndarray:
        return np.full(self.size, 0.5 / max(spread, 1e-9))

    def bounds(self, s0: float, spread: float) -> tuple[np.ndarray, np.ndarray]:
        lim = np.full(self.size, 0.5 / max(spread, 1e-9))
        return -lim, lim

    def _deltas(self, cov: Covariates) -> np.ndarray:
        """(N, P): c - c_ref, and r - r_ref with a reference."""
        d = self.delta(cov)[:, None]
        if self.reference is None:
            return d
        return np.hstack([d, (cov.get(self.reference) - self.reference_ref)[:, None]])

    def _factor(self, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        if self.reference is None:  # the one-column product, without a matrix product
            return 1.0 + self.delta(cov) * float(theta[0])
        return 1.0 + self._deltas(cov) @ np.asarray(theta, np.float64)

    def row_divisor(self, cov: Covariates, theta: np.ndarray) -> np.ndarray:
        return self._factor(cov, theta)

    def apply(self, x, cov, theta):
        return per_row(np.divide, x, self._factor(cov, theta))

    def d_theta(self, x, cov, theta):
        d = self._deltas(cov)
        k = self._factor(cov, theta)
        return -x[:, :, None] * (d / k[:, None] ** 2)[:, None, :]

    def d_x(self, x, cov, theta):
        return _eye(len(x)) / self._factor(cov, theta)[:, None, None]

    def unit_vjp(self, j, s, x, cov, theta, want_x=True):
        # d_theta's row j, -x_j (d / k^2), times s (einsum's sum over the axes adds zeros)
        d = self._deltas(cov)
        k = self._factor(cov, theta)
        b = s * (-x[:, j, None] * (d / k[:, None] ** 2)) if np.ndim(s) == 0 else \
            s[:, None] * (-x[:, j, None] * (d / k[:, None] ** 2))
        return b, (s * (1.0 / k) if want_x else None)

    def describe(self, theta, s0):
        out = {"rho_per_unit": float(theta[0]), "pct_per_unit": 100 * float(theta[0])}
        if self.reference is not None:
            out |= {"rho_reference_per_unit": float(theta[1]),
                    "reference_pct_per_unit": 100 * float(theta[1])}
        return out


@dataclass(frozen=True)
class Offset(Effect):
    """Offset o (Lötters eq. 3, raw units), or an offset linear in a covariate (beta per unit)."""

    kind: str = field(default="offset", init=False)
    stage: int = field(default=2, init=False)
    symbol = "o"
    linear_in_x = True
    proposed = Proposals(order=1, per_channel=True, in_time=True)
    simulated = (SimOption("--offset-tc-mg-per-c",
                           "offset temperature coefficient (random sign per axis)",
                           "offset_tc_g_per_c", 1e3, per_axis=True, channel="temperature",
                           place=0),
                 SimOption("--drift-mg-per-h", "offset drift in time", "offset_drift_g_per_h",
                           1e3, per_axis=True, channel="time", place=3))

    def prior_sd(self, s0, spread):
        if self.covariate is None:
            return np.full(3, 0.1 * s0)  # 100 mg: wider than any offset we have seen drift to
        return np.full(3, 0.1 * s0 / max(spread, 1e-9))

    def process_sd_per_sqrt_h(self, s0, spread):
        # Offsets drift within hours (Lötters sec. 1). A steady drift is the estimator's offset
        # rate (estimator.py); this walk covers what a straight line does not, and is kept small
        # so that windows from an hour ago still pin the gains and cross-axis terms; the price:
        # offsets that follow temperature swings the model lacks are tracked more slowly
        # (chosen by bench/in_use_accuracy.py; figures in docs/design.md, "Figures behind choices").
        return np.full(3, OFFSET_WALK_G_PER_SQRT_H * s0) if self.covariate is None else np.zeros(3)

    def bounds(self, s0, spread):
        if self.covariate is None:
            return np.full(3, -0.5 * s0), np.full(3, 0.5 * s0)
        lim = 0.5 * s0 / max(spread, 1e-9)
        return np.full(3, -lim), np.full(3, lim)

    def apply(self, x, cov, theta):
        if self.covariate is None:
            return per_axis(np.subtract, x, theta)
        return x - self.delta(cov)[:, None] * theta

    def d_theta(self, x, cov, theta):
        if self.covariate is None:
            return -_eye(len(x))
        return -_eye(len(x)) * self.delta(cov)[:, None, None]

    def d_x(self, x, cov, theta):
        return _eye(len(x))

    def vjp(self, g, x, cov, theta, want_x=True):
        d = -1.0 if self.covariate is None else -self.delta(cov)[:, None]
        return g * d, g if want_x else None

    per_axis_params = True

    def unit_vjp(self, j, s, x, cov, theta, want_x=True):
        d = -1.0 if self.covariate is None else -self.delta(cov)
        return s * d, (s if want_x else None)

    def describe(self, theta, s0):
        unit = "mg" if self.covariate is None else f"mg_per_{self.covariate}"
        return {f"{ax}_{unit}": 1000 * float(t) / s0 for ax, t in zip(AXES, theta, strict=True)}


@dataclass(frozen=True)
class Scale(Effect):
    """Sensitivity s per axis in raw units per g (Lötters eq. 3, s_dir)."""

    kind: str = field(default="scale", init=False)
    stage: int = field(default=3, init=False)
    symbol = "s"
    linear_in_x = True

    def nominal(self, s0):
        return np.full(3, float(s0))

    def observable_with(self, axes_covered):
        return np.array(axes_covered, bool)

    def prior_sd(self, s0, spread):
        return np.full(3, 0.05 * s0)

    def process_sd_per_sqrt_h(self, s0, spread):
        return np.full(3, SCALE_WALK_PER_SQRT_H * s0)

    def bounds(self, s0, spread):
        return np.full(3, 0.8 * s0), np.full(3, 1.2 * s0)

    def apply(self, x, cov, theta):
        return per_axis(np.divide, x, theta)

    def d_theta(self, x, cov, theta):
        return _diag(-x / theta**2)

    def d_x(self, x, cov, theta):
        return _diag(np.broadcast_to(1.0 / theta, x.shape))

    def vjp(self, g, x, cov, theta, want_x=True):
        return g * (-x / theta**2), g * (1.0 / theta) if want_x else None

    per_axis_params = True

    def unit_vjp(self, j, s, x, cov, theta, want_x=True):
        t = theta[j]
        return s * (-x[:, j] / (t * t)), (s * (1.0 / t) if want_x else None)

    def describe(self, theta, s0):
        return {f"s_{ax}": float(t) for ax, t in zip(AXES, theta, strict=True)} | {
            f"gain_{ax}_pct": 100 * (float(t) / s0 - 1) for ax, t in zip(AXES, theta, strict=True)}


@dataclass(frozen=True)
class Gain(Effect):
    """Per-axis sensitivity linear in a covariate: x / (1 + gamma (c - c_ref))."""

    kind: str = field(default="gain", init=False)
    stage: int = field(default=3, init=False)
    symbol = "gamma"
    proposed = Proposals(order=2, per_channel=True)
    simulated = (SimOption("--gain-tc-pct-per-c",
                           "gain temperature coefficient (random sign per axis)",
                           "gain_tc_per_c", 100, per_axis=True, channel="temperature", place=1),)

    def observable_with(self, axes_covered):
        return np.array(axes_covered, bool)

    def prior_sd(self, s0, spread):
        return np.full(3, 0.05 / max(spread, 1e-9))

    def bounds(self, s0, spread):
        lim = 0.2 / max(spread, 1e-9)
        return np.full(3, -lim), np.full(3, lim)

    def apply(self, x, cov, theta):
        return x / (1.0 + self.delta(cov)[:, None] * theta)

    def d_theta(self, x, cov, theta):
        d = self.delta(cov)[:, None]
        return _diag(-x * d / (1.0 + d * theta) ** 2)

    def d_x(self, x, cov, theta):
        return _diag(1.0 / (1.0 + self.delta(cov)[:, None] * theta))

    per_axis_params = True

    def unit_vjp(self, j, s, x, cov, theta, want_x=True):
        d = self.delta(cov)
        f = 1.0 + d * theta[j]
        return s * (-x[:, j] * d / f ** 2), (s * (1.0 / f) if want_x else None)

    def describe(self, theta, s0):
        return {f"{ax}_pct_per_{self.covariate}": 100 * float(t)
                for ax, t in zip(AXES, theta, strict=True)}


@dataclass(frozen=True)
class CrossAxis(Effect):
    """Cross-axis coupling / non-orthogonal axes (Bragge eq. 1 with full K; Georgieva eq. 16).

    a = M x with M = [[1, c_xy, c_xz], [0, 1, c_yz], [0, 0, 1]]: together with the diagonal
    scale, the inverse sensitivity matrix is upper-triangular, which fixes the rotation gauge
    (a rotation of the sensor frame is not observable from |a| = 1 g alone).
    """

    kind: str = field(default="cross_axis", init=False)
    stage: int = field(default=4, init=False)
    linear_in_x = True
    # its simulated form is the sensor's random misalignment (`SensorSpec.random`)
    proposed = Proposals(order=4, plain=True)

    @property
    def param_names(self) -> tuple[str, ...]:
        return ("c_xy", "c_xz", "c_yz")

    def observable_with(self, axes_covered):
        x, y, z = axes_covered
        return np.array([x and y, x and z, y and z], bool)

    def prior_sd(self, s0, spread):
        return np.full(3, 0.05)

    def bounds(self, s0, spread):
        return np.full(3, -0.2), np.full(3, 0.2)

    @staticmethod
    def matrix(theta: np.ndarray) -> np.ndarray:
        return np.array([[1.0, theta[0], theta[1]], [0.0, 1.0, theta[2]], [0.0, 0.0, 1.0]])

    def apply(self, x, cov, theta):
        return x @ self.matrix(theta).T

    def d_theta(self, x, cov, theta):
        out = np.zeros((len(x), 3, 3))
        out[:, 0, 0] = x[:, 1]
        out[:, 0, 1] = x[:, 2]
        out[:, 1, 2] = x[:, 2]
        return out

    def d_x(self, x, cov, theta):
        return np.broadcast_to(self.matrix(theta), (len(x), 3, 3))

    def describe(self, theta, s0):
        return dict(zip(self.param_names, map(float, theta), strict=True))


@dataclass(frozen=True)
class Nonlinearity(Effect):
    """Per-axis quadratic nonlinearity in g: a_i + q_i a_i^2 (q in 1/g)."""

    kind: str = field(default="nonlinearity", init=False)
    stage: int = field(default=5, init=False)
    symbol = "q"
    proposed = Proposals(order=5, plain=True)
    # the simulator's q distorts the true acceleration: the correction's q is about its opposite
    simulated = (SimOption("--nonlinearity-pct", "quadratic, % per g", "q_per_g", 100,
                           per_axis=True, channel=None, place=4),)

    def observable_with(self, axes_covered):
        return np.array(axes_covered, bool)

    def prior_sd(self, s0, spread):
        return np.full(3, 0.02)

    def bounds(self, s0, spread):
        return np.full(3, -0.2), np.full(3, 0.2)

    def apply(self, x, cov, theta):
        return x + theta * x**2

    def d_theta(self, x, cov, theta):
        return _diag(x**2)

    def d_x(self, x, cov, theta):
        return _diag(1.0 + 2.0 * theta * x)

    def describe(self, theta, s0):
        return {f"q_{ax}_per_g": float(t) for ax, t in zip(AXES, theta, strict=True)}


EFFECT_KINDS: dict[str, type[Effect]] = {
    "ratiometric": Ratiometric,
    "offset": Offset,
    "scale": Scale,
    "gain": Gain,
    "cross_axis": CrossAxis,
    "nonlinearity": Nonlinearity,
}


def sim_options() -> tuple[SimOption, ...]:
    """Every effect's `recal simulate` options, in their places."""
    return tuple(sorted((o for cls in EFFECT_KINDS.values() for o in cls.simulated),
                        key=lambda o: o.place))


def make_effect(kind: str, covariate: str | None = None, ref: float = 0.0,
                reference: str | None = None, reference_ref: float = 0.0) -> Effect:
    """Build an effect by its registry name (what model files and reports call it).

    `reference` (a second channel) exists only for "ratiometric"."""
    try:
        cls = EFFECT_KINDS[kind]
    except KeyError:
        raise ConfigError(f"unknown effect kind {kind!r}; known: {sorted(EFFECT_KINDS)}") from None
    if reference is not None:
        if cls is not Ratiometric:
            raise ConfigError(f"only a ratiometric effect takes a reference channel, not {kind!r}")
        return Ratiometric(covariate=covariate, ref=float(ref), reference=reference,
                           reference_ref=float(reference_ref))
    return cls(covariate=covariate, ref=float(ref))
