"""The scene library: one module per scene, each describing geometry, materials, depth and purpose.

Every module defines one :class:`capssim.render.scene_base.Scene` subclass; :data:`LIBRARY` lists
them all, and :func:`register_library` is the one call that registers them with the renderer's
registry (:mod:`capssim.render.scene_registry`). Nobody calls it by hand: the package declares it as
the entry point ``library`` of the group ``capssim.scenes`` (pyproject.toml), and the registry calls
every function of that group the first time a scene is looked up by name. So ``capssim scenes``
lists the library and ``capssim render NAME`` renders one without importing this package first; a
package of your own can add scenes the same way, with an entry point in that group.
"""

from __future__ import annotations

if __name__ != "capssim.scenes":
    # The folder scenes/ is installed as capssim.scenes; a bare `import scenes` would shadow other packages.
    raise ImportError(f"{__name__!r} is not an import name of capssim: the folder scenes/ is the package "
                      "capssim.scenes; write `import capssim.scenes` (after `pip install -e .`)")

from typing import Callable

from capssim.render.scene_base import Scene
from capssim.render.scene_registry import all_scenes, get_scene

from .aop_wheel import AopWheel
from .calibration_sheet import CalibrationSheet
from .colorchecker import ColorChecker
from .dolp_ramp import DolpRamp
from .materials import Materials
from .polarization_star import PolarizationStar
from .siemens_star import SiemensStar
from .textured import Textured
from .water_glare import WaterGlare
from .window_reflection import WindowReflection

#: every scene class of the library, in name order of their modules
LIBRARY: tuple[type[Scene], ...] = (AopWheel, CalibrationSheet, ColorChecker, DolpRamp, Materials, PolarizationStar,
                                    SiemensStar, Textured, WaterGlare, WindowReflection)


def register_library(register: Callable[[type[Scene]], object]) -> None:
    """Register every scene of :data:`LIBRARY`; the entry point ``capssim.scenes:register_library``.

    The registry (:mod:`capssim.render.scene_registry`) calls it once, with its own ``register``.

    Parameters
    ----------
    register : callable
        ``register(scene_class)``, e.g. :func:`capssim.render.scene_registry.register`.
    """
    for scene_class in LIBRARY:
        register(scene_class)


__all__ = ["LIBRARY", "all_scenes", "get_scene", "register_library"]
