"""Imperfect rigs on the render path (Mitsuba): the same camera model as simulate, on both the planar
warp path and the per-aperture path; meta.json["rig"]; explicit homographies; the render CLI flags."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")

from capssim.camera.psf import PSF  # noqa: E402
from capssim.camera.rig import RigModel  # noqa: E402
from capssim.camera.sensor import NoNoiseSensor  # noqa: E402
from capssim.captures.capture import read_capture  # noqa: E402
from capssim.errors import InputError  # noqa: E402
from capssim.render import render_capture  # noqa: E402
from capssim.simulate import simulate_capture  # noqa: E402

torch.set_num_threads(1)
SIZE = 32
RIG = RigModel().with_overrides(angle_offsets_deg=[1.5, -2.0, 1.0, -1.0], extinction_ratio=[300, 100, 30],
                                gain=[1.05, 0.95, 1.0, 1.02], vignetting_corner=0.2,
                                psf_sigmas_hr_px=[0.4, 0.5, 0.6, 0.5])


def relative_rms(a: np.ndarray, b: np.ndarray, margin: int = 2) -> np.ndarray:
    """``(4,)`` RMS of ``a - b`` per raw frame (``margin`` raw px cut), over the mean of ``b``."""
    d = (a - b)[:, margin:-margin, margin:-margin]
    return np.sqrt(np.mean(d ** 2, axis=(1, 2))) / b.mean()


@pytest.fixture(scope="module")
def ramp():
    return render_capture("dolp-ramp", size=SIZE, spp=4, rig=RIG, record_timing=False)


def simulate_through(cap, rig):
    """simulate_capture of a rendered capture's own gt.tiff and homographies (no PSF: gt.tiff has none
    with per-aperture PSFs), without noise."""
    return simulate_capture(cap.gt, NoNoiseSensor(), psf=PSF.none(), rig=rig, dofp_layout=cap.dofp_layout,
                            aperture_homographies=cap.aperture_homographies())


def test_render_with_a_rig_agrees_with_simulate_through_the_same_rig(ramp):
    """Measured on dolp-ramp, 32 px: aperture 0 (identity warp) to float32 rounding (3e-8); apertures
    1-3 to 2e-4 of the mean (the render warps a 4x finer reference, simulate bilinearly on the HR
    grid); the ideal model misses the rendered frames by 5-11 %."""
    sim = simulate_through(ramp, RIG)
    # inside a 2 raw px border (there the render blurs real content beyond the frame, simulate its padding)
    assert np.abs(sim.caps_raw[0] - ramp.caps_raw[0])[2:-2, 2:-2].max() < 1e-6
    assert relative_rms(sim.caps_raw, ramp.caps_raw).max() < 1e-3
    assert np.abs(sim.dofp_raw - ramp.dofp_raw).max() < 1e-6  # the DoFP camera is not the rig
    assert relative_rms(simulate_through(ramp, None).caps_raw, ramp.caps_raw).min() > 0.03


def test_rendered_meta_holds_the_true_rig(ramp, tmp_path):
    from capssim.captures.capture import write_capture

    assert ramp.meta["rig"] == RIG.to_dict()
    back = read_capture(write_capture(tmp_path / "cap", ramp))
    assert back.rig.to_dict() == RIG.to_dict()


def test_ideal_rig_renders_todays_capture():
    kw = dict(size=16, spp=4, record_timing=False)
    today, ideal = render_capture("dolp-ramp", **kw), render_capture("dolp-ramp", rig=RigModel.ideal(), **kw)
    assert np.array_equal(today.caps_raw, ideal.caps_raw) and np.array_equal(today.gt, ideal.gt)
    assert json.dumps(today.meta, sort_keys=True) == json.dumps(ideal.meta, sort_keys=True)


def test_per_aperture_path_applies_the_rig_like_the_planar_path():
    """A planar scene rendered per aperture (each through a polarizer at the rig's angle and per-colour
    extinction) against its planar-warp render: measured 0.2-0.6 % of the mean at 64 spp (Monte-Carlo
    noise and the two paths' sampling), against 2-3 % for a per-aperture render without the rig."""
    kw = dict(size=SIZE, spp=64, record_timing=False)
    warp = render_capture("aop-wheel", planar="on", rig=RIG, **kw)
    own = render_capture("aop-wheel", planar="off", rig=RIG, **kw)
    assert own.meta["render"]["path"] == "per-aperture" and own.meta["rig"] == RIG.to_dict()
    assert relative_rms(own.caps_raw, warp.caps_raw).max() < 0.012
    without = render_capture("aop-wheel", planar="off", **kw)
    assert relative_rms(without.caps_raw, warp.caps_raw)[1:].min() > 0.015


def test_explicit_homographies_only_on_the_planar_warp_path(ramp):
    h = ramp.aperture_homographies().copy()
    h[1, 0, 2] += 0.5
    cap = render_capture("dolp-ramp", size=SIZE, spp=4, rig=RIG, aperture_homographies=h, record_timing=False)
    assert np.allclose(cap.aperture_homographies(), h)
    assert relative_rms(simulate_through(cap, RIG).caps_raw, cap.caps_raw).max() < 1e-3
    with pytest.raises(InputError, match="aperture_homographies") as info:
        render_capture("dolp-ramp", size=SIZE, spp=4, planar="off", aperture_homographies=h, record_timing=False)
    assert "planar" in str(info.value)
    with pytest.raises(InputError, match="aperture_homographies"):
        render_capture("dolp-ramp", size=SIZE, spp=4, aperture_homographies=h[:3])


def test_render_cli_rig_flags(tmp_path):
    from typer.testing import CliRunner

    from capssim.cli import app

    runner = CliRunner()
    res = runner.invoke(app, ["render", "dolp-ramp", "-o", str(tmp_path / "a"), "--size", "16", "--spp", "4",
                              "--rig", "realistic", "--rig-seed", "3", "--gains", "1.1,1,1,1", "--no-timing"])
    assert res.exit_code == 0, res.output
    rig = read_capture(tmp_path / "a").rig
    expected = RigModel.preset("realistic", seed=3).with_overrides(gain=[1.1, 1, 1, 1])
    assert rig.to_dict() == expected.to_dict()
    for flags, named in ((["--extinction-ratios", "2,1"], "--extinction-ratios"),
                         (["--aperture-psf-sigmas", "0.5,0.5,0.5,9"], "--aperture-psf-sigmas"),
                         (["--rig", "nope"], "--rig")):
        res = runner.invoke(app, ["render", "dolp-ramp", "-o", str(tmp_path / "b"), "--size", "16", "--spp", "4",
                                  *flags])
        assert isinstance(res.exception, InputError) and res.exception.argument == named, repr(res.exception)
        assert not (tmp_path / "b").exists()
