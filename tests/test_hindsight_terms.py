"""Hindsight where the model fits because it has the effect's term (bench/honesty_cases.py,
`with_terms`: as `recal discover` adds it), and on the lab's six poses: accurate to the noise,
sigma neither too sure nor uselessly wide (the honesty metric of bench/honesty_cases.py)."""

from __future__ import annotations

import numpy as np
import pytest

from bench_modules import load_bench
from recal.commands.hindsight import Corrected
from recal.core import hindsight
from recal.core.discovery_data import rate_and_scale
from recal.core.pipeline_config import PipelineConfig
from recal.samples import rebatch

hc = load_bench("honesty_cases")
CASE = {c.name: c for c in hc.CASES}


def _scored(name: str, hours: float) -> tuple[dict, object]:
    """The case's recording through what `recal hindsight` runs, scored; and the fit."""
    case = CASE[name]
    raw, truth, noise_g = case.recording(1, hours)
    rate_hz, median_norm = rate_and_scale([raw])
    cfg = PipelineConfig(rate_hz=rate_hz)
    fit = hindsight.calibrate(lambda: [raw], case.model_for(median_norm, raw), cfg)
    outs = [Corrected(fit, cfg)(b) for b in rebatch([raw])]
    m = hc.honesty(np.concatenate([o.a_g for o in outs]), truth,
                   np.concatenate([o.sigma_mg for o in outs]),
                   np.concatenate([o.status for o in outs]), rate_hz, noise_g)
    return m, fit


@pytest.mark.parametrize(("name", "kind", "channel"), [
    ("temperature on offsets (2 mg/C), with its term", "offset", "temp_c"),
    ("analog 12-bit, sagging supply, with its term", "ratiometric", "vdd_v")])
def test_an_effect_with_its_term_is_calibrated_to_the_noise_in_hindsight(
        name: str, kind: str, channel: str) -> None:
    """1 h: the fit has the term, every window calibrated at about the noise left in a 1 s
    mean (1 mg; 4-9 and ~300 mg without the term, bench/hindsight_honesty.py), sigma_eff
    within 1/3 .. 3x the error, none beyond 3 sigma_eff."""
    m, fit = _scored(name, 1.0)
    assert fit.model.has(kind, channel)
    assert m["calibrated"] == m["windows"] and m["error_rms_mg"] < 1.5, m
    assert 1 / 3 <= m["over"] <= 3.0 and m["beyond_3"] == 0.0, m


def test_six_clean_poses_are_calibrated_to_the_noise_in_hindsight() -> None:
    """The lab stream (six poses held 5 s, twice) without a prior: every window calibrated
    at about the noise, none beyond 3 sigma_eff."""
    m, _ = _scored("six clean poses twice (lab)", 1.0)
    assert m["windows"] >= 80 and m["calibrated"] == m["windows"], m
    assert m["error_rms_mg"] < 1.5 and m["beyond_3"] == 0.0 and m["over"] <= 3.0, m
