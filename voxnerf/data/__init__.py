"""Data: loading a scene (transforms.json per docs/scene-format.md, its images and depth maps), image I/O, and the
importers that write other capture layouts as scenes.

Modules: :mod:`~voxnerf.data.scene` (loading, validation, the canonical box), :mod:`~voxnerf.data.image_io`
(decoding, PNG/EXR encoding, atomic writes), :mod:`~voxnerf.data.image_noise` (an image's noise level),
:mod:`voxnerf.data.importers` (COLMAP, ScanNet). Nothing is imported here, so the torch-free modules stay
torch-free for the API process.
"""
