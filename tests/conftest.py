"""Shared pytest setup. Qt tests draw offscreen: no display needed (CI, SSH)."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import sys  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _garbage_collected_between_tests():
    """A window test turns Python's automatic collection off for its process (the window collects
    on its GUI thread: foamlab.gui.background); the tests after it in the same worker collect here,
    on the main thread, by the same thresholds (a cheap count check when there is nothing to do)."""
    yield
    background = sys.modules.get("foamlab.gui.background")   # only where a test imported the window
    if background is not None:
        background.collect_pending_garbage()
