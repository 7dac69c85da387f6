"""The camera set-up options, declared once (:class:`capssim.camera.camera_setup.CameraSetup`).

Every command that makes captures (``simulate``, ``render``, ``calibration-captures``) takes them:
it declares one parameter ``setup_options: SetupOptions`` and is decorated with
:func:`with_setup_options`, which puts the options below in that parameter's place in the command's
signature (typer reads it) and hands the command their values as one :class:`SetupOptions`.

Each option spells its quantity as the set-up does (``--noise``, ``--psf-sigma-hr-px``,
``--dofp-layout``, ``--extinction-ratio``, ``--rig`` ...), with the set-up's default.
"""

from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import typer

from capssim.camera.camera_setup import (
    DEFAULT_DOFP_LAYOUT,
    DEFAULT_NOISE,
    DEFAULT_SIGMA_HR_PX,
    CameraSetup,
    sensor_from_options,
)
from capssim.camera.psf import PSF
from capssim.camera.rig import RigModel, read_rig_json
from capssim.cli._options import number_in, seed_in_range
from capssim.errors import InputError, UnknownNameError

# -- sensor, optics, DoFP ------------------------------------------------------------------------------
NoiseOption = typer.Option(DEFAULT_NOISE, "--noise", help="Sensor noise model: none | gaussian | poisson-gaussian.")
SigmaOption = typer.Option(None, "--sigma", help="Gaussian noise std on [0, 1] data (with --noise gaussian).",
                           callback=number_in("--sigma", 0.0, 1.0, what="noise std on [0, 1] data",
                                              fix="Try --sigma 0.01."))
SensorOption = typer.Option(None, "--sensor", help="Sensor preset for poisson-gaussian: python1300 | imx250myr "
                                                   "(default imx250myr).")
DofpLayoutOption = typer.Option(DEFAULT_DOFP_LAYOUT, "--dofp-layout",
                                help="DoFP 2x2 polarizer cell: sony ([[90,45],[135,0]]) | 0-45-135-90.")
PSF_KINDS = ("gaussian", "airy", "none")
PsfOption = typer.Option(PSF_KINDS[0], "--psf", help="Optical PSF: gaussian (--psf-sigma-hr-px) | airy (--f-number, "
                                                   "--wavelength-nm, --pixel-um) | none.")
PsfSigmaOption = typer.Option(DEFAULT_SIGMA_HR_PX, "--psf-sigma-hr-px",
                              help="Gaussian optical PSF std in HR pixels (0 = no blur).",
                              callback=number_in("--psf-sigma-hr-px", 0.0, what="HR pixels; 0 = no blur",
                                                 fix=f"Try --psf-sigma-hr-px {DEFAULT_SIGMA_HR_PX}."))
FNumberOption = typer.Option(1.65, "--f-number", help="f-number for --psf airy.",
                             callback=number_in("--f-number", 0.0, low_open=True))
WavelengthOption = typer.Option(550.0, "--wavelength-nm", help="Wavelength for --psf airy.",
                                callback=number_in("--wavelength-nm", 0.0, low_open=True, what="nm"))
PixelPitchOption = typer.Option(4.8, "--pixel-um", help="Raw pixel pitch for --psf airy (HR pitch is half).",
                                callback=number_in("--pixel-um", 0.0, low_open=True, what="micrometres"))
ExtinctionRatioOption = typer.Option(None, "--extinction-ratio",
                                     help="Polarizer extinction ratio T_max/T_min (>= 1; default: ideal); with "
                                          "--rig realistic or a rig file, the DoFP camera's only.",
                                     callback=number_in("--extinction-ratio", 1.0, what="T_max / T_min",
                                                        fix="For example --extinction-ratio 100."))


# -- the rig -------------------------------------------------------------------------------------------
RigOption = typer.Option(None, "--rig", help="Imperfect camera array: a preset (ideal, realistic) or a capssim-rig "
                                             "JSON file (capssim calibrate's output; its geometry, if any, gives "
                                             "the aperture homographies). Default: the ideal array.")


