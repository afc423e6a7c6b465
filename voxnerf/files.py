"""The names of the files a scene directory and a run directory hold: one place, no torch (the API imports it).

A scene directory holds ``transforms.json`` (docs/scene-format.md) beside its images; a run directory holds the
checkpoint, the report, ``eval/<split>/<frame>.png``, when the run fused one its prior, and when it refined
the training poses those poses.
"""

TRANSFORMS = "transforms.json"
CHECKPOINT = "checkpoint.pt"
REPORT = "report.json"
EVAL_DIR = "eval"
REFINED_POSES = "refined_poses.json"  # the training frames' poses after pose refinement, when the run learnt them
FUSED_PRIOR = "prior_tsdf.ply"  # the prior a run fused from the scene's depth maps, when it made one
