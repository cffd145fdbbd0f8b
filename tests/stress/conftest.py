"""Stress suite helpers: a watchdog so that an endless kernel loop fails the run instead of hanging it."""

from __future__ import annotations

import faulthandler
import sys
from pathlib import Path

import pytest

# tests/checks.py is imported as a top-level module by the main suite (rootdir-relative sys.path)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: seconds one stress test may run before the process is dumped and killed (a hung native kernel
#: cannot be interrupted from Python)
WATCHDOG_S = 300


@pytest.fixture(autouse=True)
def _watchdog():
    faulthandler.dump_traceback_later(WATCHDOG_S, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()