def _check_rig_seed(seed: int) -> int:
    return seed_in_range(seed, "--rig-seed")


RigSeedOption = typer.Option(0, "--rig-seed", callback=_check_rig_seed, help="Draw of the --rig preset, 0 .. 2**63-1.")
AngleOffsetsOption = typer.Option(None, "--angle-offsets",
                                  help="Polarizer angle errors of the 4 apertures, degrees (|x| <= 20): a,b,c,d.")
ExtinctionRatiosOption = typer.Option(None, "--extinction-ratios",
                                      help="Polarizer extinction ratios of the rig (> 1, inf = ideal): 1 value, 3 "
                                           "(per colour R,G,B) or 12 (per aperture and colour). With a rig they "
                                           "replace --extinction-ratio for the CAPS frames; the DoFP camera keeps "
                                           "--extinction-ratio.")
GainsOption = typer.Option(None, "--gains", help="Gains of the 4 cameras (1 = nominal): a,b,c,d.")
VignettingOption = typer.Option(None, "--vignetting",
                                help="Corner fall-off of a centred radial vignetting, 0..0.9 (0.2 = corners at 80 %).",
                                callback=number_in("--vignetting", 0.0, 0.9, what="the corner fall-off fraction",
                                                   fix="For example --vignetting 0.2 (corners at 80 %)."))
AperturePsfOption = typer.Option(None, "--aperture-psf-sigmas",
                                 help="Gaussian PSF std of each aperture, HR pixels (>= 0): a,b,c,d.")

#: rig flag -> (RigModel.with_overrides keyword, value counts, valid range, example)
_RIG_FLAGS = {
    "--angle-offsets": ("angle_offsets_deg", (4,), (-20.0, 20.0, False), "1.5,-0.8,0.3,-2"),
    "--extinction-ratios": ("extinction_ratio", (1, 3, 12), (1.0, math.inf, True), "200,150,60"),
    "--gains": ("gain", (4,), (1e-3, math.inf, False), "1.03,0.97,1,1.01"),
    "--aperture-psf-sigmas": ("psf_sigmas_hr_px", (4,), (0.0, math.inf, False), "0.45,0.5,0.55,0.5"),
}


def _rig_numbers(flag: str, text: str) -> list[float]:
    """The comma-separated values of rig option ``flag``, checked against :data:`_RIG_FLAGS`."""
    _, counts, (low, high, low_open), example = _RIG_FLAGS[flag]
    allow_inf = flag == "--extinction-ratios"
    count_text = " or ".join(map(str, counts))
    valid = (f"{count_text} comma-separated numbers, each {'>' if low_open else '>='} {low:g}"
             + (" (inf: ideal)" if allow_inf else f" and <= {high:g}" if math.isfinite(high) else ""))
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(flag, repr(text), valid, f"For example {flag} {example}.") from None
    if len(values) not in counts or not all(
            (math.isfinite(v) or (allow_inf and v == math.inf)) and (v > low if low_open else v >= low) and v <= high
            for v in values):
        raise InputError(flag, repr(text), valid, f"For example {flag} {example}.")
    return values


