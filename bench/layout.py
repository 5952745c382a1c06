"""recal's modules by their names in this layout, else by their names before the package layout.

The benches that run an older tree beside this one (``--old``, ``--old-src``) import the same
names from both; a tree from before the packages (``recal.node``, ``recal.sim``, ...) has them
at the package root.
"""

from __future__ import annotations

import importlib
from types import ModuleType


def module(new: str, old: str) -> ModuleType:
    """Import ``new`` (``recal.sim.wearer``), or ``old`` (``recal.sim``) where ``new`` is absent."""
    try:
        return importlib.import_module(new)
    except ModuleNotFoundError:
        return importlib.import_module(old)
