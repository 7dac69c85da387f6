"""The reconstruction-method registry and its dispatcher (colour-science style).

A method is one function in one file under ``reconstruct/methods/``, registered with
:func:`register_method`::

    @register_method("dofp-bilinear", input_kind="dofp", description="...", reference="...")
    def dofp_bilinear(capture: Capture, *, context: RunContext) -> MethodOutput: ...

:func:`reconstruct` looks the name up, runs it, checks the output (shape, finite) and
returns a :class:`MethodOutput` with the wall time of every stage. ``run_method`` also
writes ``recon/NAME.tiff`` and ``recon/NAME.json`` into the capture folder. Methods of other
packages (entry points ``capssim.methods``) join the registry through :mod:`capssim.reconstruct.plugins`.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from capssim.captures.capture import Capture, read_capture, write_reconstruction
from capssim.conventions import flip_to_rggb
from capssim.errors import CapssimError, CaptureFormatError, InputError, UnknownNameError
from capssim.stokes.physical_validity import project_to_physical

from .calibration_model import resolve_calibration
from .pipeline.options import wants_ground_truth
from .registration.parameters import registration_parameters
from .run_context import MethodOutput, RunContext, StageTimer

log = logging.getLogger(__name__)

#: the package whose modules are the registered methods, one method (or a family) per file
METHODS_PACKAGE = "capssim.reconstruct.methods"
#: the module that runs ``uncertainty=N`` (found by name: it runs the methods again through this dispatcher)
UNCERTAINTY_MODULE = "capssim.reconstruct.uncertainty.estimate"
#: the registration mode of a method that names none (:class:`MethodSpec`), and of a name no method has
DEFAULT_REGISTRATION = "local-correlation"


@dataclass(frozen=True)
class MethodSpec:
    name: str
    function: Callable[..., MethodOutput]
    input_kind: str  # "caps" or "dofp"
    description: str
    reference: str
    module: str
    #: for DoFP methods, the plain array function ``fn(mosaic, *, layout, device, timer)`` behind the method
    array_function: Callable | None = None
    #: ``frame_options(capture, options, *, homographies, device) -> dict``: options the method derives from the whole
    #: frame (``homographies`` ``(4, 3, 3)``: its aperture warps), fixed once before a tiled run cuts it (each tile
    #: then runs with them as if given); None: none
    frame_options: Callable | None = None
    #: the suites (names of eval/suites) or data its defaults were chosen on: a suite report marks its scores
    #: there (docs: guides/benchmarks.md, "Development and test data"); () for none of capssim's
    tuned_on: tuple[str, ...] = ()
    #: ``options() -> [MethodOption]``: every ``-p`` option the method takes (``capssim reconstruct --options``);
    #: None: the method lists none
    options: Callable | None = None
    #: where a plug-in method comes from (:class:`capssim.reconstruct.plugins.Plugin`); None: built in
    plugin: object | None = None
    #: the registration mode (:data:`~capssim.reconstruct.registration.REGISTRATION_MODES`) the method estimates its
    #: warps with when the run names none (``--registration``): :data:`DEFAULT_REGISTRATION`, or ``fast`` for a method
    #: whose time the registration would otherwise decide (``array-kr``)
    registration: str = DEFAULT_REGISTRATION


_METHODS: dict[str, MethodSpec] = {}
_LOADED = False


def register_method(name: str, *, input_kind: str, description: str, reference: str,
                    array_function: Callable | None = None, frame_options: Callable | None = None,
                    tuned_on: tuple[str, ...] = (), options: Callable | None = None,
                    registration: str = DEFAULT_REGISTRATION):
    """Decorator registering a reconstruction function under ``name``.

    ``array_function``: the method's plain array form, for ``capssim demosaic`` (DoFP mosaics).
    ``frame_options``: see :class:`MethodSpec` (options a tiled run fixes over the whole frame).
    ``tuned_on``: the suites or data its defaults were chosen on; ``options``: its option list (:class:`MethodSpec`);
    ``registration``: its registration mode when a run names none (:class:`MethodSpec`).
    """
    if input_kind not in ("caps", "dofp"):
        raise ValueError(f"input_kind must be 'caps' or 'dofp', got {input_kind!r}")

    def wrap(fn):
        if name in _METHODS and _METHODS[name].function is not fn:
            raise ValueError(f"method {name!r} is registered twice ({_METHODS[name].module} and {fn.__module__})")
        _METHODS[name] = MethodSpec(name, fn, input_kind, description, reference, fn.__module__, array_function,
                                    frame_options, tuple(tuned_on), options, registration=registration)
        return fn

    return wrap


def _load_methods() -> None:
    global _LOADED
    if _LOADED:
        return
    # the methods import this registry to register themselves: they are discovered here by name, not imported above
    method_modules = importlib.import_module(METHODS_PACKAGE)
    for mod in pkgutil.iter_modules(method_modules.__path__):
        if not mod.name.startswith("_"):
            importlib.import_module(f"{METHODS_PACKAGE}.{mod.name}")
    _LOADED = True
    # the entry points of capssim.methods / capssim.priors, after the built-ins; found by name like the methods
    importlib.import_module("capssim.reconstruct.plugins").load_plugins()


def available_methods() -> dict[str, MethodSpec]:
    """The registered reconstruction methods, by name (the method modules are loaded on first call).

    Returns
    -------
    dict of str to MethodSpec
        Sorted by name; each spec holds the function, its input kind (``caps`` or ``dofp``) and reference.
    """
    _load_methods()
    return dict(sorted(_METHODS.items()))


def get_method(name: str) -> MethodSpec:
    methods = available_methods()
    if name not in methods:
        raise UnknownNameError("method", name, list(methods))
    return methods[name]


def dofp_array_function(method: str) -> Callable:
    """The plain array function ``fn(mosaic, *, layout, device, timer)`` behind a DoFP method name."""
    names = [n for n, spec in available_methods().items() if spec.array_function is not None]
    if method not in names:
        raise UnknownNameError("DoFP method", method, names)
    return get_method(method).array_function


def resolve_device(device: str | torch.device = "cpu") -> torch.device:
    """``cpu``, ``cuda`` (error if absent) or ``auto`` (cuda when present)."""
    key = str(device).lower()
    if key == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if key.startswith("cuda"):
        if not torch.cuda.is_available():
            raise InputError("device", device, "cpu, or cuda on a machine with a CUDA GPU", "Use --device cpu.")
        return torch.device(key)
    if key == "cpu":
        return torch.device("cpu")
    raise InputError("device", device, "one of cpu, cuda, auto")


#: fraction of a channel's pixels without a usable observation above which reconstruct warns
UNOBSERVED_WARN_FRACTION = 0.01


def unobserved_record(method: str, mask: np.ndarray | None) -> dict | None:
    """``{"fraction": [12], "channels": [...]}`` of the pixels ``mask`` marks unobserved, and a WARNING
    naming the channels whose fraction exceeds :data:`UNOBSERVED_WARN_FRACTION` (their output there
    is no measurement but the prior's or the initialization's fill, e.g. zeros)."""
    if mask is None:
        return None
    fraction = [float(f) for f in np.asarray(mask, dtype=bool).reshape(mask.shape[0], -1).mean(axis=1)]
    channels = [c for c, f in enumerate(fraction) if f > UNOBSERVED_WARN_FRACTION]
    if channels:
        listed = ", ".join(f"{c} ({100 * fraction[c]:.0f} %)" for c in channels)
        log.warning("%s: channels %s have pixels with no usable observation (saturated or out of view); the "
                    "output there is not measured (see 'unobserved' in the record)", method, listed)
    return {"fraction": fraction, "channels": channels, "warn_fraction": UNOBSERVED_WARN_FRACTION}


def finite_or_null(value, *, path: str = "record", found: list[str] | None = None):
    """``value`` with every non-finite float replaced by ``None`` (JSON null), recursively; the paths
    of the replaced entries are appended to ``found``."""
    if isinstance(value, dict):
        return {k: finite_or_null(v, path=f"{path}.{k}", found=found) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v, path=f"{path}[{i}]", found=found) for i, v in enumerate(value)]
    if isinstance(value, (float, np.floating)) and not np.isfinite(value):
        if found is not None:
            found.append(path)
        return None
    return value


def check_horizon(capture: Capture) -> None:
    """:class:`CaptureFormatError` if a stored aperture homography's horizon crosses the HR grid.

    The denominator ``h31 x + h32 y + h33`` is affine, so its sign over the grid is that of its
    four corners; where it changes sign the warp maps part of the image behind the camera.
    """
    hh, ww = capture.hr_shape
    corners = np.array([[0, 0, 1], [ww - 1, 0, 1], [0, hh - 1, 1], [ww - 1, hh - 1, 1]], dtype=np.float64)
    for n, hom in enumerate(capture.aperture_homographies()):
        den = corners @ hom[2]
        if not (np.all(den > 0) or np.all(den < 0)):
            raise CaptureFormatError(
                f"meta.json aperture_homographies[{n}]: its horizon (h31 x + h32 y + h33 = 0) crosses the "
                f"{hh}x{ww} HR grid (denominator {den.min():.3g} .. {den.max():.3g} at the corners), so part of the "
                "image would map behind the camera. Check the calibration, or reconstruct without --true-warps.")


def run_on_rggb(spec: MethodSpec, capture: Capture, context: RunContext) -> MethodOutput:
    """``spec.function(capture)``; a DoFP mosaic of another CFA (BGGR, GRBG, GBRG) is given to it as
    RGGB (:meth:`Capture.dofp_as_rggb`, exact) and the result flipped back onto the capture's grid.
    CAPS methods read the CFA themselves (the channel each Bayer site observes)."""
    flipped = capture.dofp_as_rggb() if spec.input_kind == "dofp" else capture
    out = spec.function(flipped, context=context)
    if flipped is not capture:
        out.image = flip_to_rggb(np.asarray(out.image), capture.cfa)
        if callable(out.unobserved):
            out.unobserved = out.unobserved()
        if out.unobserved is not None:
            out.unobserved = flip_to_rggb(np.asarray(out.unobserved), capture.cfa)
    return out


def default_registration(method: str) -> str:
    """The registration mode ``method`` estimates its warps with when a run names none (:attr:`MethodSpec.registration`);
    :data:`DEFAULT_REGISTRATION` for a name no method has (its own error comes where the method is run)."""
    _load_methods()
    spec = _METHODS.get(method)
    return DEFAULT_REGISTRATION if spec is None else spec.registration


def reconstruct(capture: Capture, method: str, *, device: str | torch.device = "cpu", true_warps: bool = False,
                registration: str | None = None, progress: Callable[[int, int, str], None] | None = None,
                physical_projection: bool = True, reuse_registration: bool = True, calibration=None,
                start: np.ndarray | None = None, uncertainty: int = 0, uncertainty_options: dict | None = None,
                **options) -> tuple[MethodOutput, dict]:
    """Run ``method`` (a name of :func:`available_methods`) on ``capture``, in memory.

    Parameters
    ----------
    capture, method : Capture, str
        Raw frames ``(4, H, W)`` (CAPS) or ``(2H, 2W)`` (DoFP) with their ``meta.json``; a method name.
    device, true_warps, registration, progress, reuse_registration : optional, default: see signature
        Torch device; true warps; registration mode (None: :func:`default_registration`); progress(i, n, stage); reuse.
    physical_projection, calibration, **options : optional, default: see signature
        Project onto ``I >= 0``, ``I0 + I90 = I45 + I135``, DoLP <= 1 where all four angles are observed;
        the CAPS array model (None: the capture's calibration file if it names one, ``"ideal"``, ``"truth"``
        or a ``capssim-rig`` file); the method's options (e.g. ``iterations``).
    start : numpy.ndarray, optional
        A warm start ``(12, 2H, 2W)`` for an iterative method's solver (:attr:`RunContext.start`).
    uncertainty, uncertainty_options : int, dict, optional
        With ``uncertainty = N >= 2``, the error bars of the reconstruction by an ``N``-replicate bootstrap
        (:mod:`capssim.reconstruct.uncertainty`): ``output.uncertainty`` and the record's ``uncertainty``;
        ``uncertainty_options``: ``seed``, ``equivariant``, ``warm_iterations``, ``registration_jitter_hr_px``,
        ``calibration`` (None: the shipped one; ``"none"``; a file).

    Returns
    -------
    (MethodOutput, dict)
        ``output.image`` ``(12, 2H, 2W)`` float32; the record of ``recon/NAME.json`` (``wall_time_s``, ``stages_s``).
    """
    spec = get_method(method)
    registration = spec.registration if registration is None else registration
    dev = resolve_device(device)
    _check_run(spec, capture, true_warps=true_warps, registration=registration, uncertainty=uncertainty,
               uncertainty_options=uncertainty_options)
    model = resolve_calibration(capture, calibration) if spec.input_kind == "caps" else None
    timer = StageTimer(dev)
    ctx = RunContext(device=dev, timer=timer, options=dict(options), true_warps=true_warps,
                     registration=registration, reuse_registration=reuse_registration, progress=progress,
                     calibration=model, start=start)
    t0 = time.perf_counter()
    with torch.no_grad():
        out = run_on_rggb(spec, capture, ctx)
    total = time.perf_counter() - t0
    image = _checked_image(method, out.image, capture.hr_shape, options)
    if callable(out.unobserved):
        out.unobserved = out.unobserved()
    projection = None
    if physical_projection:
        with timer.stage("physical_projection"):
            image, projection = project_to_physical(image, unobserved=out.unobserved)
        total += timer.stages["physical_projection"]
    out.image = image
    record = {
        "method": method,
        "description": spec.description,
        "reference": spec.reference,
        "input": spec.input_kind, "tuned_on": list(spec.tuned_on),
        "device": str(dev),
        "true_warps": true_warps,
        "options": options,
        "params": out.params,
        "wall_time_s": total,
        "stages_s": dict(timer.stages),
        "history": out.history,
        "physical_projection": None if projection is None else projection.to_dict(),
        "calibration": None if model is None else model.record,
        **out.extra,
    }
    unobserved = unobserved_record(method, out.unobserved)
    if unobserved is not None:
        record["unobserved"] = unobserved
    non_finite: list[str] = []
    if uncertainty:
        _add_uncertainty(capture, method, out, record, uncertainty, uncertainty_options,
                         {"device": dev, "physical_projection": physical_projection, "calibration": calibration})
    record = finite_or_null(record, found=non_finite)
    if non_finite:
        log.warning("%s: non-finite values recorded as null: %s", method, ", ".join(non_finite[:8]))
    return out, record


def _check_run(spec: MethodSpec, capture: Capture, *, true_warps: bool, registration: str, uncertainty: int,
               uncertainty_options: dict | None) -> None:
    """The checks of :func:`reconstruct` before any work: the uncertainty options, the registration mode, the true
    warps' horizon, a DoFP frame for a DoFP method."""
    if uncertainty:
        importlib.import_module(UNCERTAINTY_MODULE).check_uncertainty_options(uncertainty, uncertainty_options)
    if spec.input_kind == "caps" and not true_warps:
        registration_parameters(registration)  # UnknownNameError lists the modes
    if spec.input_kind == "caps" and true_warps:
        check_horizon(capture)
    if spec.input_kind == "dofp" and capture.dofp_raw is None:
        raise CaptureFormatError(f"method {spec.name!r} needs dofp_raw.tiff, which this capture lacks.")


