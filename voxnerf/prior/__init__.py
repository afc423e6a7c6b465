"""The geometry prior (paper III-B): loading it, the Sparse Voxel Octree and its C ray tracer, free-space carving,
pseudo ground-truth depth, depth fusion, and the focal-length check against the prior.

Modules: :mod:`~voxnerf.prior.loading` (mesh or point cloud to points with a noise sigma),
:mod:`~voxnerf.prior.octree` (the octree and first-hit casting, ``octree_trace.c``),
:mod:`~voxnerf.prior.carving` (free-space carving by measured depth), :mod:`~voxnerf.prior.pseudo_depth`,
:mod:`~voxnerf.prior.depth_fusion` (a prior fused from the scan's depth maps), :mod:`~voxnerf.prior.focal_check`.
"""

from voxnerf import old_module_names

# ``from voxnerf.prior import X`` for the names of the old flat module, which is now voxnerf.prior.loading
__getattr__ = old_module_names(__name__, "voxnerf.prior.loading")
