"""Cameras: the rules a camera follows, rays through pinholes and lenses, camera paths, and pose refinement.

Modules: :mod:`~voxnerf.cameras.rules` (pose and intrinsics rules, numpy only), :mod:`~voxnerf.cameras.rays`
(ray generation), :mod:`~voxnerf.cameras.lens` (OpenCV lens models), :mod:`~voxnerf.cameras.paths` (camera paths
for videos, numpy only), :mod:`~voxnerf.cameras.pose_refinement` (a rigid correction per training image),
:mod:`~voxnerf.cameras.neighbours` (the training cameras nearest a pose). Nothing is imported here: the API
process imports the numpy-only modules without torch.
"""

from voxnerf import old_module_names

# ``from voxnerf.cameras import X`` for the names of the old flat module, which is now voxnerf.cameras.rays
__getattr__ = old_module_names(__name__, "voxnerf.cameras.rays")
