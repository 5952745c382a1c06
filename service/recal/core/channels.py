"""Which auxiliary channels a sensor model reads, and which samples may enter a window: one rule
for the pipeline, the batch window means, the node's start and the gateway's start check.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

from recal.core.effects import TIME
from recal.core.model import SensorModel
from recal.errors import ModelError
from recal.samples import RawBatch

__all__ = ["check_channels", "missing_channels", "unnamed_for", "usable"]

#: how a device's channels are named when no header named them (`recal.io.frames`)
_UNNAMED = re.compile(r"aux\d+")


def missing_channels(model: SensorModel, aux_names: Sequence[str]) -> list[str]:
    """The channels the model reads (its covariates, time aside) that ``aux_names`` lack, in
    the model's order."""
    return [c for c in model.covariates if c != TIME and c not in aux_names]


def unnamed_for(got: Sequence[str], names: Sequence[str]) -> bool:
    """Whether ``got`` are the unnamed placeholders (``aux0``, ``aux1``, ...) of as many
    channels as ``names``, which are named: a stream whose header was not heard (printed only
    at boot) carrying the channels a state was built with, in the same order."""
    return (len(got) == len(names) > 0 and tuple(got) != tuple(names)
            and all(_UNNAMED.fullmatch(g) for g in got)
            and not any(_UNNAMED.fullmatch(n) for n in names))


def check_channels(model: SensorModel, aux_names: tuple[str, ...]) -> None:
    """A model whose covariates the input's channels lack is an error, said before any work."""
    missing = missing_channels(model, aux_names)
    if missing:
        raise ModelError(f"model needs channels {sorted(missing)} that the input lacks "
                         f"(it has {list(aux_names)})")


def usable(gate: np.ndarray, b: RawBatch, model: SensorModel) -> np.ndarray:
    """The detector's gate where the channels the model uses are finite too: only such samples
    may enter a window (an imported row may lack a value; a NaN must never reach the estimator
    or a checkpoint). The gate already excludes readings that are not finite."""
    cols = [b.aux_names.index(c) for c in model.covariates if c != TIME]
    if cols:
        return gate & np.isfinite(b.aux[:, cols]).all(axis=1)
    return gate
