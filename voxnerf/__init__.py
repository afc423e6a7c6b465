"""VoxNeRF: prior-guided neural radiance fields for indoor scans.

The engine is split like nerfstudio's rooms around nerfacc-style functional tensor contracts:
:mod:`voxnerf.data` (scenes, images, importers), :mod:`voxnerf.cameras` (camera rules, rays, lenses, paths, pose
refinement), :mod:`voxnerf.prior` (the geometry prior and its octree), :mod:`voxnerf.model` (field, samplers,
volume rendering, losses), :mod:`voxnerf.training` (set-up stages, loop, callbacks) and :mod:`voxnerf.inference`
(rendering, evaluation, videos, export). Every public function documents tensor shapes and units; "normalised
units" means the canonical box of :class:`voxnerf.data.scene.SceneTransform`, "scene units" the units of the
input poses.

The engine's modules sat in one flat folder before version 0.2; their old names (``voxnerf.scene``,
``voxnerf.render``, ...) still import, as aliases of the new modules, with a DeprecationWarning.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__version__ = "0.1.0"

# Old flat module -> its module now. The four whose old name is now a package's (cameras, prior, model, inference)
# are served by that package's ``__getattr__`` instead (see voxnerf/model/__init__.py).
MOVED_MODULES = {
    "voxnerf.scene": "voxnerf.data.scene", "voxnerf.image_io": "voxnerf.data.image_io",
    "voxnerf.image_noise": "voxnerf.data.image_noise", "voxnerf.importers": "voxnerf.data.importers",
    "voxnerf.camera_rules": "voxnerf.cameras.rules", "voxnerf.lens": "voxnerf.cameras.lens",
    "voxnerf.camera_path": "voxnerf.cameras.paths", "voxnerf.pose_refinement": "voxnerf.cameras.pose_refinement",
    "voxnerf.neighbours": "voxnerf.cameras.neighbours",
    "voxnerf.octree": "voxnerf.prior.octree", "voxnerf.octree_carving": "voxnerf.prior.carving",
    "voxnerf.pseudo_depth": "voxnerf.prior.pseudo_depth", "voxnerf.depth_fusion": "voxnerf.prior.depth_fusion",
    "voxnerf.focal_check": "voxnerf.prior.focal_check",
    "voxnerf.field": "voxnerf.model.field", "voxnerf.hash_kernel": "voxnerf.model.hash_kernel",
    "voxnerf.samplers": "voxnerf.model.samplers", "voxnerf.rendering": "voxnerf.model.volume_rendering",
    "voxnerf.appearance": "voxnerf.model.appearance", "voxnerf.losses": "voxnerf.model.losses",
    "voxnerf.render": "voxnerf.inference.render", "voxnerf.evaluation": "voxnerf.inference.evaluation",
    "voxnerf.metrics": "voxnerf.inference.metrics", "voxnerf.video": "voxnerf.inference.video",
    "voxnerf.export": "voxnerf.inference.export", "voxnerf.outputs": "voxnerf.inference.encoding",
    "voxnerf.training.evals": "voxnerf.training.eval_passes",
    "voxnerf.training.corrections": "voxnerf.training.stages.corrections",
    "voxnerf.training.focal": "voxnerf.training.stages.focal",
    "voxnerf.training.weight_decay": "voxnerf.training.stages.weight_decay",
}


def moved_to(old: str) -> str | None:
    """The module an old name now imports (``voxnerf.importers.colmap`` -> ``voxnerf.data.importers.colmap``)."""
    head, tail = old, ""
    while head.startswith("voxnerf."):  # the name, then each package above it: a lookup per level
        if head in MOVED_MODULES:
            return MOVED_MODULES[head] + tail
        head, _, last = head.rpartition(".")
        tail = f".{last}{tail}"
    return None


def warn_moved(old: str, new: str) -> None:
    warnings.warn(f"{old} is now {new}; the old name will be removed", DeprecationWarning, stacklevel=3)


def old_module_names(package: str, module: str):
    """A package's ``__getattr__`` that serves the names of the old flat module ``package`` (now ``module``) with a
    DeprecationWarning; the package's submodules and dunder names are left to the import system."""

    def __getattr__(name: str):
        if name.startswith("__") or importlib.util.find_spec(f"{package}.{name}") is not None:
            raise AttributeError(name)
        target = importlib.import_module(module)
        if not hasattr(target, name):
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        warn_moved(f"{package}.{name}", f"{module}.{name}")
        value = getattr(target, name)
        setattr(sys.modules[package], name, value)  # warned once; later reads find the name directly
        return value

    return __getattr__


class _Alias(importlib.abc.Loader):
    def __init__(self, old: str, new: str):
        self.old, self.new = old, new

    def create_module(self, spec):
        warn_moved(self.old, self.new)
        return importlib.import_module(self.new)

    def exec_module(self, module) -> None:
        pass


class _MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Imports an old module name as the module it moved to (the same module object under both names)."""

    def find_spec(self, fullname, path, target=None):
        new = moved_to(fullname)
        return None if new is None else importlib.util.spec_from_loader(fullname, _Alias(fullname, new))


if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.insert(0, _MovedModuleFinder())  # first: the path finder would load a moved submodule twice
