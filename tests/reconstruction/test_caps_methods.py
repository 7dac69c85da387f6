"""End-to-end CAPS methods (caps and its three ablations) and the hard cases of the issue."""

import importlib.util

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError, InputError, UnknownNameError
from capssim.reconstruct.methods.caps import CapsOptions
from capssim.reconstruct.registry import reconstruct
from capssim.simulate import PoseRanges, simulate_capture

METHODS = ["caps", "caps-no-cagf", "caps-no-nlstr", "caps-iccp"]


def scene(h=48, w=48, seed=0, level=1.0):
    from scipy.ndimage import gaussian_filter

    from capssim.stokes.polarization import twelve_from_stokes

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    s0 = np.stack([0.3 + 0.3 * (np.sin(2 * np.pi * 4 * xx + 2 * yy) > 0) * g
                   + 0.1 * gaussian_filter(rng.random((h, w)), 2) for g in (1.0, 0.7, 0.5)])
    d = 0.5 * gaussian_filter(rng.random((h, w)), 5) / 0.5
    a = np.pi * yy
    gt = twelve_from_stokes(np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)]))
    return (level * gt).astype(np.float32)


def capture(gt, sigma=0.01, seed=0, **pose):
    sensor = make_sensor("gaussian", sigma=sigma) if sigma else make_sensor("none")
    return simulate_capture(gt, sensor, seed=seed, pose_ranges=PoseRanges(**pose))


def psnr(x, gt):
    return float(np.mean([-10 * np.log10(np.mean((np.clip(x[c], 0, 1) - gt[c]) ** 2) + 1e-20) for c in range(12)]))


@pytest.mark.parametrize("method", METHODS)
def test_method_runs_and_records(method):
    gt = scene()
    cap = capture(gt)
    out, record = reconstruct(cap, method, true_warps=True, iterations=6)
    assert out.image.shape == (12, 48, 48) and out.image.dtype == np.float32 and np.isfinite(out.image).all()
    assert psnr(out.image, gt) > 25
    assert record["params"]["iterations"] == 6
    for stage in ("registration", "init", "data_term", "admm_update"):
        assert stage in record["stages_s"]
    assert record["registration"]["error_hr_px_median"] == 0.0
    hist = record["history"]
    assert len(hist) == 6 * (3 if method == "caps-iccp" else 1)
    assert all({"mu", "objective", "data"} <= set(h) for h in hist)
    if method != "caps-no-nlstr":
        assert all("n_similar" in h for h in hist)
    assert 20 < record["init_psnr_db"] < 60


def test_params_follow_the_paper_and_the_ablation_switches():
    cap = capture(scene(), sigma=0.0)
    _, rec = reconstruct(cap, "caps", true_warps=True, iterations=1)
    p = rec["params"]
    assert (p["block"], p["n_similar"], p["nu"], p["c1"], p["c2"], p["mu0"], p["grow_rate"], p["grow_step"],
            p["dt"]) == (8, 40, 0.2, 0.002, 0.02, 0.5, 0.1, 5, 1.0)
    assert p["use_cagf"] and p["use_nlstr"]
    _, rec = reconstruct(cap, "caps-iccp", true_warps=True, iterations=1)
    assert (rec["params"]["c1"], rec["params"]["c2"]) == (0.001, 0.01)
    assert rec["params"]["bayer_method"] == "ri"  # the paper's ICCP: the Bayer demosaicking of [15]
    _, rec = reconstruct(cap, "caps-no-cagf", true_warps=True, iterations=1)
    assert not rec["params"]["use_cagf"]


def test_caps_denoises_better_than_data_only():
    gt = scene(64, 64, seed=3)
    cap = capture(gt, sigma=0.03, seed=3)
    full, _ = reconstruct(cap, "caps", true_warps=True)
    data_only, _ = reconstruct(cap, "caps-no-nlstr", true_warps=True)
    assert psnr(full.image, gt) > psnr(data_only.image, gt) + 1.0


def test_options_are_checked():
    cap = capture(scene(), sigma=0.0)
    with pytest.raises(UnknownNameError):
        reconstruct(cap, "caps", true_warps=True, not_an_option=1)
    with pytest.raises(InputError, match="option iterations: got 'many'; expected an integer. Give iterations as an integer"):
        reconstruct(cap, "caps", true_warps=True, iterations="many")
    with pytest.raises(InputError, match="option mu0: got 'nan'; expected a finite number"):
        reconstruct(cap, "caps", true_warps=True, mu0="nan")
    with pytest.raises(UnknownNameError, match="Did you mean 'caps-plus'"):
        reconstruct(cap, "caps-plu", true_warps=True)
    with pytest.raises(InputError):
        reconstruct(cap, "caps", true_warps=True, c1=-1)
    out, rec = reconstruct(cap, "caps", true_warps=True, iterations="2", adaptive="block", stride="8")
    assert rec["params"]["stride"] == 8 and np.isfinite(out.image).all()


def test_estimated_warps_need_registration():
    cap = capture(scene(), sigma=0.0)
    if importlib.util.find_spec("capssim.reconstruct.registration") is None:
        with pytest.raises(CapssimError, match="--true-warps"):
            reconstruct(cap, "caps", iterations=1)
    else:
        out, rec = reconstruct(cap, "caps", iterations=1)
        assert np.isfinite(out.image).all()
        assert rec["registration"]["source"].startswith("estimated")
        assert np.isfinite(rec["registration"]["error_hr_px_median"])


