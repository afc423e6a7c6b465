"""What a failed capture import or output says (worker/imports.py, worker/outputs.py): a disk that filled up under
it says so, however deep in the exception chain the ``ENOSPC`` / ``EDQUOT`` lies; the engine's own refusals stay
as they are; anything else is an internal error. (A real full disk under a training job is exercised with real
processes in test_worker_disk_full.py.)"""

from __future__ import annotations

import errno
from types import SimpleNamespace

import pytest

from voxnerf.errors import SceneError, VoxNeRFError
from worker import imports, outputs
from worker.disk_full import DISK_FULL, disk_full_message

ROW = SimpleNamespace(id="0" * 32, kind="video")
FULL = OSError(errno.ENOSPC, "No space left on device")


def _wrapped_in_scene_error() -> SceneError:
    try:
        try:
            raise FULL
        except OSError as err:
            raise SceneError("scene/images/frame_00001.jpg", "cannot write") from err
    except SceneError as err:
        return err


@pytest.mark.parametrize("why_failed", [imports._why_failed, outputs._why_failed])
@pytest.mark.parametrize("err", [FULL, OSError(errno.EDQUOT, "Disk quota exceeded"), _wrapped_in_scene_error()])
def test_a_full_disk_is_said_as_such(why_failed, err):
    message = why_failed(ROW, err)
    assert message.startswith(DISK_FULL) and "free space" in message
    assert "internal error" not in message


@pytest.mark.parametrize("why_failed", [imports._why_failed, outputs._why_failed])
def test_the_engines_refusals_stay_as_they_are(why_failed):
    message = why_failed(ROW, SceneError("capture.bag", "no camera topic"))
    assert "capture.bag: no camera topic" in message and not message.startswith(DISK_FULL)


@pytest.mark.parametrize("why_failed", [imports._why_failed, outputs._why_failed])
def test_anything_else_is_an_internal_error(why_failed):
    assert why_failed(ROW, KeyError("x")) == "internal error: KeyError: 'x'"
    assert why_failed(ROW, OSError(errno.EACCES, "Permission denied")).startswith("internal error: PermissionError")


def test_the_message_names_what_was_being_written():
    assert disk_full_message(FULL, "the scene was written") == f"{DISK_FULL} while the scene was written " \
        "(No space left on device)"
    assert disk_full_message(VoxNeRFError("no"), "x") is None
