"""Run a Zenoh router as a Python process (there is no zenohd binary on our package registries).

``recal router`` calls :func:`run_router`; tests and demos start one as a child process with
:func:`start_router_process` (``python -m recal.io.router --listen tcp/127.0.0.1:PORT``).

A router lets clients (``mode: "client"``) reach each other: every sample and query goes
through it. Peers connected to the same router talk to each other only if gossip scouting is
enabled on both sides (the router then introduces them and they connect directly); the router
starts with gossip on for that reason. Gossip travels only over links already open, so it does
not reach beyond the configured endpoints.

Security: by default anyone who reaches the router may publish and query anything. The
ready line says which protections the configuration turns on (``tls=mtls|tls|off``,
``acl=on|off``), and a router that listens beyond loopback without mutual TLS and access
control prints a warning line. ``configs/fleet/router.json5`` is a router with both (Zenoh's
own ``transport/link/tls`` and ``access_control``; certificates from
``configs/fleet/make-certs.sh``).

When the router dies, clients keep running: their puts are silently unmatched, and they
reconnect by themselves once a router listens on the same endpoint again (back-off set by
``connect/retry/*`` in the client's config).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType

import zenoh

from recal.io.bus_config import DEFAULT_ROUTER_ENDPOINT, zenoh_config

__all__ = ["READY_PREFIX", "RouterProcess", "main", "run_router", "security_summary",
           "start_router_process"]

READY_PREFIX = "recal-router ready"
WARNING_PREFIX = "recal-router: warning:"
_LOOPBACK_HOSTS = ("127.", "localhost", "[::1]")
STOPPED_PREFIX = "recal-router stopped"
_POLL_S = 0.2  # how often the router loop checks the stop event (signals are handled between)
_OUTPUT_LINES_KEPT = 200


def run_router(
    listen_endpoints: Sequence[str] | None = None,
    config_file: str | Path | None = None,
    stop_event: threading.Event | None = None,
    *,
    gossip_scouting: bool | None = None,
    out: Callable[[str], None] | None = None,
    parent_pid: int | None = None,
) -> int:
    """Open a Zenoh session in router mode and block until stopped; return an exit code (0).

    ``listen_endpoints`` defaults to ``[tcp/127.0.0.1:7447]`` (or the config file's). Stops
    when ``stop_event`` is set, on SIGINT/SIGTERM when called from the main thread, or when
    ``parent_pid`` is given and this process's parent changes (the parent died). Prints
    ``recal-router ready zid=<zid> listen=<endpoints>`` once listening (tests wait for it) and
    ``recal-router stopped`` at the end. Raises ``zenoh.ZError`` if it cannot listen (port in
    use, bad endpoint).
    """
    emit = out or _print_flush
    if listen_endpoints is None and config_file is None:
        listen_endpoints = [DEFAULT_ROUTER_ENDPOINT]
    config = zenoh_config(
        mode="router",
        listen=listen_endpoints,
        config_file=config_file,
        gossip_scouting=gossip_scouting,
    )
    stop = stop_event if stop_event is not None else threading.Event()
    previous = _install_signal_handlers(stop)
    try:
        session = zenoh.open(config)
        try:
            listen = config.get_json("listen/endpoints")
            tls, acl, exposed = security_summary(config)
            emit(f"{READY_PREFIX} zid={session.zid()} listen={listen} tls={tls} acl={acl}")
            if exposed and (tls != "mtls" or acl != "on"):
                emit(f"{WARNING_PREFIX} listening on {', '.join(exposed)} without mutual TLS "
                     f"and access control: anyone who reaches it may publish and query "
                     f"anything (see configs/fleet/router.json5)")
            while not stop.wait(_POLL_S):
                if parent_pid is not None and os.getppid() != parent_pid:
                    emit("recal-router parent exited")
                    break
        finally:
            session.close()
    finally:
        _restore_signal_handlers(previous)
    emit(STOPPED_PREFIX)
    return 0


def security_summary(config: zenoh.Config) -> tuple[str, str, list[str]]:
    """``(tls, acl, exposed)`` of a router config: tls "mtls" (every listen endpoint is TLS
    and clients must show a certificate), "tls" or "off"; acl "on" or "off"; the listen
    endpoints not on loopback."""
    def get(path: str) -> object:
        raw = config.get_json(path)
        return json.loads(raw) if isinstance(raw, str) else raw

    listen = get("listen/endpoints")
    endpoints = [str(e) for e in listen] if isinstance(listen, list) else []
    all_tls = bool(endpoints) and all(e.startswith(("tls/", "quic/")) for e in endpoints)
    mtls = get("transport/link/tls/enable_mtls") is True
    tls = ("mtls" if mtls else "tls") if all_tls else "off"
    acl = "on" if get("access_control/enabled") is True else "off"
    exposed = [e for e in endpoints
               if not e.split("/", 1)[-1].startswith(_LOOPBACK_HOSTS)]
    return tls, acl, exposed


def _print_flush(line: str) -> None:
    print(line, flush=True)  # flush: a parent process waits for this line on a pipe


def _install_signal_handlers(stop: threading.Event) -> dict[int, object]:
    """Make SIGINT/SIGTERM set ``stop``; only possible from the main thread."""
    if threading.current_thread() is not threading.main_thread():
        return {}

    def handler(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    previous: dict[int, object] = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        previous[signum] = signal.signal(signum, handler)
    return previous


def _restore_signal_handlers(previous: dict[int, object]) -> None:
    for signum, old in previous.items():
        signal.signal(signum, old)  # type: ignore[arg-type]


class RouterProcess:
    """A router running as a child process (``python -m recal.io.router``), for tests and demos.

    Its combined stdout/stderr is read by a daemon thread into a bounded buffer (last 200
    lines, see :attr:`output`), so the child can never block on a full pipe. Use as a context
    manager or call :meth:`stop`; :meth:`kill` simulates a crash (SIGKILL).
    """

    def __init__(
        self,
        listen_endpoints: Sequence[str],
        config_file: str | Path | None = None,
        python: str = sys.executable,
    ) -> None:
        self.listen_endpoints = list(listen_endpoints)
        self.config_file = config_file
        self.python = python
        self.zid: str | None = None
        self._proc: subprocess.Popen[str] | None = None
        self._lines: deque[str] = deque(maxlen=_OUTPUT_LINES_KEPT)
        self._ready = threading.Event()
        self._reader: threading.Thread | None = None

    def command(self) -> list[str]:
        """The command line used to start the child."""
        cmd = [self.python, "-m", "recal.io.router"]
        for endpoint in self.listen_endpoints:
            cmd += ["--listen", endpoint]
        if self.config_file is not None:
            cmd += ["--config", str(self.config_file)]
        # A child left behind by a crashed test run would hold the port; make it follow us.
        cmd += ["--parent-pid", str(os.getpid())]
        return cmd

    def start(self, ready_timeout_s: float = 15.0) -> RouterProcess:
        """Start the child and wait until it prints its ready line; raise RuntimeError if not."""
        if self.alive:
            raise RuntimeError("router process already running")
        self._lines.clear()
        self._ready.clear()
        self.zid = None
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self._proc = subprocess.Popen(
            self.command(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        self._reader = threading.Thread(target=self._read_output, args=(self._proc,), daemon=True)
        self._reader.start()
        if not self._wait_ready(ready_timeout_s):
            output = self.output
            self.kill()
            raise RuntimeError(f"router did not become ready:\n{output}")
        return self

    def _read_output(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip("\n")
            self._lines.append(line)
            if line.startswith(READY_PREFIX):
                self.zid = _field(line, "zid")
                self._ready.set()

    def _wait_ready(self, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._ready.wait(0.05):
                return True
            if self._proc is None or self._proc.poll() is not None:
                return False
        return False

    @property
    def pid(self) -> int | None:
        """The child's process id, if started."""
        return None if self._proc is None else self._proc.pid

    @property
    def alive(self) -> bool:
        """Whether the child is running."""
        return self._proc is not None and self._proc.poll() is None

    @property
    def output(self) -> str:
        """The last lines the child printed."""
        return "\n".join(self._lines)

    def stop(self, timeout_s: float = 5.0) -> int | None:
        """SIGTERM the child, wait up to ``timeout_s``, then SIGKILL; return its exit code."""
        if self._proc is None:
            return None
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self._proc.kill()
        return self._finish()

    def kill(self) -> int | None:
        """SIGKILL the child (a crash, as far as its clients can tell); return its exit code."""
        if self._proc is None:
            return None
        if self._proc.poll() is None:
            self._proc.kill()
        return self._finish()

    def _finish(self) -> int | None:
        assert self._proc is not None
        code = self._proc.wait(5.0)
        if self._reader is not None:
            self._reader.join(2.0)  # the pipe closes with the child, so this ends promptly
        if self._proc.stdout is not None:
            self._proc.stdout.close()
        return code

    def __enter__(self) -> RouterProcess:
        if not self.alive:
            self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


def _field(line: str, name: str) -> str | None:
    for token in line.split():
        if token.startswith(f"{name}="):
            return token.split("=", 1)[1]
    return None


def start_router_process(
    listen_endpoints: Sequence[str],
    config_file: str | Path | None = None,
    ready_timeout_s: float = 15.0,
) -> RouterProcess:
    """Start ``python -m recal.io.router`` listening on ``listen_endpoints``; wait until ready."""
    return RouterProcess(listen_endpoints, config_file).start(ready_timeout_s)


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m recal.io.router", description="Run a Zenoh router (loopback default)."
    )
    parser.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to listen on, repeatable (default {DEFAULT_ROUTER_ENDPOINT})",
    )
    parser.add_argument("--config", metavar="FILE", help="Zenoh JSON5 config file")
    parser.add_argument(
        "--no-gossip",
        action="store_true",
        help="disable gossip scouting (peers then cannot "
        "find each other through this router; clients are unaffected)",
    )
    parser.add_argument(
        "--parent-pid",
        type=int,
        metavar="PID",
        help="exit when this process is no longer our parent (used by RouterProcess)",
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry: parse arguments and run the router until SIGINT/SIGTERM."""
    args = _parse_args(argv)
    return run_router(
        listen_endpoints=args.listen,
        config_file=args.config,
        gossip_scouting=False if args.no_gossip else None,
        parent_pid=args.parent_pid,
    )


if __name__ == "__main__":
    sys.exit(main())
