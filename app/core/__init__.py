"""The service core: what the API (``app``) and the workers (``worker``) share, and the only place they meet.

- :mod:`app.core.settings`: every ``VOXNERF_*`` setting (:class:`Settings`, the one :func:`get_settings`);
- :mod:`app.core.db`, :mod:`app.core.models`: database engine and sessions, the tables;
- :mod:`app.core.progress`: which job columns carry training progress, derived from the engine's
  :class:`voxnerf.training.records.ProgressEvent`;
- :mod:`app.core.lease`: the lease lifecycle every kind of queued work shares (claim with a fence, lease renewal,
  progress, cancel, finish, stale sweep, re-send of lost messages, worker deaths);
- :mod:`app.core.jobstore`: every read and write of scenes and training jobs (their kind of work: ``JOBS``);
- :mod:`app.core.outputs`: output jobs (their kind of work: ``OUTPUTS``), their files, which jobs can be rendered
  from;
- :mod:`app.core.storage`: scenes and runs in an object store (``VOXNERF_STORAGE_URL``);
- :mod:`app.core.celery_app`: task and queue names, the Celery app factory (nothing is built at import time);
- :mod:`app.core.dispatch`: publishing train, render and output tasks, and the sweep over every kind of work
  (requeueing rows whose worker died, re-sending lost messages);
- :mod:`app.core.broker`: the embedded filesystem broker transport;
- :mod:`app.core.render_results`: how a render's outcome travels from the render worker back to the API;
- :mod:`app.core.render_request`: the render request both the API and the render task parse;
- :mod:`app.core.tokens`: named API tokens, the principal of a request, the scope rule, per-token queue limits and
  webhook secrets.

Nothing here imports the API modules, the workers, or torch (tests/test_architecture.py).
"""
