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

from recal.config.settings import RediscoveryConfig
from recal.core.pipeline import Pipeline

__all__ = ["Rediscovery", "RediscoverySchedule"]

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


class RediscoverySchedule:
    """When a node reruns discovery: every ``[discovery] every_h`` device hours, one run at a
    time, its result taken ``adopt_after_s`` device seconds after it started.

    ``next_us``: the device time of the next run (None: scheduled from the data).
    """

    def __init__(self, cfg: RediscoveryConfig, next_us: int | None = None) -> None:
        self.cfg = cfg
        self.next_us = next_us
        self.run: Rediscovery | None = None  # a run in its thread

    @property
    def due_us(self) -> int | None:
        """The next run as a checkpoint keeps it: a run still going is not saved, it is due
        again at once on restart, rather than every_h after it, which a daemon restarted more
        often than every_h would otherwise never reach."""
        return self.run.started_us if self.run is not None else self.next_us

    def poll(self, sensor_id: str, pipe: Pipeline | None, last_t_us: int | None
             ) -> Rediscovery | None:
        """Start a run on a copy of ``pipe``'s window buffer when one is due; the run whose
        result is to be adopted now, else None."""
        cfg = self.cfg
        if not cfg.enabled or pipe is None or last_t_us is None:
            return None
        if self.run is not None:
            if last_t_us >= self.run.due_us:
                run, self.run = self.run, None
                return run
            return None  # one run at a time
        every_us = round(cfg.every_h * 3.6e9)
        if self.next_us is None:
            self.next_us = last_t_us + every_us
        if last_t_us < self.next_us:
            return None
        self.next_us = last_t_us + every_us
        windows = pipe.buffer.windows()  # fresh arrays: the thread's own copy
        if not pipe.bootstrapped or len(windows) < cfg.min_windows:
            return None
        self.run = Rediscovery.start(sensor_id, windows, pipe, last_t_us,
                                     last_t_us + round(cfg.adopt_after_s * 1e6), cfg.blocks)
        if cfg.adopt_after_s <= 0:
            run, self.run = self.run, None
            return run
        return None