def rig_from_options(rig: Optional[str], rig_seed: int = 0, *, angle_offsets: Optional[str] = None,
                     extinction_ratios: Optional[str] = None, gains: Optional[str] = None,
                     vignetting: Optional[float] = None, aperture_psf_sigmas: Optional[str] = None,
                     extinction_ratio: Optional[float] = None):
    """``(RigModel | None, ArrayGeometry | None)`` of the rig options; ``(None, None)`` when none is given.

    ``rig``: ``ideal``, ``realistic`` (drawn with ``rig_seed``) or a capssim-rig JSON file (its
    geometry, if any, is returned); the other options replace the rig's quantities. On the ideal
    array (``--rig`` absent or ``ideal``) without ``--extinction-ratios``, the one
    ``extinction_ratio`` (``--extinction-ratio``) stays the CAPS polarizers' too.
    """
    texts = {"--angle-offsets": angle_offsets, "--extinction-ratios": extinction_ratios, "--gains": gains,
             "--aperture-psf-sigmas": aperture_psf_sigmas}
    overrides = {_RIG_FLAGS[flag][0]: _rig_numbers(flag, text) for flag, text in texts.items() if text is not None}
    if vignetting is not None:
        overrides["vignetting_corner"] = vignetting
    if rig is None and not overrides:
        return None, None
    geometry = None
    if rig in (None, "ideal") and extinction_ratio is not None and "extinction_ratio" not in overrides:
        overrides["extinction_ratio"] = [extinction_ratio]
    if rig is None or rig in ("ideal", "realistic"):
        model = RigModel.preset(rig or "ideal", seed=rig_seed)
    elif Path(rig).suffix.lower() == ".json" or Path(rig).exists():
        loaded = read_rig_json(rig, argument="--rig")
        model, geometry = loaded.rig, loaded.geometry
    else:
        raise InputError("--rig", repr(rig), "ideal, realistic, or a capssim-rig JSON file",
                         "Write one with `capssim calibrate`, or use --rig realistic.")
    try:
        return model.with_overrides(**overrides), geometry
    except InputError as exc:
        flag = {"rig angle_offsets_deg": "--angle-offsets", "rig extinction_ratio": "--extinction-ratios",
                "rig gain": "--gains", "rig vignetting": "--vignetting", "extinction_ratio": "--extinction-ratios",
                "vignetting": "--vignetting", "aperture PSF sigmas": "--aperture-psf-sigmas"}.get(exc.argument,
                                                                                                   exc.argument)
        raise InputError(flag, exc.received, exc.valid, exc.fix) from None


def check_rig_psfs(rig, hr_shape, *, aperture_psf_sigmas: Optional[str]) -> None:
    """Refuse rig PSFs wider than the ``hr_shape`` image, naming the flag that set them."""
    flag = "--aperture-psf-sigmas" if aperture_psf_sigmas is not None else "--rig"
    for aperture_psf in (rig.psf_objects() if rig is not None else None) or []:
        aperture_psf.check_extent(tuple(hr_shape), option=flag, memory=False)


def rig_homographies(geometry, hr_shape, *, fix: str):
    """``(4, 3, 3)`` aperture homographies of a ``--rig`` file's geometry (``None`` without one),
    refused unless made for ``hr_shape``."""
    if geometry is None:
        return None
    if tuple(geometry.hr_shape) != tuple(int(v) for v in hr_shape):
        raise InputError("--rig", f"geometry for {geometry.hr_shape[0]}x{geometry.hr_shape[1]} HR px",
                         f"the capture's size {hr_shape[0]}x{hr_shape[1]}",
                         f"Calibrate at the capture's size, or {fix}.")
    return geometry.aperture_homographies


