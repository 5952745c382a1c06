"""Effect discovery on a live node's buffer, in a thread of its own.

``[discovery] every_h`` makes a :class:`recal.node.node.CalibrationNode` rerun effect discovery
(`recal.core.discovery`) on a copy of its window buffer now and then; the run takes seconds,
so it goes to a daemon thread and the node takes its result ``adopt_after_s`` device seconds
later. The core is pure, so the thread shares nothing with the node's pipeline. The method:
docs/design.md (effect discovery).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import numpy as np

from recal.core.pipeline import Pipeline

__all__ = ["Rediscovery"]

log = logging.getLogger(__name__)


class Rediscovery:
    """One effect-discovery run on a copy of a node's buffer, in a daemon thread (the core is
    pure: it shares nothing with the node's pipeline); `result` waits for it."""

    def __init__(self, started_us: int, due_us: int, model_names: tuple[str, ...]) -> None:
        self.started_us = started_us
        self.due_us = due_us
        self.model_names = model_names
        self._done = threading.Event()
        self._result: Any = None

    @classmethod
    def start(cls, sensor_id: str, windows: Any, pipe: Pipeline, started_us: int,
              due_us: int, blocks: int) -> Rediscovery:
        # imported here, not at the top: discovery is off by default, and every daemon and
        # replay would otherwise load its four modules at start (~15 ms)
        from recal.core import discovery

        run = cls(started_us, due_us, pipe.model.names)
        args = (windows, pipe.aux_names, pipe.t0_us or 0, pipe.model, pipe.params.copy(),
                discovery.DiscoveryConfig(blocks=blocks))

        def work() -> None:
            try:
                run._result = discovery.discover_pipeline(*args)
            except Exception as exc:  # reported as discovery_failed: the waiter must wake
                if not isinstance(exc, (ValueError, np.linalg.LinAlgError)):
                    log.exception("rediscovery of %s failed", sensor_id)
                run._result = exc
            finally:
                run._done.set()

        threading.Thread(target=work, name=f"recal-discover-{sensor_id}", daemon=True).start()
        return run

    def result(self) -> Any:
        self._done.wait()
        return self._result
