"""The core's public API (`recal.core.__all__`): every name is there, is the very object its
home module defines, and importing any core module alone works whatever was imported first."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

import recal.core

#: Names without a __module__ (constants) and the module that defines them.
CONSTANTS = {"TIME": "recal.core.covariates", "EFFECT_KINDS": "recal.core.effects"}

CORE_MODULES = sorted(m.name for m in pkgutil.iter_modules(recal.core.__path__, "recal.core."))


def _home(name: str, obj: object) -> str:
    return CONSTANTS.get(name) or obj.__module__  # type: ignore[attr-defined]


@pytest.mark.parametrize("name", recal.core.__all__)
def test_every_public_name_is_its_home_modules_object(name: str) -> None:
    obj = getattr(recal.core, name)
    home = importlib.import_module(_home(name, obj))
    assert home.__name__.startswith("recal.core."), f"{name} comes from {home.__name__}"
    assert getattr(home, name) is obj
    assert name in home.__all__, f"{home.__name__} does not list {name} in __all__"


def test_all_lists_every_name_once_and_only_public_ones() -> None:
    names = recal.core.__all__
    assert len(names) == len(set(names))
    assert not [n for n in names if n.startswith("_")]
    # the entry points a newcomer looks for first
    assert {"Pipeline", "PipelineConfig", "SensorModel", "Prior", "make_effect", "discover",
            "DiscoveryConfig", "DiscoveryResult", "Status"} <= set(names)


def test_each_core_module_imports_alone_in_a_fresh_interpreter() -> None:
    """core/__init__ imports the submodules: importing one of them first must not meet a
    half-initialised module (an import cycle inside the core)."""
    assert len(CORE_MODULES) >= 15
    code = ("import importlib, sys\n"
            "for m in sys.argv[1:]:\n"
            "    importlib.import_module(m)\n")
    for first in CORE_MODULES:
        rest = [m for m in CORE_MODULES if m != first]
        r = subprocess.run([sys.executable, "-c", code, first, *rest],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, f"importing {first} first: {r.stderr[-2000:]}"
