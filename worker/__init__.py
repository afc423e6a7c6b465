"""Celery workers of the VoxNeRF service: a ``train`` queue (one job per process) and a ``render`` queue.

A worker holds the tasks (:mod:`worker.tasks`: training with its lease and progress writer, rendering with its
model cache) and how a worker process starts (:mod:`worker.run`). Everything it shares with the API (settings,
job store, storage, queues, broker, render results, the render request) is in :mod:`app.core`.
"""
