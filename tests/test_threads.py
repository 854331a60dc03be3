"""The thread count a run's own parallel work uses (pmvir.threads)."""

from __future__ import annotations

import os

import pytest

from pmvir.geometry.sfm.matching import colmap_threads
from pmvir.threads import configured_threads, usable_threads


@pytest.mark.parametrize(("value", "expected"), [("3", 3), (" 2 ", 2), ("0", None), ("-1", None), ("two", None), ("", None)])
def test_only_a_positive_omp_num_threads_counts(monkeypatch, value: str, expected: int | None) -> None:
    monkeypatch.setenv("OMP_NUM_THREADS", value)
    assert configured_threads() == expected
    assert usable_threads() == (expected or len(os.sched_getaffinity(0)))
    assert colmap_threads() == (expected or -1)  # COLMAP's -1: every core
