"""capssim's own Mitsuba plugins, registered once per variant by :func:`register_plugins`.

* ``capssim_pattern``: an analytic texture (:data:`capssim.render.scene_base.PATTERNS`) on the
  shape's uv square, optionally multiplying a ``base`` texture;
* ``capssim_polarizer``: a thin sheet that transmits through a linear diattenuator at ``theta``
  degrees with degree ``dolp`` (1 = ideal polarizer) and an optional ``transmittance``.

The classes derive from Mitsuba's, which exist only once a variant is set, so each is built by a
factory for the active variant.
"""

from __future__ import annotations

from capssim.render.scene_base import PATTERNS

_registered: set[str] = set()


def _pattern_texture(dr, mi):
    """The ``capssim_pattern`` texture class of the active variant."""
    class PatternTexture(mi.Texture):
        def __init__(self, props):
            mi.Texture.__init__(self, props)
            name = props.get("pattern")
            if name not in PATTERNS:
                raise ValueError(f"capssim_pattern: unknown pattern {name!r}")
            self.function = PATTERNS[name]
            self.half_size = float(props.get("half_size", 1.0))
            self.params = {k: float(props.get(k)) for k in props.keys()
                           if k not in ("pattern", "half_size", "base")}
            self.base = props.get("base") if "base" in props else None
            self.name = name

        def _value(self, si):
            x = (2.0 * si.uv.x - 1.0) * self.half_size
            y = (2.0 * si.uv.y - 1.0) * self.half_size
            return self.function(dr, mi, x, y, self.params)

        def eval(self, si, active=True):
            v = mi.UnpolarizedSpectrum(self._value(si))
            return v * self.base.eval(si, active) if self.base is not None else v

        def eval_1(self, si, active=True):
            v = self._value(si)
            return v * self.base.eval_1(si, active) if self.base is not None else v

        def eval_3(self, si, active=True):
            v = self._value(si)
            c = mi.Color3f(v, v, v)
            return c * self.base.eval_3(si, active) if self.base is not None else c

        def mean(self):
            return 0.5

        def is_spatially_varying(self):
            return True

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"capssim_pattern[{self.name}]"

    return PatternTexture


def _diattenuator_sheet(dr, mi):
    """The ``capssim_polarizer`` BSDF class of the active variant."""
    class DiattenuatorSheet(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.theta = props.get("theta", 0.0)
            self.dolp = props.get("dolp", 1.0)
            self.transmittance = props.get("transmittance") if "transmittance" in props else None
            flags = mi.BSDFFlags.Null | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_flags = flags
            self.m_components = [flags]

        @staticmethod
        def _value(tex, si, active):
            return tex.eval_1(si, active) if isinstance(tex, mi.Texture) else mi.Float(float(tex))

        def _mueller(self, si, forward, active):
            theta = dr.deg2rad(self._value(self.theta, si, active))
            d = dr.clip(self._value(self.dolp, si, active), 0.0, 1.0)
            t = mi.UnpolarizedSpectrum(1.0)
            if self.transmittance is not None:
                t = self.transmittance.eval(si, active)
            if not mi.is_polarized:
                return mi.Spectrum(0.5 * t)
            q = mi.UnpolarizedSpectrum(0.5 * (1.0 + d)) * t
            r = mi.UnpolarizedSpectrum(0.5 * (1.0 - d)) * t
            m = mi.mueller.rotated_element(mi.UnpolarizedSpectrum(theta), mi.mueller.diattenuator(q, r))
            a_axis = mi.Vector3f(0.0, 1.0, 0.0)
            eff_a = dr.normalize(a_axis - dr.dot(a_axis, forward) * forward)
            eff_t = dr.cross(forward, eff_a)
            return mi.mueller.rotate_mueller_basis_collinear(m, forward, eff_t, mi.mueller.stokes_basis(forward))

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = -si.wi
            bs.pdf = mi.Float(1.0)
            bs.eta = mi.Float(1.0)
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.Null)
            bs.sampled_component = mi.UInt32(0)
            forward = si.wi if ctx.mode == mi.TransportMode.Radiance else -si.wi
            return bs, self._mueller(si, forward, active)

        def eval(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Spectrum(0.0), mi.Float(0.0)

        def eval_null_transmission(self, si, active=True):
            return self._mueller(si, si.wi, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            return "capssim_polarizer"

    return DiattenuatorSheet


def register_plugins() -> None:
    """Register ``capssim_pattern`` and ``capssim_polarizer`` for the active Mitsuba variant."""
    import drjit as dr
    import mitsuba as mi

    variant = mi.variant()
    if variant in _registered:
        return
    pattern_texture, diattenuator_sheet = _pattern_texture(dr, mi), _diattenuator_sheet(dr, mi)
    mi.register_texture("capssim_pattern", lambda props: pattern_texture(props))
    mi.register_bsdf("capssim_polarizer", lambda props: diattenuator_sheet(props))
    _registered.add(variant)


__all__ = ["register_plugins"]
