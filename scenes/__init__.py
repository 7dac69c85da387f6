"""The scene library: one module per scene, each describing geometry, materials, depth and purpose.

Every module defines one :class:`capssim.render.scene_base.Scene` subclass and registers it
with the renderer's registry (:func:`capssim.render.scene_registry.register`). Importing this
package imports every scene module, so the registry then holds the whole library:
``capssim scenes`` lists it; ``capssim render NAME`` renders one.
"""

from __future__ import annotations

if __name__ != "capssim.scenes":
    # The folder scenes/ is installed as capssim.scenes; a bare `import scenes` would shadow other packages.
    raise ImportError(f"{__name__!r} is not an import name of capssim: the folder scenes/ is the package "
                      "capssim.scenes; write `import capssim.scenes` (after `pip install -e .`)")

import importlib
import pkgutil

from capssim.render.scene_registry import all_scenes, get_scene, register


def _import_all() -> None:
    """Import (and so register) every scene module of this package, in name order."""
    for module in sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")):
        importlib.import_module(f"{__name__}.{module}")


_import_all()

__all__ = ["all_scenes", "get_scene", "register"]
