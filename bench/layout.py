"""recal's modules by their names in this layout, else by their names before the package layout.

The benches that run an older tree beside this one (``--old``, ``--old-src``) import the same
names from both; a tree from before the packages (``recal.node``, ``recal.sim``, ...) has them
at the package root.
"""

from __future__ import annotations

import importlib
from types import ModuleType


def module(new: str, *old: str) -> ModuleType:
    """Import ``new`` (``recal.sim.wearer``), or the first of ``old`` (``recal.sim``) that is
    there where ``new`` is absent (a module split later has more than one older name)."""
    for name in (new, *old[:-1]):
        try:
            return importlib.import_module(name)
        except ModuleNotFoundError:
            pass
    return importlib.import_module(old[-1])
