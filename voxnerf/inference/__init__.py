"""Inference: what a trained run is used for. Rendering any pose (the full and the fast path), evaluation and its
metrics, videos, geometry export, and the encoding of renders as PNG / EXR.

Modules: :mod:`~voxnerf.inference.render` (load a run, render poses), :mod:`~voxnerf.inference.fast_path`
(front-to-back compositing with skipping), :mod:`~voxnerf.inference.evaluation`,
:mod:`~voxnerf.inference.metrics` (PSNR, SSIM, LPIPS), :mod:`~voxnerf.inference.video`,
:mod:`~voxnerf.inference.export` (mesh / point cloud), :mod:`~voxnerf.inference.encoding` (PNG / EXR, numpy only:
the API imports it). Nothing is imported here.
"""

from voxnerf import old_module_names

# ``from voxnerf.inference import X`` for the names of the old flat module, which is now voxnerf.inference.fast_path
__getattr__ = old_module_names(__name__, "voxnerf.inference.fast_path")
