"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from gateway_process import GatewayProcess


@pytest.fixture
def children() -> Iterator[list[GatewayProcess]]:
    """Gateway processes a test started; any still running at the end are killed."""
    procs: list[GatewayProcess] = []
    yield procs
    for gp in procs:
        gp.kill()