# -- hard cases: a result or a clear error, never NaN -------------------------------------------
def _finite_run(cap, method="caps", **options):
    out, rec = reconstruct(cap, method, true_warps=True, **options)
    assert np.isfinite(out.image).all()
    assert all(np.isfinite(h["objective"]) for h in rec["history"])
    return out.image, rec


@pytest.mark.parametrize("method", ["caps", "caps-iccp"])
def test_constant_image(method):
    image, _ = _finite_run(capture(np.full((12, 32, 32), 0.37, np.float32), sigma=0.0), method, iterations=5)
    assert np.allclose(image, 0.37, atol=1e-3)


def test_black_and_very_dark_images():
    image, _ = _finite_run(capture(np.zeros((12, 32, 32), np.float32), sigma=0.0), iterations=5)
    assert np.abs(image).max() < 1e-4
    gt = scene(level=1e-3)  # S0 near 0
    image, _ = _finite_run(capture(gt, sigma=0.0), iterations=5)
    assert np.abs(image - gt).max() < 2e-3


def test_saturated_pixels_get_zero_weight():
    gt = scene()
    gt[:, 10:20, 10:20] *= 4.0  # far above full scale: clipped in every aperture
    cap = capture(gt, sigma=0.01)
    assert cap.caps_saturated().any()
    image, rec = _finite_run(cap, iterations=5)
    assert rec["field_of_view_weight_fraction"] < 0.99
    outside = np.ones((48, 48), bool)
    outside[6:24, 6:24] = False
    assert psnr(image[:, outside][:, None], np.clip(gt, 0, 1)[:, outside][:, None]) > 25


def test_misregistration_larger_than_the_search_window():
    gt = scene(64, 64)
    cap = capture(gt, sigma=0.01, shift_max_px=12.0, rotation_max_deg=2.0)
    shifts = [abs(v) for p in cap.meta["poses"]["apertures"] for v in p["shift_xy_px"]]
    assert max(shifts) > 7  # more than the 7 px block-matching radius
    image, _ = _finite_run(cap, iterations=5)
    assert psnr(image[:, 14:-14, 14:-14], gt[:, 14:-14, 14:-14]) > 25


def test_very_strong_noise():
    image, _ = _finite_run(capture(scene(), sigma=0.3), iterations=5)
    assert image.min() > -1 and image.max() < 2


@pytest.mark.parametrize("size", [(108, 116), (36, 44)])
def test_sizes_not_multiple_of_the_block(size):
    gt = scene(*size)
    image, rec = _finite_run(capture(gt, sigma=0.01), iterations=3, stride=5)
    assert image.shape == (12, *size)
    assert rec["params"]["n_groups"] > 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu():
    cap = capture(scene(), sigma=0.01)
    cpu, _ = reconstruct(cap, "caps", true_warps=True, iterations=3)
    gpu, rec = reconstruct(cap, "caps", device="cuda", true_warps=True, iterations=3)
    assert rec["device"].startswith("cuda")
    assert np.abs(cpu.image - gpu.image).max() < 1e-2


def test_options_compose_the_parameter_objects_under_the_same_names():
    """CapsOptions holds one parameter object per step; the option names and the record stay flat."""
    names = ["iterations", "mu0", "grow_rate", "grow_step", "dt", "n_similar", "n_similar_step", "n_similar_min",
             "rematch_change", "rematch_min_gap", "rematch_max_gap", "dictionary_gap", "block", "stride",
             "search_radius", "match_components", "c1", "c2", "adaptive", "weight_bandwidth", "strip_mb", "nu",
             "cagf_radius", "cagf_eps", "psf_sigma", "fov_mask", "data_term", "prior", "track_psnr", "preset"]
    assert list(CapsOptions().to_dict()) == names == list(CapsOptions.option_names())
    opts = CapsOptions.from_options({"iterations": "7", "strip-mb": "0.5", "cagf_radius": 2, "rematch_max_gap": 4,
                                     "fov_mask": "off"}, c1=0.001)
    assert (opts.admm.iterations, opts.nlstr.strip_mb, opts.cagf.radius, opts.matching.rematch_max_gap,
            opts.nlstr.c1, opts.fov_mask) == (7, 0.5, 2, 4, 0.001, False)
    assert CapsOptions().to_dict()["strip_mb"] == 64.0 and CapsOptions().nlstr.strip_bytes == 64 * 2**20
    with pytest.raises(UnknownNameError):
        CapsOptions.from_options({"eps": 1e-3})  # NLSTR's eps is not an option
    with pytest.raises(InputError):
        CapsOptions.from_options({"rematch_min_gap": 5, "rematch_max_gap": 2}).validated_parameters()


def test_preset_fast_sets_its_options_and_explicit_options_win():
    fast = CapsOptions.from_options({"preset": "fast"})
    assert (fast.admm.iterations, fast.matching.dictionary_gap, fast.matching.rematch_min_gap, fast.nlstr.stride,
            fast.nlstr.match_components, fast.preset) == (7, 4, 4, 6, 3, "fast")
    assert CapsOptions.from_options({"preset": "fast", "iterations": "12"}).admm.iterations == 12
    default = CapsOptions.from_options({})
    assert (default.admm.iterations, default.matching.dictionary_gap, default.preset) == (25, 5, "default")
    assert CapsOptions.from_options({"preset": "literal"}).matching.dictionary_gap == 1
    assert CapsOptions.from_options({"preset": "fast"}, c1=0.001).nlstr.c1 == 0.001  # a method's own defaults stay
    with pytest.raises(UnknownNameError):
        CapsOptions.from_options({"preset": "fastest"})
