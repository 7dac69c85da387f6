"""Physically based rendering of CAPS captures with Mitsuba 3 (docs: guides/rendering.md).

``render_capture(scene, ...)`` renders a registered scene through the four apertures and the
DoFP camera and returns a :class:`~capssim.captures.capture.Capture` of kind ``rendered``;
``list_scenes()`` lists the registered scenes. Scenes register in its registry
(:mod:`capssim.render.scene_registry`), which loads the scene library through its entry point.
Importing this package points ``DRJIT_LIBLLVM_PATH`` at libLLVM 19 when it is installed
(Mitsuba's LLVM variants need it); Mitsuba itself is imported lazily.
"""

from capssim.render.variants import configure_llvm_environment

configure_llvm_environment()

from capssim.render.pipeline import render_capture  # noqa: E402
from capssim.render.scene_base import CameraPose, Scene, SceneInfo  # noqa: E402
from capssim.render.scene_registry import all_scenes, get_scene, register  # noqa: E402
from capssim.render.settings import RenderSettings  # noqa: E402


def list_scenes() -> dict[str, SceneInfo]:
    """``name -> SceneInfo`` for every registered scene, sorted by name."""
    return {name: scene.info for name, scene in all_scenes().items()}


__all__ = ["CameraPose", "RenderSettings", "Scene", "SceneInfo", "all_scenes", "get_scene", "list_scenes",
           "register", "render_capture"]