# -- one value for the command ------------------------------------------------------------------------
@dataclass(frozen=True)
class SetupOptions:
    """The values of the camera set-up options of one command line (their names are the parameters')."""

    noise: str = NoiseOption.default
    sigma: Optional[float] = SigmaOption.default
    sensor: Optional[str] = SensorOption.default
    dofp_layout: str = DofpLayoutOption.default
    psf: str = PsfOption.default
    psf_sigma_hr_px: float = PsfSigmaOption.default
    f_number: float = FNumberOption.default
    wavelength_nm: float = WavelengthOption.default
    pixel_um: float = PixelPitchOption.default
    extinction_ratio: Optional[float] = ExtinctionRatioOption.default
    rig: Optional[str] = RigOption.default
    rig_seed: int = RigSeedOption.default
    angle_offsets: Optional[str] = AngleOffsetsOption.default
    extinction_ratios: Optional[str] = ExtinctionRatiosOption.default
    gains: Optional[str] = GainsOption.default
    vignetting: Optional[float] = VignettingOption.default
    aperture_psf_sigmas: Optional[str] = AperturePsfOption.default

    def rig_model(self, *, default: Optional[str] = None):
        """``(RigModel | None, ArrayGeometry | None)`` of the rig options (:func:`rig_from_options`);
        ``default``: the ``--rig`` of a command line without one (``None``: no rig)."""
        return rig_from_options(self.rig or default, self.rig_seed, angle_offsets=self.angle_offsets,
                                extinction_ratios=self.extinction_ratios, gains=self.gains,
                                vignetting=self.vignetting, aperture_psf_sigmas=self.aperture_psf_sigmas,
                                extinction_ratio=self.extinction_ratio)

    def optical_psf(self):
        """The :class:`capssim.camera.psf.PSF` of ``--psf`` and its parameters."""
        kind = self.psf.lower()
        if kind == "gaussian":
            return PSF.gaussian(self.psf_sigma_hr_px)
        if kind == "airy":
            return PSF.airy(self.f_number, self.wavelength_nm, self.pixel_um / 2.0)
        if kind == "none":
            return PSF.none()
        raise InputError("--psf", repr(self.psf), " | ".join(PSF_KINDS), "For example --psf gaussian.")

    def camera_setup(self, rig=None):
        """The :class:`capssim.camera.camera_setup.CameraSetup` of these options, with ``rig`` (from :meth:`rig_model`)."""
        try:
            sensor = sensor_from_options(self.noise, sigma=self.sigma, preset=self.sensor)
        except UnknownNameError as exc:
            flag = "--noise" if exc.kind == "noise model" else "--sensor"
            raise InputError(flag, repr(exc.name), f"one of {', '.join(exc.known)}") from None
        try:
            return CameraSetup(sensor=sensor, psf=self.optical_psf(), dofp_layout=self.dofp_layout,
                               extinction_ratio=self.extinction_ratio, rig=rig)
        except InputError as exc:  # name the flag, not the field
            if not exc.argument.startswith("setup "):
                raise
            flag = "--" + exc.argument.removeprefix("setup ").replace("_", "-")
            raise InputError(flag, exc.received, exc.valid, exc.fix) from None


#: the options' parameters, in the order ``--help`` lists them
SETUP_PARAMETERS = tuple(
    inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option, annotation=annotation)
    for name, annotation, option in (
        ("noise", str, NoiseOption), ("sigma", Optional[float], SigmaOption), ("sensor", Optional[str], SensorOption),
        ("dofp_layout", str, DofpLayoutOption), ("psf", str, PsfOption), ("psf_sigma_hr_px", float, PsfSigmaOption),
        ("f_number", float, FNumberOption), ("wavelength_nm", float, WavelengthOption),
        ("pixel_um", float, PixelPitchOption), ("extinction_ratio", Optional[float], ExtinctionRatioOption),
        ("rig", Optional[str], RigOption), ("rig_seed", int, RigSeedOption),
        ("angle_offsets", Optional[str], AngleOffsetsOption),
        ("extinction_ratios", Optional[str], ExtinctionRatiosOption), ("gains", Optional[str], GainsOption),
        ("vignetting", Optional[float], VignettingOption), ("aperture_psf_sigmas", Optional[str], AperturePsfOption)))


def with_setup_options(command):
    """Decorate a typer command that has a ``setup_options: SetupOptions`` parameter: the command line
    takes the camera set-up options (:data:`SETUP_PARAMETERS`) in its place, and the command receives
    their values as one :class:`SetupOptions`."""
    signature = inspect.signature(command, eval_str=True)
    if "setup_options" not in signature.parameters:
        raise TypeError(f"{command.__name__} has no 'setup_options' parameter")
    parameters = []
    for parameter in signature.parameters.values():
        if parameter.name != "setup_options":
            parameters.append(parameter.replace(kind=inspect.Parameter.KEYWORD_ONLY))
        else:
            parameters.extend(SETUP_PARAMETERS)

    @functools.wraps(command)
    def wrapper(**kwargs):
        values = {p.name: kwargs.pop(p.name) for p in SETUP_PARAMETERS if p.name in kwargs}
        return command(setup_options=SetupOptions(**values), **kwargs)

    wrapper.__signature__ = signature.replace(parameters=parameters)
    wrapper.__annotations__ = {p.name: p.annotation for p in parameters}
    return wrapper
