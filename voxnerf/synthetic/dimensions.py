"""The default room's size, which the geometry, the textures' height-dependent patterns and the camera path share.

World frame: metres, +Z up.
"""

from __future__ import annotations

ROOM_SIZE: tuple[float, float, float] = (5.0, 4.0, 2.6)
"""Room width (x), depth (y) and height (z) in metres."""
