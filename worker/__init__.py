"""Celery workers of the VoxNeRF service: a ``train`` queue (one job per process) and a ``render`` queue.

A worker holds the tasks (:mod:`worker.tasks`: training with its lease and progress writer, rendering with its
model cache) and how a worker process starts (:mod:`worker.run`). Everything it shares with the API (settings,
job store, storage, queues, broker, render results, the render request) is in :mod:`app.core`.
"""

import os

# Before torch (and its OpenMP runtime) loads: OpenMP threads that wait sleep instead of spinning. A worker
# shares the machine's cores with the other workers (the embedded service runs train, render and outputs
# workers side by side); spinning threads of one then hold the cores the others' threads wait for, and every
# parallel operation stalls until the scheduler runs both. docs/performance.md ("Render paths") measures it.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
