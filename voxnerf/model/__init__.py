"""The model (paper III-B to III-D): the hash-grid field and its CPU kernel, the samplers, volume rendering, the
per-image appearance, the losses, and the model that holds them.

Modules: :mod:`~voxnerf.model.field` (hash encoding and MLPs), :mod:`~voxnerf.model.hash_kernel` (the C kernel of
the encoding, ``hashgrid.c``), :mod:`~voxnerf.model.samplers` (VoxNeRF, occupancy grid, uniform),
:mod:`~voxnerf.model.volume_rendering` (compositing, stable by construction), :mod:`~voxnerf.model.appearance`,
:mod:`~voxnerf.model.losses`, :mod:`~voxnerf.model.voxnerf_model` (:class:`VoxNeRFModel`).
"""

from voxnerf import old_module_names

# ``from voxnerf.model import X`` for the names of the old flat module, which is now voxnerf.model.voxnerf_model
__getattr__ = old_module_names(__name__, "voxnerf.model.voxnerf_model")
