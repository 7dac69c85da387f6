"""Parameters of the aperture registration (paper section 3.1) and its named modes.

:class:`RegistrationParameters` holds every option of
:func:`capssim.reconstruct.registration.estimate_lr_homographies`; :data:`REGISTRATION_MODES`
names the parameter sets a user picks with ``capssim reconstruct --registration NAME``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from capssim.errors import InputError, UnknownNameError

from .luminance import LUMINANCE_METHODS
from .motion import MOTION_MODELS

#: the largest aperture rotation (deg) and relative scale error a camera array plausibly has; the
#: simulator draws at most 0.5 deg and 0.005. A larger estimate is a false match (e.g. a polarizing
#: wheel, whose analyzer images are rotated copies of each other) and falls back to the identity.
MAX_PLAUSIBLE_ROTATION_DEG = 5.0
MAX_PLAUSIBLE_SCALE_ERROR = 0.05


@dataclass(frozen=True)
class RegistrationParameters:
    """Options of :func:`~capssim.reconstruct.registration.estimate_lr_homographies`.

    Attributes
    ----------
    model
        motion model of each aperture: ``translation``, ``euclidean``, ``similarity`` (default; the
        paper's synthetic protocol), ``affine`` or ``homography``.
    luminance
        the registration image of each aperture: ``auto`` (default: the more Stokes-consistent of the
        two), or one of :data:`~capssim.reconstruct.registration.luminance.LUMINANCE_METHODS`,
        ``binomial`` or ``ri-binomial``.
    window_radius
        radius (pyramid-level pixels) of the local photometric-fit windows.
    stokes_weight, stokes_levels
        weight of the Stokes-consistency term ``I0 + I90 = I45 + I135`` and on how many of the finest
        pyramid levels it is used (0 turns it off: pairwise local correlation only).
    max_iterations
        L-BFGS iterations per pyramid level.
    min_correlation
        below this final local R^2 an aperture is flagged unreliable (warning + flag).
    robust_power, robust_levels, robust_passes, robust_window_radius
        IRLS on the ``robust_levels`` finest levels: ``robust_passes`` passes with windows weighted
        by their local R^2 to the power ``robust_power`` and of radius ``robust_window_radius``
        (None: ``window_radius``; the default 1, 3 x 3 windows, straddles fewer differently
        polarized structures).
    presmooth_sigma
        std (raw pixels) of a Gaussian blur of the registration images (0: none).
    stokes_subspace_std
        > 0: end with the Stokes-subspace refinement (:mod:`~capssim.reconstruct.registration.rescue`),
        moving only along directions the Stokes residual fixes to within this many raw pixels (mode
        ``stokes-subspace``: 0.01). For Stokes-consistent data whose polarization texture biases the
        local correlation.
    max_rotation_deg, max_scale_error
        an aperture warp rotated by more than this (degrees) or scaled by more than
        ``1 +- max_scale_error`` is not a camera array's: it falls back to the identity with a
        warning (``fallback`` ``identity: implausible warp``).
    retry_window_radius
        when some warp is implausible, the registration runs again with local-correlation windows of
        this radius (raw pixels; 0: no retry) and keeps the new warps if all of them are plausible and
        their registered images obey ``I0 + I90 = I45 + I135`` better (lower Stokes residual). Small
        windows lock onto aliased periodic texture (a 512 px Siemens star); wider ones see more of it.
    polarization_cue_radius
        when the structure is in the polarization only (flat ``S0``), the motion common to the 45 and 135 deg
        apertures, which no intensity criterion sees, is searched within this many raw pixels and set by the
        smoothness of the linear polarization
        (:mod:`~capssim.reconstruct.registration.polarization_cue`; 0: off, a warning only).
    half_resolution_min_size
        > 0: fit the warps down to the half-resolution pyramid level only wherever that level's shorter side has
        at least this many pixels (0: always down to full resolution). The restart from more peaks then refines
        at full resolution only the starts that beat the current estimate at half resolution. Mode
        ``fast``: 128, so 512 px frames and larger register at half resolution, about 2-4x faster, at a
        measured cost in warp accuracy (docs: notes/registration.md).
    """

    model: str = "similarity"
    luminance: str = "auto"
    window_radius: int = 3
    stokes_weight: float = 1.0
    stokes_levels: int = 2
    max_iterations: int = 60
    min_correlation: float = 0.3
    robust_power: float = 4.0
    robust_levels: int = 2
    robust_passes: int = 2
    robust_window_radius: int | None = 1
    presmooth_sigma: float = 0.0
    stokes_subspace_std: float = 0.0
    max_rotation_deg: float = MAX_PLAUSIBLE_ROTATION_DEG
    max_scale_error: float = MAX_PLAUSIBLE_SCALE_ERROR
    retry_window_radius: int = 6
    polarization_cue_radius: float = 6.0
    half_resolution_min_size: int = 0

    @classmethod
    def for_mode(cls, name: str) -> RegistrationParameters:
        """The parameters of a :data:`REGISTRATION_MODES` name."""
        return registration_parameters(name)

    def replace(self, **changes) -> RegistrationParameters:
        """A copy with some fields changed.

        Parameters
        ----------
        **changes
            Field names as keywords, e.g. ``model="affine"``.

        Returns
        -------
        RegistrationParameters
        """
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise UnknownNameError("registration parameter", unknown[0], [f.name for f in dataclasses.fields(self)])
        return dataclasses.replace(self, **changes)

    def validate(self) -> RegistrationParameters:
        """Raise :class:`~capssim.errors.InputError` (or ``UnknownNameError``) for a bad value; return ``self``."""
        if self.model not in MOTION_MODELS:
            raise UnknownNameError("registration model", self.model, list(MOTION_MODELS))
        if self.luminance not in LUMINANCE_METHODS and self.luminance != "auto":
            raise UnknownNameError("luminance", self.luminance, [*LUMINANCE_METHODS, "auto"])
        if not (self.stokes_weight >= 0 and math.isfinite(self.stokes_weight)):
            raise InputError("stokes_weight", self.stokes_weight, "a finite number >= 0")
        if not (self.stokes_subspace_std >= 0 and math.isfinite(self.stokes_subspace_std)):
            raise InputError("stokes_subspace_std", self.stokes_subspace_std, "a finite number >= 0 (0: off)")
        if not (self.max_rotation_deg > 0 and math.isfinite(self.max_rotation_deg)):
            raise InputError("max_rotation_deg", self.max_rotation_deg, "a finite angle > 0 in degrees")
        if not (0 <= self.polarization_cue_radius <= 64 and math.isfinite(self.polarization_cue_radius)):
            raise InputError("polarization_cue_radius", self.polarization_cue_radius,
                             "a search radius in raw pixels in [0, 64] (0: off)")
        if not (0 < self.max_scale_error < 1):
            raise InputError("max_scale_error", self.max_scale_error, "a relative scale error in (0, 1)")
        for name in ("window_radius", "stokes_levels", "max_iterations", "robust_levels", "robust_passes",
                     "retry_window_radius", "half_resolution_min_size"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (1 if name == "max_iterations" else 0):
                raise InputError(name, value, "an integer >= 1" if name == "max_iterations" else "an integer >= 0")
        if self.robust_window_radius is not None and (isinstance(self.robust_window_radius, bool) or not isinstance(
                self.robust_window_radius, int) or self.robust_window_radius < 0):
            raise InputError("robust_window_radius", self.robust_window_radius,
                             "an integer >= 0, or None (window_radius)")
        for name in ("robust_power", "presmooth_sigma"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise InputError(name, value, "a finite number >= 0")
        if not math.isfinite(self.min_correlation):
            raise InputError("min_correlation", self.min_correlation, "a finite local R^2 threshold (0 to 1)")
        return self


#: named registration modes (``capssim reconstruct --registration NAME``)
REGISTRATION_MODES: dict[str, RegistrationParameters] = {
    "local-correlation": RegistrationParameters(),
    "binomial-luminance": RegistrationParameters(luminance="binomial"),
    "ri-luminance": RegistrationParameters(luminance="ri-binomial"),
    "stokes-subspace": RegistrationParameters(stokes_subspace_std=0.01, luminance="binomial"),
    "fast": RegistrationParameters(luminance="binomial", half_resolution_min_size=128),
}


def registration_parameters(mode: str) -> RegistrationParameters:
    """The :class:`RegistrationParameters` of a named registration mode.

    Parameters
    ----------
    mode : str
        A :data:`REGISTRATION_MODES` name, e.g. ``local-correlation``.

    Returns
    -------
    RegistrationParameters
        A frozen value; ``.replace(field=value)`` gives a modified copy.

    Raises
    ------
    UnknownNameError
        An unknown mode (the message lists them).
    """
    if mode not in REGISTRATION_MODES:
        raise UnknownNameError("registration mode", mode, list(REGISTRATION_MODES))
    return REGISTRATION_MODES[mode]
