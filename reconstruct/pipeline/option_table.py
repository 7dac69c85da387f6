"""Every ``-p`` option a CAPS method takes, one line each: name, default, valid values, meaning.

``capssim reconstruct --options METHOD`` prints a method's :class:`MethodOption` list, and the unknown-option
error (:func:`unknown_option`) lists every name of it with the nearest one ("did you mean"). The pipeline's
options (:class:`~capssim.reconstruct.pipeline.options.CapsOptions`, paper section 5.1 for their defaults)
are described here once; a method adds its own (e.g. ``caps-plus``'s selection options) and its defaults.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

from capssim.errors import InputError

from .options import CapsOptions, _default
from .slots import available_data_terms, available_priors, parameter_defaults

__all__ = ["CAPS_OPTION_MEANINGS", "MethodOption", "caps_method_options", "check_option_names", "format_options",
           "unknown_option"]


@dataclass(frozen=True)
class MethodOption:
    """One ``-p NAME=VALUE`` option of a method: its default, valid values and one line of meaning."""

    name: str
    default: object
    valid: str
    meaning: str


#: name -> (valid values, meaning) of every option of the CAPS pipeline (paper section 5.1 for the defaults)
CAPS_OPTION_MEANINGS: dict[str, tuple[str, str]] = {
    "iterations": ("integer in [0, 1000]", "ADMM iterations (eq. 20-30; the paper's 25)"),
    "mu0": ("number in (0, 1]", "the first penalty weight mu of eq. 27"),
    "grow_rate": ("number >= 0", "mu grows by this every grow_step iterations (eq. 27)"),
    "grow_step": ("integer >= 1", "iterations between two growths of mu (eq. 27)"),
    "dt": ("number > 0", "step of the data term's gradient step (eq. 25-26)"),
    "n_similar": ("integer >= 1", "similar blocks per group of NLSTR's block matching (section 3.3)"),
    "n_similar_step": ("integer >= 0", "the group shrinks by this at each re-match"),
    "n_similar_min": ("integer >= 1", "the smallest group size"),
    "rematch_change": ("number >= 0", "relative image change that triggers a new block matching"),
    "rematch_min_gap": ("integer >= 1", "fewest iterations between two block matchings"),
    "rematch_max_gap": ("integer >= 1", "most iterations between two block matchings"),
    "dictionary_gap": ("integer >= 1", "iterations between two dictionary (SVD) updates of NLSTR"),
    "block": ("integer >= 2", "NLSTR block side (HR px)"),
    "stride": ("integer >= 1", "step between reference blocks (HR px)"),
    "search_radius": ("integer >= 1", "block-matching search radius (HR px)"),
    "match_components": ("integer >= 0", "principal components of the channels block matching uses (0: all)"),
    "c1": ("number >= 0", "the sparse-code threshold constant c1 (eq. 22)"),
    "c2": ("number >= 0", "the adaptive weight constant c2 (eq. 28)"),
    "adaptive": ("element or scalar", "the adaptive weight of eq. 28 per element or one per image"),
    "weight_bandwidth": ("number > 0", "bandwidth of the similarity weights of a group"),
    "strip_mb": ("number > 0", "memory of one strip of NLSTR's batched work (MB)"),
    "nu": ("number >= 0", "the weight of the group mean in NLSTR's estimate"),
    "cagf_radius": ("integer >= 1, below the sub-image size", "CAGF's guided-filter window radius (eq. 12-14)"),
    "cagf_eps": ("number > 0", "CAGF's guided-filter regularizer (eq. 12-14)"),
    "psf_sigma": ("-1, or number >= 0", "the PSF std in HR px (-1: the capture's own)"),
    "fov_mask": ("true or false", "give 0 weight to observations outside the reference view"),
    "data_term": ("a registered data term", "the data term slot (cagf: eq. 15-16, 25-26)"),
    "prior": ("a registered prior", "the prior slot (nlstr: section 3.3)"),
    "track_psnr": ("true or false", "record the PSNR against gt.tiff after every iteration"),
    "preset": ("default, literal or fast", "a named set of the options above (explicit options win)"),
}
#: one line of meaning of each registered prior's own options (shown while that prior is chosen)
PRIOR_OPTION_MEANINGS: dict[str, str] = {
    "denoiser_blend": "the learned denoiser's share of the intensity in nlstr-denoiser (0: NLSTR alone)",
    "denoiser_sigma_start": "the denoiser's noise level at the first iteration",
    "denoiser_sigma_end": "the denoiser's noise level at the end of its schedule",
    "denoiser_sigma_steps": "iterations over which the denoiser's noise level falls (0: the whole run)",
    "denoiser_weights": "a trained denoiser's model.pt (default: the shipped weights)",
    "denoiser_precision": "the denoiser's arithmetic (float32 or bfloat16)",
    "tikhonov_weight": "the weight of the Tikhonov prior",
}


def caps_method_options(defaults: dict | None = None) -> list[MethodOption]:
    """The pipeline's options with a method's ``defaults`` (``PipelineConfig.defaults``) over the paper's; the
    options of the default prior follow."""
    defaults = dict(defaults or {})
    out = []
    for name in CapsOptions.option_names():
        valid, meaning = CAPS_OPTION_MEANINGS.get(name, ("see the reconstruction guide", ""))
        if name == "data_term":
            valid = "one of " + ", ".join(available_data_terms())
        elif name == "prior":
            valid = "one of " + ", ".join(available_priors())
        out.append(MethodOption(name, defaults.get(name, _default(name)), valid, meaning))
    prior = str(defaults.get("prior", _default("prior")))
    for name, value in parameter_defaults(available_priors()[prior]).items():
        out.append(MethodOption(name, defaults.get(name, value), f"see prior {prior!r}",
                                PRIOR_OPTION_MEANINGS.get(name, f"an option of the {prior} prior")))
    return out


def format_options(method: str, options: list[MethodOption]) -> str:
    """The lines ``capssim reconstruct --options METHOD`` prints: one option per line."""
    width = max((len(o.name) for o in options), default=4)
    lines = [f"{method}: {len(options)} options (-p NAME=VALUE)"]
    lines += [f"  {o.name:<{width}}  default {o.default!r:<12} valid: {o.valid}. {o.meaning}" for o in options]
    return "\n".join(lines)


def unknown_option(method: str, name: str, options: list[MethodOption]) -> InputError:
    """The refusal of an option ``name`` that ``method`` does not take: every valid name, and the nearest."""
    names = [o.name for o in options]
    close = difflib.get_close_matches(str(name).replace("-", "_"), names, n=1)
    fix = (f"Did you mean {close[0]!r}? " if close else "") + f"capssim reconstruct --options {method} describes each."
    return InputError(f"option {name}", f"an unknown option of {method!r}",
                      f"one of {', '.join(names)}", fix)


def check_option_names(method: str, given, options: list[MethodOption], *, also=()) -> None:
    """Refuse (:func:`unknown_option`) the first name of ``given`` (``-`` read as ``_``) that is neither one of
    ``options`` nor of ``also`` (the options of a prior chosen by ``-p prior=``)."""
    known = {o.name for o in options} | set(also)
    for key in dict(given or {}):
        if str(key).replace("-", "_") not in known:
            raise unknown_option(method, str(key), options)
