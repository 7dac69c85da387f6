"""The design calculator (paper eq. 5-8) and the import direction of the packages."""

from __future__ import annotations

import math

import pytest

from capssim.camera.design import DesignInputs, system_design
from capssim.errors import InputError


def test_prototype_numbers():
    d = system_design(DesignInputs())
    assert abs(d["diffraction_to_nyquist_ratio"] - 8.67) < 0.01
    assert d["r_sr"] == 2.0 and d["sr_limited_by"] == "apertures"
    f_p = 35 / 4.8e-3
    assert math.isclose(d["overlap_width_m"], (1280 * 10_000 / f_p - 40) / 1000)
    assert math.isclose(d["fov_h_deg"], 2 * math.degrees(math.atan(1280 / (2 * f_p) - 40 / 20_000)))
    assert d["fov_h_deg"] < d["single_aperture_fov_h_deg"]


def test_diffraction_limited_case():
    d = system_design(DesignInputs(f_number=16, pixel_um=2.0, apertures=16))
    assert d["sr_limited_by"] == "diffraction" and d["r_sr"] == d["diffraction_to_nyquist_ratio"] < 4


def test_bad_inputs():
    with pytest.raises(InputError, match="f-number"):
        system_design(DesignInputs(f_number=0))
    with pytest.raises(InputError, match="apertures"):
        system_design(DesignInputs(apertures=2.5))


