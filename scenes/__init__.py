"""The scene library: one module per scene, each describing geometry, materials, depth and purpose.

Every module defines one :class:`capssim.render.scene_base.Scene` subclass and registers
it with :func:`register`. ``capssim scenes`` lists them; ``capssim render NAME`` renders one.
"""

from __future__ import annotations

if __name__ != "capssim.scenes":
    # The folder scenes/ is installed as capssim.scenes; a bare `import scenes` would shadow other packages.
    raise ImportError(f"{__name__!r} is not an import name of capssim: the folder scenes/ is the package "
                      "capssim.scenes; write `import capssim.scenes` (after `pip install -e .`)")

import importlib
import pkgutil

from capssim.errors import UnknownNameError

SCENES: dict = {}

def register(cls):
    """Class decorator: add a scene (instance of ``cls``) to the library under ``cls.info.name``."""
    instance = cls()
    name = instance.info.name
    if name in SCENES and type(SCENES[name]) is not cls:
        raise ValueError(f"scene {name!r} registered twice")
    SCENES[name] = instance
    return cls

def _load_all() -> None:
    for module in sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")):
        importlib.import_module(f"{__name__}.{module}")

def get_scene(name: str):
    """The registered scene called ``name`` (raises :class:`UnknownNameError`)."""
    _load_all()
    key = str(name).strip().lower()
    if key not in SCENES:
        raise UnknownNameError("scene", name, list(SCENES))
    return SCENES[key]

def all_scenes() -> dict:
    _load_all()
    return dict(sorted(SCENES.items()))
