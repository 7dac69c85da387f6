"""The scene registry: scene libraries register here, and the renderer finds their scenes by name.

The renderer never imports the scene library. A library registers through one call: the
functions of the entry-point group :data:`ENTRY_POINT_GROUP` (capssim's own is
``capssim.scenes:register_library``, declared in pyproject.toml) are called once, with
:func:`register`, the first time a scene is looked up or listed. Nobody imports
:mod:`capssim.scenes` for its side effects.
"""

from __future__ import annotations

from importlib.metadata import entry_points

from capssim.errors import InputError, UnknownNameError
from capssim.render.scene_base import Scene

#: the entry-point group whose functions ``fn(register)`` register scene libraries
ENTRY_POINT_GROUP = "capssim.scenes"

_SCENES: dict[str, Scene] = {}
_LIBRARIES_LOADED = False


def _load_libraries() -> None:
    """Call every registration function of :data:`ENTRY_POINT_GROUP` once per process."""
    global _LIBRARIES_LOADED
    if _LIBRARIES_LOADED:
        return
    _LIBRARIES_LOADED = True
    for point in entry_points(group=ENTRY_POINT_GROUP):
        point.load()(register)


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
    _load_libraries()
    key = str(name).strip().lower()
    if not _SCENES:
        raise InputError("scene", name, "the name of a registered scene (none is registered)",
                         f"Reinstall capssim (pip install -e .): its scene library registers through the entry-point "
                         f"group {ENTRY_POINT_GROUP!r}.")
    if key not in _SCENES:
        raise UnknownNameError("scene", name, list(_SCENES))
    return _SCENES[key]


def all_scenes() -> dict[str, Scene]:
    """``name -> Scene`` for every registered scene, sorted by name."""
    _load_libraries()
    return dict(sorted(_SCENES.items()))


__all__ = ["ENTRY_POINT_GROUP", "all_scenes", "get_scene", "register"]
