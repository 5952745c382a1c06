"""How the simulated wearer moves and how its aux channels evolve (`recal.sim.wearer`).

:class:`WearerSpec` holds four groups: the still postures (:class:`PostureSpec`), the steps of a
movement (:class:`StepSpec`), the temperature channel (:class:`TemperatureSpec`) and the supply
channel (:class:`SupplySpec`). Every field of a group is also a keyword of WearerSpec itself
(``WearerSpec(upright_tilt_deg=2.0, still_s=(20.0, 60.0))``), and ``to_dict`` / ``from_dict``
keep one flat table of them all: the truth file's ``params["wearer"]``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any

import numpy as np

from recal.errors import UsageError

__all__ = ["PostureSpec", "Range", "StepSpec", "SupplySpec", "TemperatureSpec", "WearerSpec"]

Range = tuple[float, float]


def _tuples_again(spec: Any) -> None:
    """Store a (min, max) read from JSON (a list) as a tuple again."""
    for f in fields(spec):
        val = getattr(spec, f.name)
        if isinstance(val, list | np.ndarray):
            object.__setattr__(spec, f.name, tuple(float(x) for x in val))


@dataclass(frozen=True)
class PostureSpec:
    """The still postures and how long each part of the schedule lasts.

    Attributes:
        still_s: (min, max) still-posture duration in s, uniform.
        move_s: (min, max) movement duration in s, uniform.
        p_upright, p_lying, p_any: posture kind probabilities (normalized by their sum).
        upright_only: every posture upright (then the p_* are ignored).
        upright_tilt_deg: upright = at-rest reading within this angle of +z.
        lying_band_deg: lying = at-rest reading within ± this elevation of the x-y plane.
        sway_g: RMS of the still-posture sway in g (mostly tilt; 0 = perfectly still).
        sway_max_hz: highest sway frequency in Hz.
        still_margin_s: samples this close to a still posture's ends are not `still`.
    """

    still_s: Range = (20.0, 180.0)
    move_s: Range = (4.0, 30.0)
    p_upright: float = 0.6
    p_lying: float = 0.25
    p_any: float = 0.15
    upright_only: bool = False
    upright_tilt_deg: float = 30.0
    lying_band_deg: float = 30.0
    sway_g: float = 0.002
    sway_max_hz: float = 0.3
    still_margin_s: float = 0.5

    def __post_init__(self) -> None:
        _tuples_again(self)
        if self.still_s[0] <= 2 * self.still_margin_s or self.move_s[0] <= 0:
            raise UsageError("still_s must exceed twice still_margin_s, move_s must be > 0")
        if not self.upright_only and min(self.p_upright, self.p_lying, self.p_any) < 0:
            raise UsageError("posture probabilities must be >= 0")
        if not self.upright_only and self.p_upright + self.p_lying + self.p_any <= 0:
            raise UsageError("posture probabilities must not all be 0")

    @property
    def kind_probabilities(self) -> np.ndarray:
        if self.upright_only:
            return np.array([1.0, 0.0, 0.0])
        p = np.array([self.p_upright, self.p_lying, self.p_any], np.float64)
        return p / p.sum()


@dataclass(frozen=True)
class StepSpec:
    """The walking-like steps of a movement between two postures.

    Attributes:
        step_hz: (min, max) step frequency in Hz, drawn per movement.
        step_vertical_g: (min, max) vertical step amplitude in g (fundamental).
        step_forward_ratio: forward amplitude / vertical, at the step frequency.
        step_lateral_ratio: lateral amplitude / vertical, at half the step frequency.
        wobble_deg: amplitude of the step-locked orientation wobble in deg.
    """

    step_hz: Range = (1.6, 2.2)
    step_vertical_g: Range = (0.15, 0.35)
    step_forward_ratio: float = 0.5
    step_lateral_ratio: float = 0.3
    wobble_deg: float = 5.0

    def __post_init__(self) -> None:
        _tuples_again(self)


@dataclass(frozen=True)
class TemperatureSpec:
    """The board temperature channel.

    Attributes:
        temp_mean_c: mean skin/board temperature in °C.
        temp_range_c: (min, max) °C the temperature is clipped to.
        temp_wander_c: standard deviation of the slow temperature wander in °C.
        temp_wander_tau_min: correlation time of the wander in minutes.
        temp_excursion_every_h: mean interval between outdoor/indoor excursions in h (at least
            one per recording, so short recordings still see a temperature change).
        temp_excursion_c: (min, max) magnitude of an excursion in °C (70 % cold, 30 % warm).
        temp_excursion_min: (min, max) excursion duration in minutes.
        temp_lag_min: thermal time constant of the board in minutes.
        temp_noise_c: temperature sensor noise in °C.
        temp_resolution_c: temperature channel resolution in °C.
    """

    temp_mean_c: float = 31.0
    temp_range_c: Range = (22.0, 36.0)
    temp_wander_c: float = 1.5
    temp_wander_tau_min: float = 20.0
    temp_excursion_every_h: float = 1.5
    temp_excursion_c: Range = (3.0, 8.0)
    temp_excursion_min: Range = (10.0, 45.0)
    temp_lag_min: float = 3.0
    temp_noise_c: float = 0.05
    temp_resolution_c: float = 0.01

    def __post_init__(self) -> None:
        _tuples_again(self)


@dataclass(frozen=True)
class SupplySpec:
    """The supply (battery) voltage channel.

    Attributes:
        vdd_start_v, vdd_end_v: battery voltage at the first and last sample in V.
        vdd_wander_v: standard deviation of slow supply wander in V (5 min correlation).
        vdd_dip_v: (min, max) depth of load dips in V.
        vdd_dip_s: (min, max) duration of load dips in s.
        vdd_dip_every_s: mean interval between load dips in s.
        vdd_noise_v: supply measurement noise in V.
        vdd_resolution_v: supply channel resolution in V.
    """

    vdd_start_v: float = 4.1
    vdd_end_v: float = 3.6
    vdd_wander_v: float = 0.01
    vdd_dip_v: Range = (0.03, 0.10)
    vdd_dip_s: Range = (1.0, 10.0)
    vdd_dip_every_s: float = 120.0
    vdd_noise_v: float = 0.002
    vdd_resolution_v: float = 0.001

    def __post_init__(self) -> None:
        _tuples_again(self)


#: each group of WearerSpec and its class, in the order of the flat table
_GROUPS: dict[str, type] = {"postures": PostureSpec, "steps": StepSpec,
                            "temperature": TemperatureSpec, "supply": SupplySpec}
#: the group each flat keyword belongs to
_GROUP_OF: dict[str, str] = {f.name: group for group, cls in _GROUPS.items()
                             for f in fields(cls)}


@dataclass(frozen=True, init=False)
class WearerSpec:
    """How the simulated wearer moves, and how the aux channels evolve.

    Attributes:
        postures: the still postures and the schedule's durations (:class:`PostureSpec`).
        steps: the steps of a movement (:class:`StepSpec`).
        always_aux: generate both aux channels even if the sensor does not need them.
        temperature: the temperature channel (:class:`TemperatureSpec`).
        supply: the supply channel (:class:`SupplySpec`).

    Any field of a group is a keyword too, laid over the group given (or its default):
    ``WearerSpec(upright_only=True, temp_wander_c=0.5)``.
    """

    postures: PostureSpec = field(default_factory=PostureSpec)
    steps: StepSpec = field(default_factory=StepSpec)
    always_aux: bool = False
    temperature: TemperatureSpec = field(default_factory=TemperatureSpec)
    supply: SupplySpec = field(default_factory=SupplySpec)

    def __init__(self, postures: PostureSpec | None = None, steps: StepSpec | None = None,
                 always_aux: bool = False, temperature: TemperatureSpec | None = None,
                 supply: SupplySpec | None = None, **flat: Any) -> None:
        given = {"postures": postures, "steps": steps, "temperature": temperature,
                 "supply": supply}
        changes: dict[str, dict[str, Any]] = {group: {} for group in _GROUPS}
        for name, value in flat.items():
            if name not in _GROUP_OF:
                raise TypeError(f"WearerSpec() got an unexpected keyword argument {name!r}")
            changes[_GROUP_OF[name]][name] = value
        for group, cls in _GROUPS.items():
            base = given[group]
            spec = (cls(**changes[group]) if base is None
                    else replace(base, **changes[group]) if changes[group] else base)
            object.__setattr__(self, group, spec)
        object.__setattr__(self, "always_aux", always_aux)

    def to_dict(self) -> dict[str, Any]:
        """One flat table of every group's fields, (min, max) pairs as lists."""
        flat: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            flat.update(asdict(value) if is_dataclass(value) else {f.name: value})
        return {k: list(v) if isinstance(v, tuple) else v for k, v in flat.items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> WearerSpec:
        """The spec of a flat table (`to_dict`); keys it does not know are left out."""
        known = {*_GROUP_OF, "always_aux"}
        return cls(**{k: v for k, v in d.items() if k in known})
