"""Choosing the Mitsuba 3 variant: the cheapest one that a scene needs, on the fastest backend that works.

What a scene needs (:class:`~capssim.render.scene_base.SceneInfo`):

* ``polarizing``: some element changes the polarization state (a polarizer plate, a smooth
  dielectric, a conductor, ``pplastic``). Otherwise every ray carries unpolarized light
  (emitters are unpolarized) and ``S1 = S2 = 0`` exactly, so an unpolarized variant is exact.
* ``spectral``: some reflectance or emission is not spectrally flat (a colour chart, a
  natural image, coloured paint, dispersion). Otherwise a neutral scene under the D65
  white-balance illuminant gives camera RGB = ``(1, 1, 1)`` x the monochrome value exactly,
  and a ``mono`` variant (one wavelength sample per ray instead of four) is exact.

Backends, fastest first: ``cuda`` -> ``llvm`` -> ``scalar``. The LLVM backend needs
libLLVM >= 16 (Debian's libLLVM 15 aborts with ``Cannot select ... fminimum``);
:func:`configure_llvm_environment` points ``DRJIT_LIBLLVM_PATH`` at libLLVM 19 when it is
installed and no path was set. The scalar backend has no ``mono`` variants, so there a
neutral scene uses ``scalar_spectral[_polarized]``. The throughput of each backend is in
``docs/notes/rendering-internals.md``.
"""

from __future__ import annotations

import glob
import logging
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from functools import lru_cache

from capssim.errors import InputError

log = logging.getLogger(__name__)

#: libLLVM builds Dr.Jit's LLVM backend is known to work with (newest first).
LLVM_LIBRARY_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/*/libLLVM.so.2[0-9]*",
    "/usr/lib/*/libLLVM.so.19*",
    "/usr/lib/*/libLLVM-19.so*",
    "/usr/lib/*/libLLVM.so.1[6-8]*",
    "/usr/lib/*/libLLVM-1[6-8].so*",
)
MIN_TRUSTED_LLVM = 19   # used without a probe
MIN_PROBED_LLVM = 16    # 16..18: a subprocess probe decides (a failing LLVM aborts the process)
BACKENDS = ("cuda", "llvm", "scalar")

_notices_given: set[str] = set()


