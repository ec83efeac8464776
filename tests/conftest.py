"""Shared pytest setup. Qt tests draw offscreen: no display needed (CI, SSH)."""

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
