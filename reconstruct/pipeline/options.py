"""The options of the CAPS pipeline (``-p NAME=VALUE``) and the public option parsing every method shares.

:func:`coerce_option` turns one raw option (a string from the command line, or a typed value from
Python or a suite file) into the type of its default; :class:`CapsOptions` holds every option of the
CAPS pipeline (:mod:`capssim.reconstruct.pipeline.run`): one parameter object per step, each with its
own defaults, plus the names of the data term and the prior (:mod:`.slots`) and the prior's own
parameters. ``caps-naive`` and ``caps-sisr`` parse their options with :func:`coerce_option` too and
ignore the CAPS option names (:func:`caps_option_names`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from capssim.errors import InputError, UnknownNameError

from ..model.cagf import CAGFParameters
from ..model.observation_model import CAPTURE_PSF_SIGMA
from ..priors.nlstr import NLSTRParameters
from ..priors.nlstr_prior import MatchSchedule
from ..solvers.admm import ADMMParameters
from ..solvers.interfaces import DivergenceError
from .slots import (
    DEFAULT_DATA_TERM,
    DEFAULT_PRIOR,
    available_priors,
    get_data_term,
    get_prior,
    parameter_defaults,
    prior_option_names,
    reserve_option_names,
)

__all__ = ["PRESETS", "CapsOptions", "caps_option_names", "coerce_option", "explain_divergence", "given_option_names",
           "wants_ground_truth"]


def given_option_names(options) -> frozenset[str]:
    """The names of the options given (``-p NAME=VALUE``, a mapping), as the pipeline reads them: ``-`` as ``_``."""
    return frozenset(str(key).replace("-", "_") for key in dict(options or {}))


def coerce_option(name: str, raw, kind: type):
    """``raw`` as a value of ``kind`` (``bool``, ``int``, ``float`` or ``str``), for the option ``name``.

    Parameters
    ----------
    name : str
        The option's name, for the error message.
    raw : object
        A value of ``kind`` (returned as it is) or its text: ``1/true/yes/on`` and ``0/false/no/off``
        for a bool, an integral number for an int, a finite number for a float.
    kind : type
        The option's type, usually the type of its default.

    Returns
    -------
    object
        The value, of type ``kind``.

    Raises
    ------
    InputError
        Naming ``option NAME`` when ``raw`` is not a value of ``kind``.
    """
    if isinstance(raw, kind) and not (kind is int and isinstance(raw, bool)):
        return raw
    text = str(raw).strip()
    try:
        if kind is bool:
            if text.lower() in ("1", "true", "yes", "on"):
                return True
            if text.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if kind is int:
            as_float = float(text)
            if not as_float.is_integer():
                raise ValueError
            return int(as_float)
        if kind is float:
            value = float(text)
            if not math.isfinite(value):
                raise ValueError
            return value
        return text
    except ValueError:
        expected = {bool: "a boolean (true/false, yes/no, 1/0)", int: "an integer",
                    float: "a finite number"}.get(kind, f"a value of type {kind.__name__}")
        raise InputError(f"option {name}", repr(raw), expected,
                         f"Give {name} as {expected} (-p {name}=VALUE on the command line; 'capssim reconstruct "
                         "--options METHOD' lists every option with its default and range).") from None


def wants_ground_truth(options: dict) -> bool:
    """True when ``options`` (``-p`` strings or typed values) set ``track_psnr``: the capture's ``gt.tiff``
    must then be read with it, or no PSNR is tracked. A value that is no bool is left to the method's parser."""
    raw = dict(options or {}).get("track_psnr", False)
    try:
        return bool(coerce_option("track_psnr", raw, bool))
    except InputError:
        return False