def configure_llvm_environment() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 if none is set and one is installed.

    Must run before ``drjit`` is imported (``capssim.render`` calls it on import). Returns
    the path in effect, or ``None``.
    """
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current:
        return current
    for pattern in LLVM_LIBRARY_GLOBS:
        hits = sorted(glob.glob(pattern), reverse=True)
        if hits:
            os.environ["DRJIT_LIBLLVM_PATH"] = hits[0]
            return hits[0]
    return None


def _notice(key: str, message: str) -> None:
    """Log a one-line warning once per process."""
    if key not in _notices_given:
        _notices_given.add(key)
        log.warning(message)


def variant_name(backend: str, *, spectral: bool, polarized: bool) -> str:
    """The Mitsuba variant for a backend and the needs of a scene (see module docstring)."""
    if backend == "scalar":
        return "scalar_spectral_polarized" if polarized else "scalar_spectral"
    colour = "spectral" if spectral else "mono"
    return f"{backend}_ad_{colour}{'_polarized' if polarized else ''}"


def _probe_llvm_subprocess() -> bool:
    """Render a 4x4 image with the LLVM backend in a child process (LLVM errors abort)."""
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_mono_polarized');"
            "import drjit as dr; s = mi.load_dict({'type': 'scene', 'sensor': {'type': 'perspective',"
            "'film': {'type': 'hdrfilm', 'width': 4, 'height': 4}}});"
            "dr.eval(mi.render(s, spp=1)); print('ok')")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                             env=dict(os.environ))
    except (OSError, subprocess.TimeoutExpired):
        return False
    return out.returncode == 0 and out.stdout.strip().endswith("ok")


@lru_cache(maxsize=None)
def backend_status(backend: str) -> tuple[bool, str]:
    """``(works, reason)`` for ``cuda``, ``llvm`` or ``scalar`` in this process (cached)."""
    import mitsuba as mi

    available = set(mi.variants())
    if backend == "scalar":
        ok = "scalar_spectral_polarized" in available
        return ok, "" if ok else "the Mitsuba build has no scalar_spectral_polarized variant"
    if not any(v.startswith(f"{backend}_ad_") for v in available):
        return False, f"the Mitsuba build has no {backend} variants"
    import drjit as dr

    if backend == "cuda":
        ok = bool(dr.has_backend(dr.JitBackend.CUDA))
        return ok, "" if ok else "no CUDA device"
    if not dr.has_backend(dr.JitBackend.LLVM):
        return False, ("libLLVM not found (install libllvm19, or set DRJIT_LIBLLVM_PATH to "
                       "libLLVM.so.19.1)")
    try:
        version = tuple(int(v) for v in dr.detail.llvm_version())
    except Exception:  # older Dr.Jit without the query
        version = (0,)
    if version[0] >= MIN_TRUSTED_LLVM:
        return True, ""
    if version[0] >= MIN_PROBED_LLVM and _probe_llvm_subprocess():
        return True, ""
    shown = ".".join(str(v) for v in version) if version[0] else "unknown"
    return False, (f"libLLVM {shown} cannot compile Mitsuba's kernels (needs >= {MIN_PROBED_LLVM}); "
                   "install libllvm19 and set DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")


@dataclass(frozen=True)
class VariantChoice:
    """The variant used and why: what the scene needs, which backend, any fallback notice."""

    variant: str
    backend: str
    spectral: bool
    polarized: bool
    requested: str
    fallback_reason: str | None = None

    @property
    def full_variant(self) -> str:
        """What a scene needing everything (spectral + polarized) would use on this backend."""
        return variant_name(self.backend, spectral=True, polarized=True)

    def to_meta(self) -> dict:
        return {"variant": self.variant, "backend": self.backend, "spectral": self.spectral,
                "polarized": self.polarized, "requested": self.requested,
                "fallback_reason": self.fallback_reason}


def _parse_variant(name: str) -> tuple[str, bool, bool]:
    m = re.fullmatch(r"(scalar|llvm_ad|cuda_ad)_(mono|spectral|rgb)(_polarized)?", name)
    if not m:
        raise InputError("variant", repr(name), "'auto' or a Mitsuba variant such as llvm_ad_spectral_polarized")
    backend = m.group(1).split("_")[0]
    if m.group(2) == "rgb":
        raise InputError("variant", name, "a mono or spectral variant",
                         "RGB variants have no spectra, so camera sensitivities cannot be applied.")
    return backend, m.group(2) == "spectral", bool(m.group(3))


def select_variant(requested: str = "auto", *, spectral: bool = True, polarized: bool = True) -> VariantChoice:
    """Pick (and activate) the Mitsuba variant for a scene's needs.

    ``requested="auto"`` tries ``cuda`` -> ``llvm`` -> ``scalar`` and logs one line when it
    falls back. A named variant is checked against the needs: an unpolarized variant for a
    polarizing scene, or a mono variant for a spectral scene, is an :class:`InputError`
    (it would be silently wrong); a richer variant than needed is allowed.
    """
    import mitsuba as mi

    requested = str(requested).strip()
    if requested == "auto":
        reasons = []
        for backend in BACKENDS:
            ok, why = backend_status(backend)
            if ok:
                name = variant_name(backend, spectral=spectral, polarized=polarized)
                reason = None
                if reasons and backend == "scalar":
                    reason = "; ".join(reasons)
                    _notice("fallback-" + backend, f"capssim render: using Mitsuba's scalar backend ({name}), "
                            f"about 7x slower: {reasons[-1]}")
                mi.set_variant(name)
                return VariantChoice(name, backend, spectral or backend == "scalar", polarized, requested, reason)
            if backend != "cuda":  # no CUDA is the normal case on a CPU machine
                reasons.append(f"{backend}: {why}")
        raise InputError("variant", "auto", "a working Mitsuba backend", "; ".join(reasons))
    backend, is_spectral, is_polarized = _parse_variant(requested)
    if requested not in mi.variants():
        raise InputError("variant", requested, f"one of {', '.join(sorted(mi.variants()))}")
    if polarized and not is_polarized:
        raise InputError("variant", requested, "a *_polarized variant",
                         "This scene changes the polarization of light; an unpolarized variant would report DoLP 0.")
    if spectral and not is_spectral:
        raise InputError("variant", requested, "a *_spectral* variant",
                         "This scene has coloured materials or lights; a mono variant would lose its colours.")
    ok, why = backend_status(backend)
    if not ok:
        raise InputError("variant", requested, f"a variant whose backend works here ({why})",
                         "Use --variant auto to fall back automatically.")
    mi.set_variant(requested)
    return VariantChoice(requested, backend, is_spectral, is_polarized, requested, None)
