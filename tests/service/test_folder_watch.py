"""Waiting on a folder (app/core/folder_watch.py), ending such a wait early (a worker that is stopping), and the
API's wait for a render's outcome on the embedded broker (app/core/render_results.py), which sleeps on one. Counts
of wake-ups (voluntary context switches of the waiting thread) and what arrived are asserted, never durations."""

from __future__ import annotations

import os
import resource
import select
import sys
import threading
import time

import pytest

from app.core import folder_watch, render_results
from app.core.folder_watch import FolderWatch
from app.core.render_results import RenderOutcome, wait_outcome, write_outcome

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify is Linux's")


def _wakeups(action) -> tuple[int, object]:
    """Voluntary context switches of this thread while ``action()`` runs, and what it returned."""
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw
    result = action()
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw - before, result


def _readable(watch: FolderWatch) -> bool:
    return bool(select.select([watch.fd], [], [], 0)[0])


def test_the_watch_sleeps_and_wakes_for_a_file_renamed_in(tmp_path):
    with FolderWatch.open(tmp_path) as watch:
        wakeups, arrived = _wakeups(lambda: watch.wait(0.3))
        assert not arrived and wakeups <= 2, wakeups  # one sleep for the whole timeout
        (tmp_path / ".m.tmp").write_bytes(b"x")  # closed after writing: an event, read and dropped here
        assert watch.wait(0.0)
        os.replace(tmp_path / ".m.tmp", tmp_path / "m.msg")
        assert _readable(watch)  # the rename was announced before anyone waited
        assert watch.wait(5.0) and not _readable(watch)  # and the wait read every event


def test_a_missing_folder_or_another_system_gives_no_watch(tmp_path, monkeypatch):
    assert FolderWatch.open(tmp_path / "absent") is None
    monkeypatch.setattr(folder_watch.sys, "platform", "darwin")
    assert FolderWatch.open(tmp_path) is None


def _write_later(results_dir, request_id: str, delay_s: float) -> threading.Thread:
    def write() -> None:
        time.sleep(delay_s)
        write_outcome(results_dir, request_id, RenderOutcome(200, "image/png", b"png bytes"))

    thread = threading.Thread(target=write)
    thread.start()
    return thread


def test_a_render_outcome_wakes_the_api_s_wait(tmp_path, monkeypatch):
    """With a 30 s poll a waiter that looked in vain first would sleep 30 s: the watch wakes it at the outcome."""
    monkeypatch.setattr(render_results, "POLL_INTERVAL_S", 30.0)
    got = {}

    def wait() -> None:
        got["outcome"] = wait_outcome(tmp_path, "r1", 60.0)

    waiter = threading.Thread(target=wait)
    waiter.start()
    _write_later(tmp_path, "r1", 0.5).join()
    waiter.join(15.0)
    assert not waiter.is_alive(), "the wait slept on after the outcome was written"
    assert got["outcome"].data == b"png bytes" and got["outcome"].status == 200
    assert list(tmp_path.iterdir()) == []  # both files taken


def test_another_request_s_outcome_does_not_end_the_wait(tmp_path):
    other = _write_later(tmp_path, "other", 0.1)
    mine = _write_later(tmp_path, "mine", 0.6)
    outcome = wait_outcome(tmp_path, "mine", 20.0)
    other.join()
    mine.join()
    assert outcome is not None and outcome.data == b"png bytes"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.json", "other.out"]  # left for its own waiter


def test_a_wait_with_no_outcome_times_out(tmp_path):
    assert wait_outcome(tmp_path, "never", 0.3) is None


def test_without_inotify_the_wait_polls_and_still_finds_the_outcome(tmp_path, monkeypatch):
    monkeypatch.setattr(folder_watch.sys, "platform", "darwin")
    writer = _write_later(tmp_path, "r2", 0.3)
    wakeups, outcome = _wakeups(lambda: wait_outcome(tmp_path, "r2", 20.0))
    writer.join()
    assert outcome is not None and outcome.data == b"png bytes"
    assert wakeups >= 20, wakeups  # it looked every POLL_INTERVAL_S


def test_wake_ends_a_watch_s_wait_and_says_so(tmp_path):
    with FolderWatch.open(tmp_path) as watch:
        outcome = []
        waiter = threading.Thread(target=lambda: outcome.append((watch.wait(60.0), watch.woken)))
        waiter.start()
        watch.wake()
        waiter.join(10)
        assert not waiter.is_alive() and outcome == [(False, True)]  # no file came; it was woken
        assert (watch.wait(0.01), watch.woken) == (False, False)  # the wake was used up: this wait timed out
        (tmp_path / "a.msg").write_bytes(b"1")
        assert (watch.wait(5.0), watch.woken) == (True, False)

def test_a_closed_watch_writes_nothing_when_woken(tmp_path):
    watch = FolderWatch.open(tmp_path)
    wake_fd = watch._wake_fd
    watch.close()
    reader, writer = os.pipe()  # likely given the closed eventfd's number
    try:
        watch.wake()
        folder_watch.wake_all()
        os.set_blocking(reader, False)
        with pytest.raises(BlockingIOError):
            os.read(reader, 8)  # nothing was written into whatever file has that number now
        assert wake_fd >= 0 and watch not in folder_watch._OPEN
    finally:
        os.close(reader)
        os.close(writer)

def test_wake_all_wakes_this_process_s_watches_only(tmp_path):
    with FolderWatch.open(tmp_path) as mine, FolderWatch.open(tmp_path) as inherited:
        inherited.pid = -1  # as a forked child sees its parent's watch
        folder_watch.wake_all()
        assert (mine.wait(0.0), mine.woken) == (False, True)
        assert (inherited.wait(0.0), inherited.woken) == (False, False)
