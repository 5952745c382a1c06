"""Per-file functions for the runner's tests, in a module of their own: a spawned worker
imports the module of the function it runs, and this one is light."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any


def dies_on_some(job: Any) -> dict[str, str]:
    """A per-file function whose process ends abruptly on files named die*, as one killed
    (out of memory) or crashed in a library would."""
    if Path(job.path).name.startswith("die"):
        os._exit(3)
    return {"path": job.rel, "status": "ok"}
