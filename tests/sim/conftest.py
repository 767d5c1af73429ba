"""Shared fixtures of the simulator tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True, scope="module")
def _sumo_cache(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """One generated-SUMO-scenario cache per test module, never the user's (``CV2X_MARL_SUMO_CACHE``)."""
    from cv2x_marl.sim.sumo import CACHE_ENV

    mp = pytest.MonkeyPatch()
    mp.setenv(CACHE_ENV, str(tmp_path_factory.mktemp("sumo-cache")))
    yield
    mp.undo()
