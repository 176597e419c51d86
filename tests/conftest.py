"""Shared test set-up: float64, the persistent compilation cache, and shared paths."""

from __future__ import annotations

import os
from pathlib import Path

import diffgyro

diffgyro.enable_x64()
diffgyro.enable_compilation_cache(os.environ.get("DIFFGYRO_CACHE_DIR"))

TESTS = Path(__file__).parent
DATA = TESTS / "data"
ROOT = TESTS.parent
