"""Physically based rendering of CAPS captures with Mitsuba 3 (README "Rendering").

``render_capture(scene, ...)`` renders a library scene (``scenes/``) through the four
apertures and the DoFP camera and returns a :class:`~capssim.capture.Capture` of kind
``rendered``; ``list_scenes()`` lists the library. Importing this package points
``DRJIT_LIBLLVM_PATH`` at libLLVM 19 when it is installed (Mitsuba's LLVM variants need it);
Mitsuba itself is imported lazily.
"""

from capssim.render.variants import configure_llvm_environment

configure_llvm_environment()

from capssim.render.pipeline import render_capture  # noqa: E402
from capssim.render.scene_base import CameraPose, Scene, SceneInfo  # noqa: E402


def list_scenes() -> dict[str, SceneInfo]:
    """``name -> SceneInfo`` for every scene in the library, sorted by name."""
    from capssim.scenes import all_scenes

    return {name: scene.info for name, scene in all_scenes().items()}


__all__ = ["CameraPose", "Scene", "SceneInfo", "list_scenes", "render_capture"]
