"""The effects discovery may add to a model: every registered kind's proposed forms.

Each kind in `effects.EFFECT_KINDS` says which of its forms discovery tries (`Proposals`):
linear in each auxiliary channel c, whatever it is called (an offset, a gain, the whole output
ratiometric in c), in each pair of channels (ratiometric in c with r as the reference rail),
without a covariate (cross-axis with the rotation gauge fixed, per-axis quadratic
nonlinearity), in time (an offset drift). `proposals` lists them in a fixed order: per channel
(channels in the data's order, kinds in `KIND_ORDER` for each), then per pair of channels, then
those without a covariate, then those in time; discovery's choices among equals follow it.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from recal.core.discovery_data import DiscoveryData, covariate_spread, usable_channels
from recal.core.effects import EFFECT_KINDS, TIME, Effect, Proposals, make_effect
from recal.core.model import SensorModel

__all__ = ["KIND_ORDER", "candidates", "proposals", "smaller_models"]

#: Kinds that discovery proposes, by what each declares of itself.
_PROPOSED: dict[str, Proposals] = {k: cls.proposed for k, cls in EFFECT_KINDS.items()
                                   if cls.proposed is not None}

#: Order of simplicity between candidates with as many observed directions (e.g. in a single
#: pose an offset, a gain and a ratiometric term in temperature all move |a| alike, one
#: direction each): the commoner effect first (offsets drift with temperature in every field
#: device; gains less; supply scaling needs a ratiometric part). Each kind's `Proposals.order`.
KIND_ORDER: tuple[str, ...] = tuple(sorted(_PROPOSED, key=lambda k: _PROPOSED[k].order))


def proposals(model: SensorModel, channels: dict[str, tuple[float, float]],
              time: tuple[float, float] | None, kinds: tuple[str, ...] = KIND_ORDER
              ) -> list[tuple[Effect, float]]:
    """Every form of the `kinds` (by their `Proposals`) that `model` lacks, with its covariate
    spread: channels maps each usable channel to (reference, spread); time is (reference,
    spread) of the time in hours, None where no time candidate is wanted."""
    wanted = [k for k in KIND_ORDER if k in kinds]
    used = {k: {c for e in model.effects if e.kind == k for c in e.channels} for k in wanted}
    out: list[tuple[Effect, float]] = []
    for name, (ref, spread) in channels.items():
        out += [(make_effect(k, name, ref), spread) for k in wanted
                if _PROPOSED[k].per_channel and name not in used[k]]
    for k in (k for k in wanted if _PROPOSED[k].channel_pairs):
        for a, b in combinations([c for c in channels if c not in used[k]], 2):
            eff = make_effect(k, a, channels[a][0], b, channels[b][0])
            out.append((eff, min(channels[a][1], channels[b][1])))
    out += [(make_effect(k), 1.0) for k in wanted
            if _PROPOSED[k].plain and not model.has(k)]
    if time is not None:
        out += [(make_effect(k, TIME, time[0]), time[1]) for k in wanted
                if _PROPOSED[k].in_time and TIME not in used[k]]
    return out


def candidates(model: SensorModel, data: DiscoveryData, kinds: tuple[str, ...] = KIND_ORDER,
               time: bool = True) -> list[tuple[Effect, float]]:
    """Every effect of `kinds` (with its covariate spread) the model could be extended by, on
    `data`: its usable channels (finite, not constant; reference the median), and its time
    (`time` asks for it) if it has one that varies."""
    t_h = data.cov.t_h
    in_time = None
    if time and data.has_time and len(t_h) and covariate_spread(t_h) > 0:
        in_time = (float(np.median(t_h)), covariate_spread(t_h))
    return proposals(model, usable_channels(data), in_time, kinds)


def smaller_models(model: SensorModel, eff: Effect, data: DiscoveryData
                   ) -> list[tuple[str, SensorModel, Effect | None]]:
    """Smaller models than `model` without `eff`: "reduce" (a ratiometric effect with a
    reference back to one of its channels, tried first) and "remove"."""
    rest = [(e, sp) for e, sp in zip(model.effects, model.spreads, strict=True) if e != eff]
    without = SensorModel(tuple(e for e, _ in rest), model.s0, tuple(sp for _, sp in rest))
    out: list[tuple[str, SensorModel, Effect | None]] = []
    ref_channel = getattr(eff, "reference", None)
    if eff.kind == "ratiometric" and ref_channel is not None:
        chans = usable_channels(data)
        for ch in (eff.covariate, ref_channel):
            if ch in chans:
                single = make_effect("ratiometric", ch, chans[ch][0])
                out.append(("reduce", without.with_effect(single, chans[ch][1]), single))
    out.append(("remove", without, None))
    return out
