"""The scene registry: library scenes register themselves here, and the renderer finds them by name.

The renderer never imports the scene library. Each module of :mod:`capssim.scenes` decorates
its :class:`~capssim.render.scene_base.Scene` subclass with :func:`register` when it is
imported, and importing :mod:`capssim.scenes` imports them all; so whoever renders or lists
library scenes by name (the command line, the dataset, the evaluation) imports
:mod:`capssim.scenes` first.
"""

from __future__ import annotations

from capssim.errors import InputError, UnknownNameError
from capssim.render.scene_base import Scene

_SCENES: dict[str, Scene] = {}


def register(cls: type[Scene]) -> type[Scene]:
    """Class decorator: add a scene (an instance of ``cls``) to the registry under ``cls().info.name``."""
    instance = cls()
    name = instance.info.name
    if name in _SCENES and type(_SCENES[name]) is not cls:
        raise ValueError(f"scene {name!r} registered twice")
    _SCENES[name] = instance
    return cls


def get_scene(name: str) -> Scene:
    """The registered scene called ``name`` (case and surrounding spaces ignored).

    Raises :class:`~capssim.errors.UnknownNameError` for a name that is not registered.
    """
    key = str(name).strip().lower()
    if not _SCENES:
        raise InputError("scene", name, "the name of a registered scene (none is registered yet)",
                         "Import capssim.scenes (the scene library) before rendering a library scene by name.")
    if key not in _SCENES:
        raise UnknownNameError("scene", name, list(_SCENES))
    return _SCENES[key]


def all_scenes() -> dict[str, Scene]:
    """``name -> Scene`` for every registered scene, sorted by name."""
    return dict(sorted(_SCENES.items()))


__all__ = ["all_scenes", "get_scene", "register"]
