"""Shared fixtures and the test layers.

Layers (markers, registered in pyproject.toml):

- ``unit``: one module or function, in process, no bus, no daemon (the default: every test
  without ``bus`` or ``e2e`` is marked ``unit`` here);
- ``bus``: frames between processes (shared-memory ring, pipe, ``udp_multicast`` in a private
  network namespace) and the simulated drives;
- ``e2e``: the whole daemon (hot-loop process, simulated drives) behind its socket or CLI;
- ``slow``: takes more than a few seconds; ``pytest -m "not slow"`` is the quick loop;
- ``serial``: starts processes or keeps time (every ``bus``/``e2e``/``netns`` test, and the unit modules
  marked so): run alone, never beside other tests.  The README's test command runs the rest on two
  workers (``pytest -n 2 -m "not serial"``, pytest-xdist), then these one at a time (``-m serial``).

Data that lives outside the repository (``../shared``) is reached through the fixtures below,
which skip with the reason where it is absent (a user's fresh clone).
"""
from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
LAYERS = ("unit", "bus", "e2e")


def pytest_collection_modifyitems(config, items):
    for item in items:
        if not any(item.get_closest_marker(m) for m in ("bus", "e2e")):
            item.add_marker(pytest.mark.unit)
        if any(item.get_closest_marker(m) for m in ("bus", "e2e", "netns")):
            item.add_marker(pytest.mark.serial)


def _shared(sub: str) -> Path:
    path = SHARED_DATA / sub
    if not path.is_dir():
        pytest.skip(f"shared data {path} is absent (../shared/data/{sub} is not checked out next to the repository)")
    return path


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository's top folder."""
    return REPO


@pytest.fixture(scope="session")
def jugglebot_dir() -> Path:
    """../shared/data/jugglebot (real hexapod measurements); skips where absent."""
    return _shared("jugglebot")


@pytest.fixture(scope="session")
def gcode_corpus_dir() -> Path:
    """../shared/data/gcode (real LinuxCNC programs); skips where absent."""
    return _shared("gcode")


@pytest.fixture(scope="session")
def default_cfg():
    """The embedded default machine (config/default.toml), loaded once."""
    from hexacnc.config import load_config
    return load_config(None)
