"""The names of the files a scene directory and a run directory hold: one place, no torch (the API imports it).

A scene directory holds ``transforms.json`` (SCENE_FORMAT.md) beside its images; a run directory holds the
checkpoint, the report and ``eval/<split>/<frame>.png``.
"""

TRANSFORMS = "transforms.json"
CHECKPOINT = "checkpoint.pt"
REPORT = "report.json"
EVAL_DIR = "eval"
