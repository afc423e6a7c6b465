"""Celery workers of the VoxNeRF service: a ``train`` queue (one job per process), a ``render`` queue and an
``outputs`` queue.

A worker holds the tasks (:mod:`worker.tasks`, the Celery side of every kind of work) and the work of each kind,
which loads the engine (:mod:`worker.training` with its progress writer, :mod:`worker.imports`,
:mod:`worker.rendering`, :mod:`worker.outputs`: videos, meshes, point clouds), what each task holds its work with
(:mod:`worker.lease`), the models a process keeps loaded (:mod:`worker.model_cache`) and how a worker process starts
(:mod:`worker.run`, which also chooses how the process's OpenMP threads wait before torch loads) and ends with the
``voxnerf serve`` that started it (:mod:`worker.parent_watch`). Everything it shares with the API (settings, job
store, storage, queues, broker, render results, the render request) is in :mod:`app.core`.
"""
