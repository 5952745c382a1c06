"""The effect registry (`effects.EFFECT_KINDS`) drives its variants: discovery's candidates and
their order, the core's public names, the named models and `recal simulate`'s options."""

from __future__ import annotations

from dataclasses import fields, replace

import pytest

import recal.core
from recal.cli import build_parser
from recal.config import MODELS
from recal.core.candidates import KIND_ORDER, proposals
from recal.core.discovery import DiscoveryConfig
from recal.core.effects import EFFECT_KINDS, TIME, Ratiometric, make_effect, sim_options
from recal.core.model import NAMED_MODELS, SensorModel
from recal.errors import ConfigError
from recal.node.node import model_name
from recal.sim.sensor import SensorSpec

CHANNELS = {"a": (1.0, 0.5), "b": (2.0, 0.25), "c": (3.0, 1.0)}
#: the kinds whose candidates and order are pinned below (a kind added later joins KIND_ORDER
#: without changing what these propose, nor in which order)
PINNED = ("offset", "gain", "ratiometric", "cross_axis", "nonlinearity")


def _labels(model: SensorModel, kinds: tuple[str, ...] = PINNED) -> list[str]:
    return [e.label for e, _ in proposals(model, CHANNELS, (0.5, 1.0), kinds)]


def test_the_kinds_in_their_order_of_simplicity() -> None:
    assert tuple(k for k in KIND_ORDER if k in PINNED) == PINNED
    assert DiscoveryConfig().kinds == KIND_ORDER


def test_candidates_per_channel_then_pairs_then_plain_then_time() -> None:
    assert _labels(SensorModel.diagonal(1.0)) == [
        "offset[a]", "gain[a]", "ratiometric[a]", "offset[b]", "gain[b]", "ratiometric[b]",
        "offset[c]", "gain[c]", "ratiometric[c]", "ratiometric[a,b]", "ratiometric[a,c]",
        "ratiometric[b,c]", "cross_axis", "nonlinearity", "offset[time]"]


def test_what_the_model_has_is_not_proposed_again() -> None:
    model = (SensorModel.full(1.0).with_effect(make_effect("offset", "a"))
             .with_effect(Ratiometric("b", reference="c")).with_effect(make_effect("offset", TIME)))
    # a ratiometric effect reads b and c: neither is proposed for another ratiometric one
    assert _labels(model) == ["gain[a]", "ratiometric[a]", "offset[b]", "gain[b]", "offset[c]",
                              "gain[c]", "nonlinearity"]
    assert _labels(model, ("gain",)) == ["gain[a]", "gain[b]", "gain[c]"]


def test_candidates_carry_their_references_and_spreads() -> None:
    found = {e.label: (e, sp) for e, sp in proposals(SensorModel.diagonal(1.0), CHANNELS, None)}
    assert "offset[time]" not in found  # no time asked for
    pair, spread = found["ratiometric[a,b]"]
    assert (pair.ref, pair.reference_ref, spread) == (1.0, 2.0, 0.25)  # the smaller spread
    assert found["gain[c]"][0].ref == 3.0 and found["gain[c]"][1] == 1.0


def test_every_effect_class_is_a_public_core_name() -> None:
    for cls in EFFECT_KINDS.values():
        assert cls.__name__ in recal.core.__all__
        assert getattr(recal.core, cls.__name__) is cls


def test_named_models_from_the_registry() -> None:
    assert MODELS == tuple(NAMED_MODELS)
    assert {"diagonal", "full"} <= set(MODELS)
    for name in NAMED_MODELS:
        model = SensorModel.named(name, 512.0)
        assert model.name == name and model_name(model) == name and model.s0 == 512.0
    assert SensorModel.diagonal(1.0).names == SensorModel.named("diagonal").names
    grown = SensorModel.full(1.0).with_effect(make_effect("nonlinearity"))
    assert grown.name is None and model_name(grown) == "offset+scale+cross_axis+nonlinearity"
    with pytest.raises(ConfigError, match="unknown model"):
        SensorModel.named("diagonal+", 1.0)


def test_every_simulator_option_sets_a_sensor_field_and_is_a_simulate_option() -> None:
    options = sim_options()
    assert [o.place for o in options] == list(range(len(options)))
    sensor_fields = {f.name for f in fields(SensorSpec)}
    assert {o.field for o in options} <= sensor_fields
    parser = build_parser()
    for o in options:
        args = parser.parse_args(["simulate", "--out", "x.mcap", o.flag, "2"])
        assert getattr(args, o.flag.lstrip("-").replace("-", "_")) == 2.0


@pytest.mark.parametrize("option", sim_options(), ids=lambda o: o.flag)
def test_a_sensor_needs_the_channel_its_effects_read(option) -> None:
    value = (0.001, 0.0, 0.0) if option.per_axis else 0.001
    sensor = replace(SensorSpec(), **{option.field: value})
    for channel in ("temperature", "supply", "time"):
        assert sensor.needs(channel) == (channel == option.channel)
    assert not any(SensorSpec().needs(c) for c in ("temperature", "supply", "time"))
    assert sensor.needs_temp == (option.channel == "temperature")
    assert sensor.needs_supply == (option.channel == "supply")
    assert sensor.needs_time == (option.channel == "time")