@dataclass
class CapsOptions:
    """Every option of the CAPS pipeline: one parameter object per step, each with its own defaults.

    The paper's defaults (section 5.1; table in docs/guides/captures.md, "The paper's parameters") live in the parameter classes:
    :class:`ADMMParameters` (eq. 27-28), :class:`MatchSchedule` (NLSTR's block matching
    across iterations), :class:`NLSTRParameters` (section 3.3) and :class:`CAGFParameters`
    (section 3.2). The user-facing option names (``-p NAME=VALUE``, the ``params`` of the
    JSON record) are :meth:`option_names`: the fields of those classes, except that CAGF's
    ``radius`` and ``eps`` are ``cagf_radius`` and ``cagf_eps`` and NLSTR's ``eps`` is not an
    option; then ``data_term`` and ``prior`` (names of :mod:`.slots`). A registered prior's own
    parameters (``prior_parameters``) are options too while that prior is chosen.
    """

    admm: ADMMParameters = field(default_factory=ADMMParameters)
    matching: MatchSchedule = field(default_factory=MatchSchedule)
    nlstr: NLSTRParameters = field(default_factory=NLSTRParameters)
    cagf: CAGFParameters = field(default_factory=CAGFParameters)
    # observation model
    psf_sigma: float = CAPTURE_PSF_SIGMA  # the capture's PSF; >= 0: a Gaussian of this std (HR px)
    fov_mask: bool = True
    # the pipeline's slots (capssim.reconstruct.pipeline.slots)
    data_term: str = DEFAULT_DATA_TERM
    prior: str = DEFAULT_PRIOR
    # diagnostics
    track_psnr: bool = False
    # named settings (PRESETS); explicit options override the preset's
    preset: str = "default"
    #: the chosen prior's own parameters (an instance of its registered ``parameters`` class, or None)
    prior_parameters: object = None

    @staticmethod
    def option_names() -> tuple[str, ...]:
        """The option names every prior shares, in the order of :meth:`to_dict`."""
        return tuple(_OPTIONS)

    @classmethod
    def from_options(cls, options: dict, **overrides) -> "CapsOptions":
        """Parse ``{name: value}`` (strings coerced to each option's type) over the typed defaults ``overrides``."""
        options = {str(key).replace("-", "_"): (key, raw) for key, raw in dict(options or {}).items()}
        preset = str(options.get("preset", (None, overrides.get("preset", "default")))[1]).strip()
        if preset not in PRESETS:
            raise UnknownNameError("preset", preset, list(PRESETS))
        values = {**overrides, **PRESETS[preset], "preset": preset}
        prior = str(options.get("prior", (None, values.get("prior", DEFAULT_PRIOR)))[1]).strip()
        own = parameter_defaults(get_prior(prior))  # the chosen prior's own options and their defaults
        own_values = {}
        for name, (key, raw) in options.items():
            if name in _OPTIONS:
                values[name] = coerce_option(name, raw, type(_default(name)))
            elif name in own:
                own_values[name] = coerce_option(name, raw, type(own[name]))
            elif name in prior_option_names():
                owners = [spec for spec in available_priors().values() if name in parameter_defaults(spec)]
                raise InputError(f"option {key}", f"prior {prior!r}", f"prior {owners[0].name!r}, whose option it is",
                                 f"Add -p prior={owners[0].name}, or leave {key} out.")
            else:
                raise UnknownNameError("option", key, [*_OPTIONS, *own])
        groups: dict[str, dict] = {group: {} for group in _GROUPS}
        top = {}
        for name, value in values.items():
            if name in own:
                own_values.setdefault(name, value)
                continue
            if name not in _OPTIONS and name not in options and name in prior_option_names():
                continue  # a method's default for its own prior, which -p prior=NAME replaced
            if name not in _OPTIONS:
                raise UnknownNameError("option", name, [*_OPTIONS, *own])
            group, attr = _OPTIONS[name]
            (groups[group] if group else top)[attr] = value
        top["prior"] = prior
        top["data_term"] = get_data_term(str(top.get("data_term", DEFAULT_DATA_TERM)).strip()).name
        spec = get_prior(prior)
        parameters = None if spec.parameters is None else spec.parameters(**own_values)
        return cls(**{group: _GROUPS[group](**kw) for group, kw in groups.items()}, **top,
                   prior_parameters=parameters)

    def validated_parameters(self) -> tuple[ADMMParameters, NLSTRParameters]:
        """Check every parameter group (:class:`InputError` on a bad value); return the ADMM and NLSTR ones."""
        self.admm.validate()
        self.matching.validate()
        self.nlstr.validate()
        if callable(getattr(self.prior_parameters, "validate", None)):
            self.prior_parameters.validate()
        return self.admm, self.nlstr

    def to_dict(self) -> dict:
        """``{option name: value}`` for every option (the method's ``params`` record), the prior's own last."""
        record = {name: getattr(getattr(self, group) if group else self, attr)
                  for name, (group, attr) in _OPTIONS.items()}
        if self.prior_parameters is not None:
            record.update({f.name: getattr(self.prior_parameters, f.name) for f in fields(self.prior_parameters)})
        return record


