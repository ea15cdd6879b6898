"""Shared test set-up: headless plotting, figures closed after each test."""

from __future__ import annotations

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("TQDM_DISABLE", "1")

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import sys

    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")


def pytest_collection_modifyitems(config, items):
    """CAD exports and notebook runs take tens of seconds each: they count as slow, so
    ``make test-fast`` (``-m "not slow"``) skips them while ``make test`` still runs them."""
    for item in items:
        if item.get_closest_marker("cad") or item.get_closest_marker("notebook"):
            item.add_marker(pytest.mark.slow)
