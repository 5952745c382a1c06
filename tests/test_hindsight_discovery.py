"""`recal hindsight` without --model on a recording with two effects nothing declares: an
analog 12-bit part whose output follows its sagging supply and whose offsets follow the
temperature (bench/honesty_cases.py, DISCOVERY_CASES; scored as bench/hindsight_honesty.py
--discover scores it). Discovery must find both effects, and the correction must be as good
as the same fit given the true model."""

from __future__ import annotations

import pytest

from bench_modules import load_bench

hh = load_bench("hindsight_honesty")
hc = load_bench("honesty_cases")


@pytest.mark.slow
@pytest.mark.float_sensitive
def test_hindsight_finds_the_supply_and_the_temperature_offset_of_an_analog_part() -> None:
    """1 h at 50 Hz. Scored by folds started from the smaller model's fold fits, a model
    inherited a diagonal fit gone astray (a z axis with 27x its gain) and nothing was found
    (2 h: the supply alone, 15 mg held out); every fold started from its own blocks' start,
    both are found and the correction is at the floor."""
    index = next(i for i, c in enumerate(hc.DISCOVERY_CASES)
                 if c.name == "temperature on offsets + analog supply")
    r = hh.run_discover(index, 1, 1.0)
    assert r["adopted"] == ["offset[temp_c]", "ratiometric[vdd_v]"], r
    assert r["error_mg"] <= 1.2 * r["floor_mg"], r
    assert r["calibrated_pct"] >= 90.0, r
    assert r["beyond_3"] <= 0.01 and r["beyond_10"] == 0.0, r
    assert r["sigma_median_mg"] <= 3 * r["error_median_mg"] + 0.5, r
