"""capssim: camera-array colour-polarization super-resolution (CAPS), simulated and scored.

The package ``capssim`` holds the camera physics; ``reconstruct`` the reconstruction methods; ``eval`` the
scoring. Imports go one way: capssim never imports reconstruct or eval (the CLI in ``capssim.cli`` loads them
lazily). capssim's own rooms, lowest first (docs/architecture.md, "The rooms of capssim/"):

* ``capssim.errors``, ``capssim.conventions``: the exceptions and the grids (apertures, angles, Bayer sites);
* ``capssim.runtime``: memory checks, the allocator, worker threads, out-of-range warnings;
* ``capssim.files``: image reading and writing, output folders, the JSON schema checker;
* ``capssim.stokes``: polarization maths (Stokes vectors, DoLP/AoP, physical validity);
* ``capssim.camera``: the array's geometry, PSF, sensor, rig, camera set-up, design quantities;
* ``capssim.operators``: the linear operators and the measurement built from them;
* ``capssim.captures``: the Capture object, its meta.json and that file's schema;
* ``capssim.visualize``; above them ``capssim.simulate`` and ``capssim.render``.

The modules that moved into the rooms keep their old names (``import capssim.capture``,
``from capssim.sensor import make_sensor``): a finder on ``sys.meta_path`` hands out the moved module itself
under its old name, imported only when asked for, so ``import capssim`` stays as light as before. The same holds
for ``capssim.eval.calibration`` (now ``capssim.reconstruct.calibration``) and the held-out validation and
polarization filter of ``capssim.reconstruct.model`` (now ``capssim.reconstruct.selection``).
"""

import importlib
import importlib.machinery
import logging
import sys

__version__ = "0.2.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

#: old dotted name -> the module's name in its room (tests/test_moved_names.py imports each)
MOVED_MODULES = {
    **{f"capssim.{name}": f"capssim.camera.{name}" for name in (
        "array_geometry", "homography", "psf", "sensor", "rig", "rig_checks", "rig_parts", "camera_setup",
        "design")},
    **{f"capssim.{name}": f"capssim.captures.{name}" for name in ("capture", "capture_meta", "capture_schema")},
    "capssim.measurement": "capssim.operators.measurement",
    **{f"capssim.{name}": f"capssim.files.{name}" for name in ("imageio", "output_paths", "schema")},
    **{f"capssim.{name}": f"capssim.stokes.{name}" for name in ("polarization", "physical_validity")},
    **{f"capssim.{name}": f"capssim.runtime.{name}" for name in ("resources", "threads", "allocator", "data_range")},
    # rooms of the reconstruction: the rig's estimation out of eval/, a method's choices out of the forward model
    "capssim.eval.calibration": "capssim.reconstruct.calibration",
    **{f"capssim.eval.calibration.{name}": f"capssim.reconstruct.calibration.{name}" for name in (
        "calibrate", "flat_field", "geometry_fit", "malus", "psf_fit", "report")},
    **{f"capssim.reconstruct.model.{name}": f"capssim.reconstruct.selection.{name}" for name in (
        "holdout", "polarization_filter", "polarization_evidence")},
}


class _MovedModuleLoader:  # (not importlib.abc.Loader: importlib.abc imports importlib.resources, slow)
    """Loads an old name as the moved module itself (one module object under two names)."""

    def __init__(self, new_name: str):
        self.new_name = new_name

    def create_module(self, spec):
        module = importlib.import_module(self.new_name)
        self._spec = module.__spec__  # the import system sets __spec__ to the old name's; put it back
        return module

    def exec_module(self, module):
        module.__spec__ = self._spec


class _MovedModuleFinder:
    """Finds the old dotted names of the modules that moved into capssim's rooms."""

    def find_spec(self, fullname, path=None, target=None):
        new_name = MOVED_MODULES.get(fullname)
        if new_name is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _MovedModuleLoader(new_name))


if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.insert(0, _MovedModuleFinder())


def __getattr__(name: str):
    """``capssim.capture`` and the other old names as attributes (imported on first use)."""
    if f"capssim.{name}" in MOVED_MODULES:
        return importlib.import_module(f"capssim.{name}")
    raise AttributeError(f"module 'capssim' has no attribute {name!r}")
