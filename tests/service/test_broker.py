"""The embedded broker's wait (app/core/broker.py): an idle consumer sleeps on the queue folder's watch and wakes
for a message, not every ``polling_interval``; a consumer whose channel is full, or one without inotify, polls; a
worker that starts to stop ends its consumer's wait.
Counts of wake-ups (voluntary context switches of the waiting thread), never durations, are what is asserted."""

from __future__ import annotations

import multiprocessing
import resource
import sys
import time
from pathlib import Path

import pytest
from kombu import Connection, Exchange, Queue

from app.core import folder_watch

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="inotify is Linux's")


def _connection(folder: Path, polling_interval: float) -> Connection:
    for name in ("q", "c", "claimed"):
        (folder / name).mkdir(exist_ok=True)
    options = {
        "data_folder_in": str(folder / "q"),
        "data_folder_out": str(folder / "q"),
        "control_folder": str(folder / "c"),
        "claimed_folder": str(folder / "claimed"),
        "polling_interval": polling_interval,
    }
    return Connection("filesystem://", transport="app.core.broker:Transport", transport_options=options)


@pytest.fixture
def name(request) -> str:
    """A queue name of the test's own: kombu's filesystem transport keeps the bindings it declared in a
    process-wide state, so a connection to another folder would not write a binding declared before again."""
    return f"jobs-{request.node.name[:40]}"


def _put_later(folder: str, name: str, delay_s: float) -> None:
    time.sleep(delay_s)
    with _connection(Path(folder), 0.01) as conn:
        queue = conn.SimpleQueue(name)
        queue.put({"n": 1})
        queue.close()


def _wakeups(action) -> tuple[int, object]:
    """Voluntary context switches of this thread while ``action()`` runs, and what it returned."""
    before = resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw
    result = action()
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw - before, result


def test_an_idle_consumer_sleeps_until_its_timeout(tmp_path, name):
    with _connection(tmp_path, polling_interval=0.01) as conn:
        queue = conn.SimpleQueue(name)
        with pytest.raises(queue.Empty):  # the first look declares the queue (files written and synced)
            queue.get(timeout=0.05)

        def wait_idle():
            with pytest.raises(queue.Empty):
                queue.get(timeout=1.0)

        wakeups, _ = _wakeups(wait_idle)
        queue.close()
    assert wakeups < 10, wakeups  # kombu's own loop: one a polling interval, about 100


def test_a_message_wakes_a_consumer_whose_polling_interval_is_longer_than_its_wait(tmp_path, name):
    """With a 30 s polling interval a poll could not see a message within the 20 s ``get``: the watch does."""
    with _connection(tmp_path, polling_interval=30.0) as conn:
        queue = conn.SimpleQueue(name)
        producer = multiprocessing.get_context("spawn").Process(target=_put_later, args=(str(tmp_path), name, 0.5))
        producer.start()
        message = queue.get(timeout=20.0)
        producer.join(30)
        assert message.payload == {"n": 1}
        message.ack()
        queue.close()


def test_a_consumer_whose_channel_is_full_polls_at_its_interval(tmp_path, name):
    """A channel at its prefetch limit cannot take the message the folder announces, and nothing announces that
    its task ended: it looks again every ``polling_interval`` (kombu's behaviour)."""
    queue = Queue(name, Exchange(name), name)
    with _connection(tmp_path, polling_interval=0.01) as conn:
        received = []
        with conn.Consumer(queue, callbacks=[lambda body, message: received.append(message)]) as consumer:
            consumer.qos(prefetch_count=1)
            conn.Producer().publish({"n": 1}, exchange=queue.exchange, routing_key=name, declare=[queue])
            conn.drain_events(timeout=5)
            assert len(received) == 1  # unacked: the channel is full
            wakeups, _ = _wakeups(lambda: pytest.raises(TimeoutError, conn.drain_events, timeout=0.5))
            assert wakeups >= 20, wakeups  # it polled (every 10 ms), not slept on the watch
            received[0].ack()


def test_without_inotify_the_consumer_polls_and_still_receives(tmp_path, name, monkeypatch):
    monkeypatch.setattr(folder_watch.sys, "platform", "darwin")
    with _connection(tmp_path, polling_interval=0.01) as conn:
        queue = conn.SimpleQueue(name)
        queue.put({"n": 2})
        wakeups, message = _wakeups(lambda: queue.get(timeout=5.0))
        assert message.payload == {"n": 2}
        message.ack()
        idle, _ = _wakeups(lambda: pytest.raises(queue.Empty, queue.get, timeout=0.5))
        queue.close()
    assert idle >= 20, idle





def test_a_woken_consumer_hands_back_to_its_caller_before_its_timeout(tmp_path, name):
    """Celery's loop drains events 2 s at a time and reads its stop flag between them: a worker that is stopping
    (worker.tasks wakes every watch on ``worker_shutting_down``) must not sit out the rest of the wait."""
    import threading

    queue = Queue(name, Exchange(name), name)
    with _connection(tmp_path, polling_interval=30.0) as conn, conn.Consumer(queue, callbacks=[]):
        raised = []

        def drain():
            try:
                conn.drain_events(timeout=60.0)
            except TimeoutError:
                raised.append(True)

        waiter = threading.Thread(target=drain)
        waiter.start()
        time.sleep(0.3)  # let it reach the wait (a wake before it is kept for the next wait anyway)
        folder_watch.wake_all()
        waiter.join(10)
        assert not waiter.is_alive() and raised == [True]


def test_the_worker_wakes_its_watches_when_it_starts_to_stop():
    from celery.signals import worker_shutting_down

    from worker import tasks

    assert any(receiver() is tasks._wake_idle_consumer for _, receiver in worker_shutting_down.receivers)
