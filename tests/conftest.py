"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway_process import GatewayProcess


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
    """The platform state folder (recal.config.default_state_dir), where a config without
    ``[checkpoint] dir`` keeps checkpoints and locks, in a folder of the test's own: never the
    user's, never shared with another test (or a child process it starts)."""
    home = tmp_path_factory.mktemp("state")
    monkeypatch.setenv("XDG_STATE_HOME", str(home))
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    return home / "recal"
