"""System-design quantities of a camera-array SR imager (paper section 2.3, eq. 5-8).

* ``f_diffraction / f_Nyquist = 2 A P / (1.22 lambda f) = 2 P / (1.22 lambda N)`` with the
  aperture diameter ``A = f / N``.
* Theoretical SR magnification ``r_SR = min(f_diffraction / f_Nyquist, sqrt(apertures))`` (eq. 5).
* Common-overlap width ``R_x = N_x Z / f_P - B`` with ``f_P = f / P`` (eq. 6), and the
  effective fields of view ``FOV_h = 2 atan(N_x / (2 f_P) - B / (2 Z))``, ``FOV_v`` likewise (eq. 7-8).

Refused (one line, naming the option): a depth ``Z`` at or inside the focal length (no real image), a
depth at which the views do not overlap (``R_x`` or ``R_y`` <= 0: the effective field of view would be
negative), and inputs that make any quantity infinite or NaN.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

from capssim.errors import InputError


@dataclass(frozen=True)
class DesignInputs:
    """Lens, sensor and array parameters. Defaults are the paper's prototype (section 5.3)."""

    focal_length_mm: float = 35.0
    f_number: float = 1.65
    pixel_um: float = 4.8
    wavelength_nm: float = 550.0
    apertures: int = 4
    baseline_mm: float = 40.0
    depth_m: float = 10.0
    width_px: int = 1280
    height_px: int = 1024


def system_design(inputs: DesignInputs = DesignInputs()) -> dict:
    """All design quantities as a dict (lengths in mm/m as named, angles in degrees)."""
    for name, value in asdict(inputs).items():
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise InputError(name.replace("_", "-"), value, "a finite positive number")
    if int(inputs.apertures) != inputs.apertures:
        raise InputError("apertures", inputs.apertures, "a whole number of apertures")
    f_mm = inputs.focal_length_mm
    p_mm = inputs.pixel_um * 1e-3
    f_pixels = f_mm / p_mm
    b_mm = inputs.baseline_mm
    z_overlap_m = b_mm * f_pixels / min(inputs.width_px, inputs.height_px) * 1e-3  # R_x, R_y > 0 beyond it
    if inputs.depth_m * 1e3 <= f_mm:
        nearest = max(2 * f_mm * 1e-3, 1.5 * z_overlap_m)
        raise InputError("--depth-m", inputs.depth_m, f"a depth beyond the focal length ({f_mm:g} mm = "
                         f"{f_mm * 1e-3:g} m): nearer, the lens forms no real image",
                         (f"Use --depth-m {_up(nearest)} or more, or a shorter --focal-length-mm."
                          if math.isfinite(nearest) else "Use a shorter --focal-length-mm."))
    lam_mm = inputs.wavelength_nm * 1e-6
    a_mm = f_mm / inputs.f_number
    ratio = 2 * a_mm * p_mm / (1.22 * lam_mm * f_mm)
    r_sr = min(ratio, math.sqrt(inputs.apertures))
    z_mm = inputs.depth_m * 1e3
    rx_mm = inputs.width_px * z_mm / f_pixels - b_mm
    ry_mm = inputs.height_px * z_mm / f_pixels - b_mm
    fov_h = 2 * math.degrees(math.atan(inputs.width_px / (2 * f_pixels) - b_mm / (2 * z_mm)))
    fov_v = 2 * math.degrees(math.atan(inputs.height_px / (2 * f_pixels) - b_mm / (2 * z_mm)))
    single_h = 2 * math.degrees(math.atan(inputs.width_px / (2 * f_pixels)))
    if rx_mm <= 0 or ry_mm <= 0:  # the views share no part of the scene: eq. 7-8 turn negative
        raise InputError("--depth-m", inputs.depth_m, f"a depth at which the apertures' views overlap: more than "
                         f"{z_overlap_m:.4g} m for --baseline-mm {b_mm:g} (the overlap min(R_x, R_y) = "
                         f"min(N_x, N_y) Z / f_P - B is {min(rx_mm, ry_mm) * 1e-3:.4g} m at {inputs.depth_m:g} m)",
                         f"Use --depth-m {_up(z_overlap_m * 1.5)} or more, or a smaller --baseline-mm.")
    result = {
        "inputs": asdict(inputs),
        "aperture_diameter_mm": a_mm,
        "f_nyquist_cycles_per_mm": 1 / (2 * p_mm),
        "f_diffraction_cycles_per_mm": a_mm / (1.22 * lam_mm * f_mm) * 1.0,
        "diffraction_to_nyquist_ratio": ratio,
        "sqrt_apertures": math.sqrt(inputs.apertures),
        "r_sr": r_sr,
        "sr_limited_by": "apertures" if math.sqrt(inputs.apertures) <= ratio else "diffraction",
        "pixel_focal_length_px": f_pixels,
        "overlap_width_m": rx_mm * 1e-3,
        "overlap_height_m": ry_mm * 1e-3,
        "fov_h_deg": fov_h,
        "fov_v_deg": fov_v,
        "single_aperture_fov_h_deg": single_h,
        "equivalent_focal_length_mm": math.sqrt(inputs.apertures) * f_mm,
    }
    for key, value in result.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError("design inputs", f"{key} = {value} from {_shown(inputs)}", "inputs whose every "
                             "design quantity is a finite number", "Use the values of a real lens and sensor "
                             "(the defaults are the paper's prototype).")
    return result


def _up(value: float) -> str:
    """``value`` rounded up to 2 significant digits, for a suggested option value."""
    if not (math.isfinite(value) and value > 0):
        return f"{value:g}"
    digits = 1 - math.floor(math.log10(value))
    return f"{math.ceil(value * 10.0 ** digits) / 10.0 ** digits:.2g}"


def _shown(inputs: DesignInputs) -> str:
    return " ".join(f"--{k.replace('_', '-')} {v:g}" for k, v in asdict(inputs).items())
