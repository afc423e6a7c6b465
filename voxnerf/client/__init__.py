"""The VoxNeRF service's Python client (:mod:`voxnerf.client.api`) and the ``voxnerf remote`` commands that use it
(:mod:`voxnerf.client.commands`). The only part of ``voxnerf`` that imports the service's code: the pydantic
models of its requests and answers (``app.schemas``, ``app.core.render_request``), so both sides check the same
rules (tests/test_architecture.py holds the engine to that)."""

from voxnerf.client.api import DEFAULT_URL, ApiError, Client, Event, Progress

__all__ = ["DEFAULT_URL", "ApiError", "Client", "Event", "Progress"]
