"""Registration of the four apertures of a CAPS capture (paper section 3.1): their homographies from the data alone.

The room's public face is :func:`estimate_lr_homographies` (:mod:`.estimate`) and its options
:class:`RegistrationParameters` (:mod:`.parameters`). Inside: the registration images
(:mod:`.luminance`), the multi-aperture engine (:mod:`.engine`: candidates :mod:`.rescue`, pyramid
:mod:`.levels`, criterion :mod:`.criterion` minimized by :mod:`.lbfgs`, motion models and spline resampling :mod:`.motion`, small
image operations :mod:`.image_ops`) and the store of estimated warps beside a capture (:mod:`.store`).
"""

from .estimate import (
    REGISTRATION_MODES,
    RegistrationParameters,
    RegistrationResult,
    estimate_lr_homographies,
    registration_parameters,
)

__all__ = ["REGISTRATION_MODES", "RegistrationParameters", "RegistrationResult", "estimate_lr_homographies",
           "registration_parameters"]
