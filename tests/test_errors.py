"""voxnerf.errors: one-line messages naming file and key, and the classes callers catch."""

from __future__ import annotations

from pathlib import Path

import pytest

from voxnerf.errors import RunError, SceneError, TrainingDiverged, VoxNeRFError


def test_scene_error_names_file_and_key():
    err = SceneError(Path("/s/transforms.json"), "must be positive", key="frames[3].fl_x")
    assert str(err) == "/s/transforms.json: frames[3].fl_x: must be positive"
    assert (err.file, err.key, err.message) == ("/s/transforms.json", "frames[3].fl_x", "must be positive")


def test_scene_error_without_key_names_the_file_alone():
    assert str(SceneError("prior.ply", "contains no geometry")) == "prior.ply: contains no geometry"


@pytest.mark.parametrize(("cls", "builtin"), [(SceneError, ValueError), (RunError, ValueError),
                                              (TrainingDiverged, RuntimeError)])
def test_every_error_is_a_voxnerf_error_and_its_builtin_kind(cls, builtin):
    err = cls("f", "m") if cls is SceneError else cls("m")
    assert isinstance(err, VoxNeRFError) and isinstance(err, builtin)
