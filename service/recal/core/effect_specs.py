"""What an effect declares of itself beyond its arithmetic: which of its forms discovery
proposes and how simple it is (`Proposals`), and how `recal simulate` gives a simulated sensor
the same effect (`SimOption`). Each class of `effects.EFFECT_KINDS` carries them; discovery's
candidates (`candidates`) and the simulate command read them from there.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Proposals", "SimOption"]


@dataclass(frozen=True)
class Proposals:
    """The forms of an effect that discovery proposes (`candidates.candidates`), and its rank.

    Attributes:
        order: rank of simplicity among kinds whose candidates determine as many directions
            (lower: tried as the simpler; `candidates.KIND_ORDER`).
        per_channel: one candidate per usable aux channel c, linear in c.
        channel_pairs: one per pair of usable channels (c, and r as a reference: `make_effect`'s
            `reference`).
        plain: one without a covariate.
        in_time: one in time (hours; where the data have time and the settings ask for it).
    A channel that an effect of the same kind already reads is not proposed again for it.
    """

    order: float
    per_channel: bool = False
    channel_pairs: bool = False
    plain: bool = False
    in_time: bool = False


@dataclass(frozen=True)
class SimOption:
    """How `recal simulate` gives its sensor an effect: a command-line option (default 0) that
    sets one `recal.sim.sensor.SensorSpec` field.

    Attributes:
        flag, help: the option and its help text.
        field: the SensorSpec field; its value is the option's divided by `divisor`
            (1e3: mg to g, 100: % to a fraction).
        per_axis: three values of the option's size, each with a random sign; else one number.
        channel: what the effect reads in the simulator ("temperature", "supply", "time"), so
            the recording carries it; None: nothing.
        place: position among the options, which is also the order the random signs are drawn
            in (a seed keeps its sensor).
    """

    flag: str
    help: str
    field: str
    divisor: float
    per_axis: bool
    channel: str | None
    place: int
