"""The sensor model: one named parameter vector over a chain of effects, and the correction.

    a = f(v; p)            raw reading v -> acceleration in g (the chain in `effects`)
    h(v, p) = |a|          Lötters eq. 8, generalized to any chain of effects
    xi = 1 g - h(v, p)     Lötters eq. 14
    B = dh/dp              Lötters eq. 13a, here by the chain rule through the stages

The diagonal model (Lötters, 6 parameters) is `offset + scale`; the full model (Bragge,
Georgieva: offsets and a 3x3 sensitivity with the rotation gauge fixed) adds `cross_axis`.
See docs/design.md ("The core, module by module").
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from recal.core.effects import Covariates, CrossAxis, Effect, Offset, Scale, make_effect
from recal.core.triaxial import norm3, per_axis, per_row
from recal.errors import ConfigError

__all__ = ["NAMED_MODELS", "AffineCorrection", "SensorModel"]

#: The models a config names (``model = "diagonal"``), by their effects (none reads a channel).
NAMED_MODELS: dict[str, tuple[type[Effect], ...]] = {
    "diagonal": (Offset, Scale),     # Lötters' six parameters
    "full": (Offset, Scale, CrossAxis),  # Bragge/Georgieva, nine
}


@dataclass(frozen=True, eq=False)
class AffineCorrection:
    """a = (v A) / d + c for readings v (N,3): A (3,3), c (3,), and d the product of the
    per-sample factors the leading stages divide every reading by (none: d = 1). What
    `SensorModel.correct` computes, to rounding, for a model `SensorModel.affine` accepts."""

    A: np.ndarray
    c: np.ndarray
    divisors: tuple[tuple[Effect, np.ndarray], ...] = ()

    def __call__(self, v: np.ndarray, cov: Covariates | None,
                 out: np.ndarray | None = None) -> np.ndarray:
        """Corrected readings, into ``out`` (N,3) if given; cov is needed with divisors.
        In place, column by column (`triaxial.per_row`, `per_axis`)."""
        out = np.matmul(np.asarray(v, np.float64), self.A, out=out)
        for e, theta in self.divisors:
            per_row(np.divide, out, e.row_divisor(cov, theta), out=out)  # type: ignore[arg-type]
        return per_axis(np.add, out, self.c, out=out)


@dataclass(frozen=True, eq=False)
class SensorModel:
    """An ordered chain of effects plus the nominal sensitivity s0 (raw units per g).

    Attributes:
        effects: the stages, sorted by stage order.
        s0: nominal sensitivity in raw units per g (e.g. 1024 counts/g, 9.81 for m/s^2).
        spreads: typical range of each effect's covariate (for default priors and bounds).
    """

    effects: tuple[Effect, ...]
    s0: float = 1.0
    spreads: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not self.effects:
            raise ConfigError("a model needs at least one effect (offsets, scale, ...)")
        if not self.s0 > 0:
            raise ConfigError(f"s0 (raw units per g) must be positive, not {self.s0}")
        spreads = tuple(self.spreads) or (1.0,) * len(self.effects)
        if len(spreads) != len(self.effects):
            raise ConfigError("one spread per effect")
        # stable sort keeps insertion order within a stage, and spreads stay with their effect
        pairs = sorted(zip(self.effects, map(float, spreads), strict=True),
                       key=lambda es: es[0].stage)
        keys = [e.key for e, _ in pairs]
        if len(set(keys)) != len(keys):
            raise ConfigError(f"duplicate effects in model: {keys}")
        object.__setattr__(self, "effects", tuple(e for e, _ in pairs))
        object.__setattr__(self, "spreads", tuple(sp for _, sp in pairs))
        # Slices and names are asked for many times per estimator update: compute them once.
        bounds = np.cumsum([0, *(e.size for e in self.effects)]).tolist()
        slices = tuple(slice(a, b) for a, b in pairwise(bounds))
        object.__setattr__(self, "_slices", slices)
        object.__setattr__(self, "_slice_of", {e.key: sl for e, sl in zip(self.effects, slices,
                                                                          strict=True)})
        object.__setattr__(self, "_names", tuple(n for e in self.effects for n in e.param_names))

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def diagonal(cls, s0: float = 1.0) -> SensorModel:
        """Lötters' six parameters: offsets and per-axis sensitivities."""
        return cls.named("diagonal", s0)

    @classmethod
    def full(cls, s0: float = 1.0) -> SensorModel:
        """Offsets and an upper-triangular inverse sensitivity (Bragge/Georgieva, 9 parameters)."""
        return cls.named("full", s0)

    @classmethod
    def named(cls, name: str, s0: float = 1.0) -> SensorModel:
        """One of `NAMED_MODELS`."""
        try:
            return cls(tuple(kind() for kind in NAMED_MODELS[name]), s0)
        except KeyError:
            raise ConfigError(f"unknown model {name!r}; known: {', '.join(NAMED_MODELS)}") from None

    @property
    def name(self) -> str | None:
        """The `NAMED_MODELS` name of this chain of effects (None: not a named one)."""
        keys = tuple(e.key for e in self.effects)
        return next((name for name, kinds in NAMED_MODELS.items()
                     if keys == tuple((k.kind, None) for k in kinds)), None)

    def with_effect(self, effect: Effect, spread: float = 1.0) -> SensorModel:
        return SensorModel((*self.effects, effect), self.s0, (*self.spreads, float(spread)))

    def extend(self, p: np.ndarray, effect: Effect, spread: float = 1.0) -> tuple[SensorModel,
                                                                                   np.ndarray]:
        """The model with one more effect, and p carried over with the new effect at nominal."""
        new = self.with_effect(effect, spread)
        q = new.nominal()
        for e in self.effects:
            q[new.slice(e)] = p[self.slice(e)]
        return new, q

    # --- the named parameter vector ----------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return self._names

    @property
    def size(self) -> int:
        return len(self._names)

    def slice(self, effect: Effect | tuple[str, str | None]) -> slice:
        key = effect if isinstance(effect, tuple) else effect.key
        try:
            return self._slice_of[key]
        except KeyError:
            raise KeyError(f"model has no effect {key}") from None

    def has(self, kind: str, covariate: str | None = None) -> bool:
        return any(e.key == (kind, covariate) for e in self.effects)

    def index(self, name: str) -> int:
        return self.names.index(name)

    @functools.cached_property
    def covariates(self) -> tuple[str, ...]:
        # the model is immutable; asked at every step (`channels.usable`)
        return tuple(sorted({c for e in self.effects for c in e.channels}))

    def nominal(self) -> np.ndarray:
        return self._nominal.copy()

    def prior_sd(self) -> np.ndarray:
        return self._prior_sd.copy()

    def process_sd_per_sqrt_h(self) -> np.ndarray:
        return self._process_sd.copy()

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self._bounds
        return lo.copy(), hi.copy()

    # The model is immutable: these are built once (each estimator update asks for them).
    @functools.cached_property
    def _nominal(self) -> np.ndarray:
        return np.concatenate([e.nominal(self.s0) for e in self.effects])

    @functools.cached_property
    def _prior_sd(self) -> np.ndarray:
        return np.concatenate([e.prior_sd(self.s0, sp)
                               for e, sp in zip(self.effects, self.spreads, strict=True)])

    @functools.cached_property
    def _process_sd(self) -> np.ndarray:
        return np.concatenate([e.process_sd_per_sqrt_h(self.s0, sp)
                               for e, sp in zip(self.effects, self.spreads, strict=True)])

    @functools.cached_property
    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = zip(*(e.bounds(self.s0, sp)
                       for e, sp in zip(self.effects, self.spreads, strict=True)), strict=True)
        return np.concatenate(lo), np.concatenate(hi)

    def observable_with(self, axes_covered: tuple[bool, bool, bool]) -> np.ndarray:
        """Parameters the data can move given the axes covered (see Effect.observable_with)."""
        return np.concatenate([e.observable_with(axes_covered) for e in self.effects])

    def mask(self, kinds: Iterable[str]) -> np.ndarray:
        """Boolean mask of the parameters that belong to effects of the given kinds."""
        kinds = set(kinds)
        return np.concatenate([np.full(e.size, e.kind in kinds) for e in self.effects])

    # --- the correction and its Jacobian -----------------------------------------------------
    @functools.cached_property
    def axes_apart(self) -> bool:
        """Every stage keeps the axes apart (`Effect.unit_vjp`): the Jacobian of the correction
        can be taken axis by axis (`status.correction_jacobian`)."""
        return all(type(e).unit_vjp is not Effect.unit_vjp for e in self.effects)

    def correct(self, p: np.ndarray, v: np.ndarray, cov: Covariates) -> np.ndarray:
        """Raw readings (N,3) -> acceleration in g (N,3): the inverse of Lötters eq. 3."""
        x = np.asarray(v, np.float64)
        for e, sl in zip(self.effects, self._slices, strict=True):
            x = e.apply(x, cov, p[sl])
        return x

    def affine(self, p: np.ndarray) -> AffineCorrection | None:
        """The correction as one small matrix product (`AffineCorrection`), to rounding, when
        the model's first stages each divide the whole reading by a factor of the covariates
        (ratiometric) and the others are affine and read no covariate (offsets, scales,
        cross-axis terms); else None. It corrects a recording at a fraction of the chain's
        cost."""
        k = 0
        while k < len(self.effects) and self.effects[k].divides_rows:
            k += 1
        if not all(e.affine for e in self.effects[k:]):
            return None
        rest = SensorModel(self.effects[k:], self.s0, self.spreads[k:])
        q = np.concatenate([p[sl] for sl in self._slices[k:]] or [np.zeros(0)])
        pts = rest.correct(q, np.vstack([np.zeros(3), np.eye(3)]),
                           Covariates(np.zeros(4), np.zeros((4, 0))))
        divisors = tuple((e, p[sl]) for e, sl in zip(self.effects[:k], self._slices[:k],
                                                       strict=True))
        return AffineCorrection(pts[1:] - pts[0], pts[0], divisors)

    def residual(self, p: np.ndarray, v: np.ndarray, cov: Covariates) -> np.ndarray:
        """xi = 1 - |a| alone (Lötters eq. 14), as `residual_jacobian` computes it: what a
        step-length test needs, without the Jacobian."""
        a = self.correct(p, v, cov)
        return 1.0 - norm3(a)

    def residual_jacobian(self, p: np.ndarray, v: np.ndarray,
                          cov: Covariates) -> tuple[np.ndarray, np.ndarray]:
        """xi = 1 - |a| (Lötters eq. 14) and B = d|a|/dp (eq. 13a, by the chain rule).

        Returns (xi (N,), B (N, P)).
        """
        xs = [np.asarray(v, np.float64)]
        for e, sl in zip(self.effects, self._slices, strict=True):
            xs.append(e.apply(xs[-1], cov, p[sl]))
        a = xs[-1]
        r = norm3(a)
        g = a / np.maximum(r, 1e-12)[:, None]  # d|a|/da
        B = np.empty((len(a), self.size))
        for k in range(len(self.effects) - 1, -1, -1):
            sl = self._slices[k]
            B[:, sl], g_in = self.effects[k].vjp(g, xs[k], cov, p[sl], k > 0)
            g = g_in if k else g
        return 1.0 - r, B

    # --- reporting and files -----------------------------------------------------------------
    def describe(self, p: np.ndarray, gain_reference: float | None = None) -> dict[str, dict]:
        """Parameters by effect, in physical units (mg, %, ...): gains in % of gain_reference,
        offsets in mg of it (raw units per g; None: s0). Without a prior that is the data's
        own scale: s0 is then a recording's median norm, offsets and all (5 % over a sensor's
        1 g with 50 mg of offset along the vertical), no unit to report offsets in."""
        ref = self.s0 if gain_reference is None else float(gain_reference)
        return {e.label: e.describe(p[self.slice(e)], ref) for e in self.effects}

    def sensitivity_matrix(self, p: np.ndarray) -> np.ndarray:
        """K in v = K a + o for the linear part (raw per g), rotation gauge fixed."""
        T = np.diag(1.0 / p[self.slice(Scale())])
        if self.has("cross_axis"):
            T = CrossAxis.matrix(p[self.slice(CrossAxis())]) @ T
        return np.linalg.inv(T)

    def axis_angles_deg(self, p: np.ndarray) -> dict[str, float]:
        """Angles between the sensing axes (Georgieva et al.: phi=(x,y), psi=(x,z), theta=(y,z))."""
        K = self.sensitivity_matrix(p)
        rows = K / np.linalg.norm(K, axis=1, keepdims=True)

        def ang(i: int, j: int) -> float:
            return float(np.degrees(np.arccos(np.clip(rows[i] @ rows[j], -1, 1))))

        return {"phi_xy_deg": ang(0, 1), "psi_xz_deg": ang(0, 2), "theta_yz_deg": ang(1, 2)}

    def to_dict(self) -> dict:
        return {"s0": self.s0,
                "effects": [{**e.spec(), "spread": sp}
                            for e, sp in zip(self.effects, self.spreads, strict=True)]}

    @classmethod
    def from_dict(cls, d: dict) -> SensorModel:
        effects = [make_effect(e["kind"], e.get("covariate"), e.get("ref", 0.0),
                               e.get("reference"), e.get("reference_ref", 0.0))
                   for e in d["effects"]]
        spreads = [float(e.get("spread", 1.0)) for e in d["effects"]]
        return cls(tuple(effects), float(d.get("s0", 1.0)), tuple(spreads))

    def params_dict(self, p: np.ndarray) -> dict[str, float]:
        return dict(zip(self.names, map(float, p), strict=True))

    def params_from(self, values: dict[str, float] | Sequence[float]) -> np.ndarray:
        if isinstance(values, dict):
            p = self.nominal()
            for k, val in values.items():
                p[self.index(k)] = float(val)
            return p
        p = np.asarray(values, np.float64)
        if p.shape != (self.size,):
            raise ConfigError(f"expected {self.size} parameters, got {p.shape}")
        return p