#: named settings of the CAPS methods (``-p preset=NAME``): the options each sets; explicit options win.
#: ``default``: the paper's parameters (section 5.1), dictionaries every 5th iteration; ``literal``:
#: Algorithm 1 as written, dictionaries at every iteration (same metrics within 0.08 dB, slower);
#: ``fast``: 7 iterations, block matching on the 3 leading principal components of the channels and at
#: most every 4th iteration, dictionaries every 4th, reference blocks every 6 px: about 3.8x faster at
#: 512 px with stored warps, within 0.2 dB on kettle and textured (docs/notes/reconstruction-speed.md;
#: ``caps-fast`` in the ``ablation`` suite).
PRESETS: dict[str, dict] = {
    "default": {},
    "literal": {"dictionary_gap": 1},
    "fast": {"iterations": 7, "dictionary_gap": 4, "stride": 6, "match_components": 3, "rematch_min_gap": 4},
}

#: the parameter group of each CapsOptions field that holds one
_GROUPS = {"admm": ADMMParameters, "matching": MatchSchedule, "nlstr": NLSTRParameters, "cagf": CAGFParameters}


def _option_table() -> dict[str, tuple[str | None, str]]:
    """Option name -> (group field of CapsOptions or None, attribute), in the record's order."""
    renamed = {("cagf", "radius"): "cagf_radius", ("cagf", "eps"): "cagf_eps"}
    hidden = {("nlstr", "eps")}
    table = {}
    for group, kind in _GROUPS.items():
        for f in fields(kind):
            if (group, f.name) not in hidden:
                table[renamed.get((group, f.name), f.name)] = (group, f.name)
    for f in fields(CapsOptions):
        if f.name not in _GROUPS and f.name != "prior_parameters":
            table[f.name] = (None, f.name)
    return table


_OPTIONS = _option_table()
reserve_option_names(_OPTIONS)


def _default(name: str):
    group, attr = _OPTIONS[name]
    return getattr(_GROUPS[group] if group else CapsOptions, attr)


def caps_option_names() -> frozenset[str]:
    """Every option name of the CAPS pipeline: the shared ones and those of every registered prior."""
    return frozenset(_OPTIONS) | prior_option_names()


def explain_divergence(exc: DivergenceError, opts: CapsOptions, defaults: CapsOptions) -> DivergenceError:
    """``exc`` naming the options set away from ``defaults`` (the likely cause), or ``dt`` if none is."""
    base = defaults.to_dict()
    changed = {k: v for k, v in opts.to_dict().items()
               if k not in ("iterations", "track_psnr", "preset") and k in base and v != base[k]}
    if not changed:
        return exc
    names = ", ".join(changed)
    return DivergenceError(f"option {names}",
                           ", ".join(f"{k}={v}" for k, v in changed.items()), solver=exc.solver,
                           iteration=exc.iteration, peak=exc.peak, bound=exc.bound,
                           fix="Set " + names + " back towards the default (" +
                               ", ".join(f"{k}={base[k]}" for k in changed) + ").")
