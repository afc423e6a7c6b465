"""The import monitor (:mod:`voxnerf.data.importers.monitor`): progress spans nest, a stop request raises, and a
count watch reports a blocking call's progress and turns a stop request into the call's cancellation."""

from __future__ import annotations

import threading
import time

import pytest

from voxnerf.data.importers.monitor import WATCH_PERIOD_S, CountWatch, ImportCancelled, ImportMonitor
from voxnerf.data.importers.sfm import sequential_pairs


def test_spans_nest_and_clamp():
    seen = []
    monitor = ImportMonitor(report=lambda step, fraction: seen.append((step, fraction)))
    part = monitor.within(0.2, 1.0).within(0.5, 1.0)  # 0.6 .. 1.0 of the whole
    part.step("half", 0.5)
    part.step("beyond", 7.0)
    monitor.within(0.0, 0.2).step("before", -1.0)
    assert seen == [("half", pytest.approx(0.8)), ("beyond", 1.0), ("before", 0.0)]


def test_check_raises_once_asked_to_stop():
    asked = threading.Event()
    monitor = ImportMonitor(should_stop=asked.is_set).within(0.1, 0.9)
    monitor.check()
    asked.set()
    with pytest.raises(ImportCancelled, match="cancelled"):
        monitor.check()


def test_a_default_monitor_reports_nowhere_and_never_stops():
    ImportMonitor().step("anything", 0.5)
    ImportMonitor().check()


class _Token:
    def __init__(self) -> None:
        self.cancelled = threading.Event()

    def cancel(self) -> None:
        self.cancelled.set()


def test_a_watch_reports_the_count_before_and_after_the_call_and_reads_nothing_while_it_runs():
    reads = []  # when the count was read: never while the call runs (its writer threads abort on a locked database)
    running = threading.Event()
    seen = []
    monitor = ImportMonitor(report=lambda step, fraction: seen.append((step, fraction)))

    def count() -> int:
        reads.append(running.is_set())
        return 4

    with CountWatch(monitor, count, 8, "extracting", "images", _Token(), before=2):
        running.set()
        time.sleep(3 * WATCH_PERIOD_S)
        running.clear()
    assert seen == [("extracting: 2 of 8 images", 0.25), ("extracting: 4 of 8 images", 0.5)]
    assert reads == [False]


def test_a_count_that_cannot_be_read_after_the_call_reports_nothing_more():
    seen = []
    with CountWatch(ImportMonitor(report=lambda *step: seen.append(step)), lambda: None, 4, "x", "images", _Token()):
        pass
    assert seen == [("x: 0 of 4 images", 0.0)]


def test_a_count_past_the_total_is_reported_as_the_total():
    seen = []
    with CountWatch(ImportMonitor(report=lambda *step: seen.append(step)), lambda: 9, 4, "x", "images", _Token()):
        pass
    assert seen[-1] == ("x: 4 of 4 images", 1.0)


def test_a_watch_cancels_the_token_when_asked_to_stop_and_reports_nothing_more_after_an_error():
    token, asked, seen = _Token(), threading.Event(), []
    monitor = ImportMonitor(report=lambda *step: seen.append(step), should_stop=asked.is_set)
    with pytest.raises(InterruptedError), CountWatch(monitor, lambda: 1, 10, "matching", "pairs", token):
        asked.set()
        assert token.cancelled.wait(5.0)
        raise InterruptedError("cancelled")  # what pycolmap raises once cancelled
    assert seen == [("matching: 0 of 10 pairs", 0.0)]


@pytest.mark.parametrize(("n", "pairs"), [(0, 0), (1, 0), (2, 1), (3, 3), (5, 8), (25, 94)])
def test_sequential_pairs_counts_the_quadratic_gaps(n, pairs):
    # gaps 1, 2, 4, 8, 16...: 25 images give 24 + 23 + 21 + 17 + 9 pairs (what COLMAP 4.2 matched on them)
    assert sequential_pairs(n) == pairs


def test_sequential_pairs_without_quadratic_overlap_counts_the_next_ones():
    assert sequential_pairs(25, overlap=15, quadratic=False) == 15 * 10 + sum(range(1, 15))
