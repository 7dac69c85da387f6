"""Plug-in methods and priors: bring your own reconstruction, from any package, without editing capssim.

**The contract.** A plug-in *method* is a callable ``fn(capture, **options)``: ``capture`` is the
:class:`~capssim.capture.Capture` that :func:`capssim.reconstruct.reconstruct` takes (raw frames
``caps_raw`` ``(4, H, W)``, ``dofp_raw`` ``(2H, 2W)``, ``meta``, ``hr_shape`` ``(2H, 2W)``, ``caps_float()``...),
``options`` the run's ``-p KEY=VALUE`` options (strings from the command line, a suite's values as written).
It returns the ``(12, 2H, 2W)`` floating-point image, channel ``c = 3 p + k`` (polarizer p over 0/45/90/135 deg,
colour k over R/G/B), linear on [0, 1], as a numpy array or a torch tensor, or a
:class:`~capssim.reconstruct.run_context.MethodOutput`. A function that also takes a ``device`` keyword gets the
run's torch device, one that takes ``context`` the :class:`~capssim.reconstruct.run_context.RunContext` (device,
``true_warps``, ``registration``, stage timer). Its *input kind* (``"caps"``, the camera array, or ``"dofp"``),
description and reference are attributes of the callable, set by the :func:`method` decorator or by hand;
defaults: ``"caps"``, the first line of its docstring, ``""``.

A plug-in *prior* is a factory ``factory(shape, *, parameters, options, device) -> Prior`` for the CAPS pipeline's
prior slot (:func:`capssim.reconstruct.pipeline.slots.register_prior` gives the protocol), chosen with
``-p prior=NAME``; its description and ``parameters`` dataclass come from the :func:`prior` decorator or attributes.

**Two ways in.** Installed packages declare entry points, and capssim loads them the first time the methods are
listed or looked up (:func:`capssim.reconstruct.registry.available_methods`), in every process, Dask workers
included::

    [project.entry-points."capssim.methods"]
    my-method = "my_package.module:my_method"
    [project.entry-points."capssim.priors"]
    my-prior = "my_package.module:my_prior_factory"

or, without installing anything, :func:`add_method` / :func:`add_prior` register them in this process (a suite
run in this process sees them; Dask workers do not). Either way they are listed by ``capssim reconstruct
--list`` with their package, run under ``capssim reconstruct -m NAME``, in suites, the error budget and the
regression check like built-in methods, and their records carry ``plugin`` (package, version, entry point).

**A broken plug-in never stops the others.** An entry point that does not import, is not callable, cannot take
a capture, names a built-in method or returns the wrong shape, a non-float dtype or non-finite values gives one
line naming the plug-in and its package (:class:`~capssim.errors.PluginError`), when it is listed or run; the
other methods run as before.
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Callable

import numpy as np
import torch

from capssim.errors import InputError, PluginError

from . import registry
from .pipeline.slots import _PRIORS, register_prior
from .registry import MethodSpec, available_methods
from .run_context import MethodOutput

log = logging.getLogger(__name__)

#: entry-point groups: ``NAME = module:callable`` registers the method / prior NAME
METHODS_GROUP = "capssim.methods"
PRIORS_GROUP = "capssim.priors"
INPUT_KINDS = ("caps", "dofp")

__all__ = ["INPUT_KINDS", "METHODS_GROUP", "PRIORS_GROUP", "Plugin", "add_method", "add_prior", "broken_plugins",
           "load_plugins", "method", "prior"]


@dataclass(frozen=True)
class Plugin:
    """Where a plug-in comes from: its name, kind (``method``/``prior``), package and version (``None`` when
    registered in this process without a package), and entry point (``module:callable``)."""

    name: str
    kind: str
    package: str | None
    version: str | None
    entry_point: str | None

    def label(self) -> str:
        """``plug-in method 'NAME' (package 1.0)``: how messages name it."""
        source = f"{self.package} {self.version or ''}".strip() if self.package else "registered in this process"
        return f"plug-in {self.kind} {self.name!r} ({source})"

    def record(self) -> dict:
        """The ``plugin`` field of a record."""
        return {"package": self.package, "version": self.version, "entry_point": self.entry_point}


#: plug-ins that failed to load: name -> their one-line message
_BROKEN: dict[str, str] = {}
_LOADED = False


# -- the public decorators --------------------------------------------------------------------------
def method(*, input_kind: str = "caps", description: str | None = None, reference: str = "") -> Callable:
    """Decorator declaring a plug-in method's input kind, description and reference (module docstring).

    Parameters
    ----------
    input_kind : {"caps", "dofp"}, keyword-only
        The camera array's four raw frames, or the DoFP mosaic.
    description : str, optional
        One line for ``capssim reconstruct --list`` (default: the docstring's first line).
    reference : str, keyword-only
        The paper or page the method comes from.

    Returns
    -------
    callable
        A decorator that sets ``input_kind``, ``description`` and ``reference`` on the function and returns it.
    """
    if input_kind not in INPUT_KINDS:
        raise InputError("input_kind", repr(input_kind), "'caps' or 'dofp'")

    def wrap(fn):
        fn.input_kind, fn.reference = input_kind, reference
        if description is not None:
            fn.description = description
        return fn

    return wrap


def prior(*, description: str | None = None, parameters: type | None = None) -> Callable:
    """Decorator declaring a plug-in prior factory's description and ``parameters`` dataclass (its own ``-p``
    options; :func:`~capssim.reconstruct.pipeline.slots.register_prior`)."""

    def wrap(factory):
        factory.parameters = parameters
        if description is not None:
            factory.description = description
        return factory

    return wrap


# -- registering --------------------------------------------------------------------------------------
def _description(fn, default: str) -> str:
    text = getattr(fn, "description", None) or (inspect.getdoc(fn) or "").strip().split("\n")[0]
    return str(text or default)


def _signature_problem(fn) -> str | None:
    """Why ``fn`` cannot be called as ``fn(capture)`` (None: it can)."""
    if not callable(fn):
        return f"is a {type(fn).__name__}, not a callable"
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return None  # a builtin without a signature: tried when it runs
    try:
        signature.bind(object())
    except TypeError as exc:
        return f"cannot be called with a capture as fn(capture, **options) ({exc})"
    return None


def _accepts(fn, name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False
    return name in params and params[name].kind in (inspect.Parameter.KEYWORD_ONLY,
                                                    inspect.Parameter.POSITIONAL_OR_KEYWORD)


def _option_names(fn) -> set[str] | None:
    """The keyword options ``fn`` takes (None: any, it has ``**options``)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return None
    if any(p.kind == inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return None
    names = [p.name for p in params.values() if p.kind in (inspect.Parameter.KEYWORD_ONLY,
                                                           inspect.Parameter.POSITIONAL_OR_KEYWORD)]
    return set(names[1:] if names and list(params)[0] == names[0] else names) - {"device", "context"}


def _image_of(plugin: Plugin, result, hr_shape: tuple[int, int]):
    """The checked ``(12, 2H, 2W)`` float32 image of a plug-in's result and the MethodOutput around it."""
    out = result if isinstance(result, MethodOutput) else MethodOutput(image=result)
    image = out.image
    if isinstance(image, torch.Tensor):
        image = image.detach().to("cpu").numpy()
    if not isinstance(image, np.ndarray):
        raise PluginError(f"{plugin.label()} returned a {type(image).__name__}; expected a (12, {hr_shape[0]}, "
                          f"{hr_shape[1]}) numpy array, torch tensor or MethodOutput.")
    if image.shape != (12, *hr_shape):
        raise PluginError(f"{plugin.label()} returned shape {tuple(image.shape)}; expected (12, {hr_shape[0]}, "
                          f"{hr_shape[1]}) (12 channels c = 3 p + k on the 2H x 2W grid).")
    if not np.issubdtype(image.dtype, np.floating):
        raise PluginError(f"{plugin.label()} returned dtype {image.dtype}; expected floating point (linear, "
                          "[0, 1] of full scale). Convert with image.astype(np.float32).")
    bad = int(np.size(image) - np.count_nonzero(np.isfinite(image)))
    if bad:
        raise PluginError(f"{plugin.label()} returned {bad} non-finite values (NaN or inf); expected a finite image.")
    out.image = image.astype(np.float32, copy=False)
    out.extra = {**out.extra, "plugin": plugin.record()}
    return out


def _method_function(plugin: Plugin, fn) -> Callable:
    """The registry's ``function(capture, *, context)`` around a plug-in ``fn(capture, **options)``."""
    options_taken = _option_names(fn)
    takes_device, takes_context = _accepts(fn, "device"), _accepts(fn, "context")

    def run(capture, *, context):
        options = dict(context.options)
        if options_taken is not None:
            unknown = sorted(set(options) - options_taken)
            if unknown:
                raise InputError("option", repr(unknown[0]), f"an option of {plugin.label()}: "
                                 + (", ".join(sorted(options_taken)) or "it takes none"))
        hr_shape = tuple(capture.hr_shape)  # the capture is looked at first (the command line's option probe stops here)
        if takes_device:
            options.setdefault("device", context.device)
        if takes_context:
            options["context"] = context
        try:
            with context.timer.stage(plugin.name):
                result = fn(capture, **options)
        except Exception as exc:  # a plug-in's own failure: one line naming it, the other methods run on
            text = " ".join(str(exc).split()) or "no message"
            raise PluginError(f"{plugin.label()} raised {type(exc).__name__}: {text}") from exc
        return _image_of(plugin, result, hr_shape)

    run.__name__ = run.__qualname__ = f"plugin_{plugin.name.replace('-', '_')}"
    run.__doc__ = inspect.getdoc(fn)
    return run


def _broken_function(message: str) -> Callable:
    def run(capture, *, context):
        raise PluginError(message)

    return run


def _method_problem(plugin: Plugin, fn, problem: str | None = None) -> str | None:
    """Why ``fn`` cannot be the method ``plugin`` (a one-line message naming it), or None."""

    taken = registry._METHODS.get(plugin.name)
    if taken is not None and taken.plugin is None:
        return (f"{plugin.label()}: the name is a built-in method's ({taken.module}); rename the entry point "
                "(the built-in method is kept).")
    if problem is None and getattr(fn, "input_kind", "caps") not in INPUT_KINDS:
        problem = (f"has input_kind {getattr(fn, 'input_kind')!r}; expected 'caps' or 'dofp' (set it with "
                   "capssim.reconstruct.plugins.method)")
    problem = problem or _signature_problem(fn)
    return None if problem is None else f"{plugin.label()} {problem}"


def _register_method(plugin: Plugin, fn, *, problem: str | None = None) -> str | None:
    """Register ``fn`` as ``plugin``, or, broken, a method that says why in one line; returns that line."""

    message = _method_problem(plugin, fn, problem)
    if message is not None:
        _BROKEN[plugin.name] = message
        taken = registry._METHODS.get(plugin.name)
        if taken is not None and taken.plugin is None:
            log.warning("%s", message)  # said nowhere else: the name stays the built-in's
            return message
        log.debug("%s", message)  # said when it is listed or run
        function, input_kind, description, reference = _broken_function(message), "caps", f"BROKEN: {message}", ""
    else:
        _BROKEN.pop(plugin.name, None)
        function, input_kind = _method_function(plugin, fn), getattr(fn, "input_kind", "caps")
        description = _description(fn, f"plug-in method from {plugin.package or 'this process'}")
        reference = str(getattr(fn, "reference", "") or "")
    module = getattr(fn, "__module__", None) or (plugin.entry_point or "?").split(":")[0]
    registry._METHODS[plugin.name] = MethodSpec(plugin.name, function, input_kind, description, reference, module,
                                       plugin=plugin)
    return message


def _prior_problem(plugin: Plugin, factory, problem: str | None = None) -> str | None:
    """Why ``factory`` cannot be the prior ``plugin`` (one line naming it), or None."""

    taken = _PRIORS.get(plugin.name)
    if taken is not None and not getattr(taken.factory, "capssim_plugin", None):
        return f"{plugin.label()}: the name is a built-in prior's; rename the entry point (the built-in prior is kept)."
    if problem is None and not callable(factory):
        problem = f"is a {type(factory).__name__}, not a callable"
    return None if problem is None else f"{plugin.label()} {problem}"


def _register_prior(plugin: Plugin, factory, *, problem: str | None = None) -> None:
    """Register ``factory`` in the CAPS pipeline's prior slot as ``plugin``, or, broken, a prior that says why."""

    message = _prior_problem(plugin, factory, problem)
    if message is not None:
        _BROKEN[f"prior:{plugin.name}"] = message
        taken = _PRIORS.get(plugin.name)
        if taken is not None and not getattr(taken.factory, "capssim_plugin", None):
            log.warning("%s", message)  # said nowhere else: the name stays the built-in's
            return
        log.debug("%s", message)

        def broken(shape, *, parameters, options, device):
            raise PluginError(message)

        broken.capssim_plugin = plugin
        register_prior(plugin.name, broken, description=f"BROKEN: {message}")
        return

    def wrapped(shape, *, parameters, options, device):
        try:
            return factory(shape, parameters=parameters, options=options, device=device)
        except Exception as exc:  # a plug-in's own failure: one line naming it
            text = " ".join(str(exc).split()) or "no message"
            raise PluginError(f"{plugin.label()} raised {type(exc).__name__}: {text}") from exc

    wrapped.capssim_plugin = plugin
    _BROKEN.pop(f"prior:{plugin.name}", None)
    register_prior(plugin.name, wrapped, description=_description(factory, f"plug-in prior from {plugin.package}"),
                   parameters=getattr(factory, "parameters", None))


def add_method(name: str, fn: Callable, *, input_kind: str | None = None, description: str | None = None,
               reference: str | None = None) -> None:
    """Register ``fn`` as the method ``name`` in this process, without installing a package.

    Parameters
    ----------
    name : str
        The method's name (``-m NAME``, a suite's ``methods:``); not a built-in method's.
    fn : callable
        ``fn(capture, **options)`` returning the ``(12, 2H, 2W)`` image (module docstring).
    input_kind, description, reference : str, optional, keyword-only
        Override the callable's attributes (:func:`method`).

    Raises
    ------
    PluginError
        One line: ``fn`` cannot take a capture, or ``name`` is a built-in method's.
    """

    available_methods()  # the built-in methods and entry points first: a name clash is found
    if input_kind is not None or description is not None or reference is not None:
        fn = method(input_kind=input_kind or getattr(fn, "input_kind", "caps"),
                    description=description if description is not None else getattr(fn, "description", None),
                    reference=reference if reference is not None else getattr(fn, "reference", ""))(fn)
    plugin = Plugin(name, "method", None, None, f"{getattr(fn, '__module__', '?')}:{getattr(fn, '__qualname__', '?')}")
    message = _method_problem(plugin, fn)
    if message is not None:
        raise PluginError(message)
    _register_method(plugin, fn)


def add_prior(name: str, factory: Callable, *, description: str | None = None,
              parameters: type | None = None) -> None:
    """Register the prior factory ``factory`` as ``-p prior=NAME`` in this process (module docstring)."""

    available_methods()
    if description is not None or parameters is not None:
        factory = prior(description=description, parameters=parameters)(factory)
    plugin = Plugin(name, "prior", None, None, f"{getattr(factory, '__module__', '?')}:"
                                                f"{getattr(factory, '__qualname__', '?')}")
    message = _prior_problem(plugin, factory)
    if message is not None:
        raise PluginError(message)
    _register_prior(plugin, factory)


# -- loading the entry points ------------------------------------------------------------------------
def _from_entry_point(point, kind: str) -> tuple[Plugin, object, str | None]:
    dist = getattr(point, "dist", None)
    package = version = None
    if dist is not None:
        package = dist.metadata["Name"] if dist.metadata is not None else None
        version = dist.version
    plugin = Plugin(point.name, kind, package or point.module.split(".")[0], version, point.value)
    try:
        return plugin, point.load(), None
    except Exception as exc:  # noqa: BLE001 - an import error of the plug-in: named, the others load on
        text = " ".join(str(exc).split()) or "no message"
        return plugin, None, f"does not load ({point.value}: {type(exc).__name__}: {text})"


def load_plugins() -> None:
    """Register every entry point of :data:`METHODS_GROUP` and :data:`PRIORS_GROUP`, once per process (called by
    :func:`capssim.reconstruct.registry.available_methods` after the built-in methods)."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    for point in entry_points(group=METHODS_GROUP):
        plugin, fn, problem = _from_entry_point(point, "method")
        _register_method(plugin, fn, problem=problem)
    for point in entry_points(group=PRIORS_GROUP):
        plugin, factory, problem = _from_entry_point(point, "prior")
        _register_prior(plugin, factory, problem=problem)


def broken_plugins() -> dict[str, str]:
    """The plug-ins that failed to load or register: name (``prior:NAME`` for a prior) -> one-line message."""
    return dict(_BROKEN)