def _checked_image(method: str, image, hr_shape, options: dict) -> np.ndarray:
    """A method's image as float32 ``(12, H, W)``; an error for another shape or a non-finite value."""
    image = np.asarray(image, dtype=np.float32)
    if image.shape != (12, *hr_shape):
        raise RuntimeError(f"method {method!r} returned shape {image.shape}, expected {(12, *hr_shape)}")
    if not np.all(np.isfinite(image)):
        given = ", ".join(f"{k}={v}" for k, v in options.items()) or "none"
        raise CapssimError(f"method {method!r} returned {int(np.sum(~np.isfinite(image)))} non-finite values "
                           f"(method options: {given}). Try the method's default options; if it fails with them "
                           "too, please report it with the capture.")
    return image


def _add_uncertainty(capture: Capture, method: str, out: MethodOutput, record: dict, replicates: int,
                     options: dict | None, run_options: dict) -> None:
    """``out.uncertainty`` and ``record["uncertainty"]``: the error bars of ``--uncertainty`` (the module is found
    by name, like the methods: the uncertainty room sits above this registry and runs the method again through it)."""
    estimate = importlib.import_module(UNCERTAINTY_MODULE).reconstruction_uncertainty
    out.uncertainty = estimate(capture, method, out.image, record, replicates=replicates, run=reconstruct,
                               run_options=run_options, **(options or {}))
    record["uncertainty"] = out.uncertainty.record


def run_method(capture_path: str | Path, method: str, **kwargs) -> dict:
    """Read a capture folder, :func:`reconstruct` it and write ``recon/METHOD.{tiff,json}``.

    Parameters
    ----------
    capture_path : str or pathlib.Path
        The capture folder.
    method : str
        A name of :func:`available_methods`.
    **kwargs
        Keyword options of :func:`reconstruct`.

    Returns
    -------
    dict
        The record written to ``recon/METHOD.json``.
    """
    capture = read_capture(capture_path, load_gt=wants_ground_truth(kwargs))  # track_psnr: PSNR per iteration
    out, record = reconstruct(capture, method, **kwargs)
    write_reconstruction(capture_path, method, out.image, record, companions=out.companions())
    return record
