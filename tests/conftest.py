"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway_process import GatewayProcess
from recal.commands.demo import free_port
from recal.io.router import RouterProcess

#: Modules whose every test checks numeric results that BLAS and numpy's SIMD kernels could
#: move in the last bits (the streaming windows, statuses and sigma, replay, alignment,
#: discovery on measured data, hindsight): marked ``float_sensitive``, which .ci/run runs a
#: second time under an emulated other CPU. Single tests elsewhere carry the marker
#: themselves. Chosen to keep that second run short (the whole of test_core and
#: test_core_api would triple it).
FLOAT_SENSITIVE_MODULES = frozenset({
    "test_windower", "test_status", "test_replay", "test_replay_joined", "test_alignment",
    "test_discovery_real", "test_hindsight"})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.module is not None and item.module.__name__ in FLOAT_SENSITIVE_MODULES:
            item.add_marker(pytest.mark.float_sensitive)


@pytest.fixture
def plain_router() -> Iterator[str]:
    """A `recal router` child process on 127.0.0.1 without access control (no fleet config):
    only the node stands between a rogue and its state."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = RouterProcess([endpoint]).start()
    try:
        yield endpoint
    finally:
        proc.stop()


@pytest.fixture
def children() -> Iterator[list[GatewayProcess]]:
    """Gateway processes a test started; any still running at the end are killed."""
    procs: list[GatewayProcess] = []
    yield procs
    for gp in procs:
        gp.kill()


@pytest.fixture(autouse=True)
def state_home(tmp_path_factory: pytest.TempPathFactory,
               monkeypatch: pytest.MonkeyPatch) -> Path:
    """The platform state folder (recal.config.settings.default_state_dir), where a config without
    ``[checkpoint] dir`` keeps checkpoints and locks, in a folder of the test's own: never the
    user's, never shared with another test (or a child process it starts)."""
    home = tmp_path_factory.mktemp("state")
    monkeypatch.setenv("XDG_STATE_HOME", str(home))
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    return home / "recal"
