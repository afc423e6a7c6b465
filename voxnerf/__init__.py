"""VoxNeRF: prior-guided neural radiance fields for indoor scans.

The engine is split like nerfstudio (field / sampler / renderer / loss) with nerfacc-style functional
tensor contracts. Every public function documents tensor shapes and units; "normalised units" means the
canonical box of :class:`voxnerf.scene.SceneTransform`, "scene units" the units of the input poses.
"""

__version__ = "0.1.0"
