"""The ``nlstr-denoiser`` prior (issue 36): the learned denoiser, its noise schedule and blend, the prior in the
pipeline (``caps-plus -p prior=nlstr-denoiser``; ``caps-plus-cv`` chooses its blend), its options and its errors."""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError, InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.polarization_split import angle_mean
from capssim.reconstruct.networks import build_network, save_model
from capssim.reconstruct.priors.nlstr_denoiser import (
    DenoiserParameters,
    NLSTRDenoiserPrior,
    denoiser_dtype,
    sigma_schedule,
)
from capssim.simulate import simulate_capture

SIZE = 40
#: caps-plus with the nlstr-denoiser prior, no polarization filter (the prior's effect alone)
DENOISED = {"prior": "nlstr-denoiser", "polarization_filter": "none"}


@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=5), make_sensor("gaussian", sigma=0.01), seed=5)


@pytest.mark.parametrize("shape", [(1, 12, 1, 1), (2, 12, 7, 5), (1, 12, 33, 18)])
def test_denoiser_keeps_shape_and_starts_near_identity_on_tiny_and_odd_sizes(shape):
    torch.manual_seed(0)
    net = build_network("denoiser", {"features": 4, "depth": 3}).eval()
    x = torch.rand(shape)
    with torch.no_grad():
        y = net(x, torch.full((shape[0],), 0.02))
    assert y.shape == x.shape and torch.isfinite(y).all()
    with pytest.raises(ValueError, match="depth"):
        build_network("denoiser", {"depth": 1})


def test_sigma_schedule_runs_log_linearly_from_start_to_end():
    values = [sigma_schedule(i, 5, 0.05, 0.005) for i in range(7)]
    assert values[0] == pytest.approx(0.05) and values[4] == pytest.approx(0.005) and values[6] == pytest.approx(0.005)
    assert values[2] == pytest.approx((0.05 * 0.005) ** 0.5)
    assert sigma_schedule(0, 1, 0.05, 0.005) == pytest.approx(0.05)


class _Constant:
    """A stand-in NLSTR: its estimate is ``z`` itself."""

    def begin(self):
        pass

    def estimate(self, z, *, mu, iteration, stage):
        return z.clone(), {"n_similar": 1}

    def after_step(self, *, iteration, change):
        return {}


def test_blend_replaces_only_the_analyzer_mean():
    """X = X_nl + w (P X_dn - P X_nl): the polarization part (I - P) X is NLSTR's, the mean is the blend."""
    g = torch.Generator().manual_seed(1)
    z, c = torch.rand(12, 6, 5, generator=g), torch.rand(12, 6, 5, generator=g)
    denoiser = lambda x, level: c[None].expand_as(x)  # noqa: E731
    for w in (0.0, 0.3, 1.0):
        prior = NLSTRDenoiserPrior(_Constant(), denoiser, DenoiserParameters(denoiser_blend=w), 4)
        x, fields = prior.estimate(z, mu=0.5, iteration=0, stage=lambda name: nullcontext())
        torch.testing.assert_close(x - angle_mean(x), z - angle_mean(z))
        torch.testing.assert_close(angle_mean(x), (1 - w) * angle_mean(z) + w * angle_mean(c))
        assert fields["denoiser_sigma"] == pytest.approx(0.05)


def test_runs_through_the_pipeline_and_blend_zero_is_caps_plus(capture, tiny_denoiser_weights):
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, polarization_filter="none")
    weights = str(tiny_denoiser_weights)
    zero, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, denoiser_weights=weights,
                          denoiser_blend=0.0, **DENOISED)
    np.testing.assert_array_equal(zero.image, plus.image)
    out, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, denoiser_weights=weights, **DENOISED)
    assert out.image.shape == (12, SIZE, SIZE) and np.isfinite(out.image).all()
    assert not np.array_equal(out.image, plus.image)
    params = record["params"]
    assert params["prior"] == "nlstr-denoiser" and params["denoiser_blend"] == 0.5 and params["use_nlstr"]
    assert [h["denoiser_sigma"] for h in record["history"]][0] == pytest.approx(0.05)


def test_the_shipped_denoiser_runs_by_default(capture):
    out, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=3, **DENOISED)
    assert np.isfinite(out.image).all() and record["params"]["prior"] == "nlstr-denoiser"


@pytest.mark.parametrize("options, match", [
    ({"denoiser_blend": 2.0}, "denoiser_blend"),
    ({"denoiser_sigma_start": 0.0}, "denoiser_sigma_start"),
    ({"denoiser_sigma_end": float("nan")}, "denoiser_sigma_end"),
    ({"denoiser_weights": "/nonexistent/model.pt"}, "denoiser_weights"),
])
def test_bad_options_name_themselves(capture, options, match):
    with pytest.raises(InputError, match=match):
        reconstruct(capture, "caps-plus", true_warps=True, iterations=2, **DENOISED, **options)


def test_other_networks_and_channel_counts_are_refused(capture, tmp_path, tiny_denoiser_weights):
    edsr = save_model(tmp_path / "edsr.pt", "edsr", {"channels": 3, "features": 4, "blocks": 1},
                      build_network("edsr", {"channels": 3, "features": 4, "blocks": 1}))
    with pytest.raises(InputError, match="denoiser"):
        reconstruct(capture, "caps-plus", true_warps=True, iterations=2, denoiser_weights=str(edsr), **DENOISED)
    with pytest.raises(CapssimError, match="12-channel"):
        reconstruct(capture, "caps-iccp", true_warps=True, iterations=2, prior="nlstr-denoiser",
                    denoiser_weights=str(tiny_denoiser_weights))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(capture):
    cpu, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=3, **DENOISED)
    gpu, record = reconstruct(capture, "caps-plus", device="cuda", true_warps=True, iterations=3, **DENOISED)
    assert record["device"].startswith("cuda")
    assert np.abs(cpu.image - gpu.image).max() < 1e-2


def test_a_model_file_trained_again_is_read_again(tmp_path):
    """The loaded denoiser is cached per file version: rewriting the file gives the new weights."""
    import os

    from capssim.reconstruct.priors.nlstr_denoiser import denoiser_model

    params = {"channels": 12, "features": 4, "depth": 3}
    path = tmp_path / "model.pt"
    torch.manual_seed(0)
    save_model(path, "denoiser", params, build_network("denoiser", params))
    first = denoiser_model(str(path), torch.device("cpu"))
    assert denoiser_model(str(path), torch.device("cpu")) is first
    torch.manual_seed(1)
    save_model(path, "denoiser", params, build_network("denoiser", params))
    os.utime(path, ns=(1, 1))  # a new version even within the file system's time resolution
    second = denoiser_model(str(path), torch.device("cpu"))
    assert second is not first
    assert not torch.equal(first.body[0].weight, second.body[0].weight)


def test_the_per_iteration_schedule_does_not_depend_on_the_run_length():
    """denoiser_sigma_steps=N: iteration k has the same noise level in a run of any length (held-out stopping)."""
    class _Identity:
        def begin(self):
            pass

        def estimate(self, z, *, mu, iteration, stage):
            return z.clone(), {}

    z = torch.rand(12, 4, 4)
    levels = {}
    for length in (10, 40):
        prior = NLSTRDenoiserPrior(_Identity(), lambda x, level: x, DenoiserParameters(denoiser_sigma_steps=15), length)
        levels[length] = [prior.estimate(z, mu=1.0, iteration=k, stage=lambda n: nullcontext())[1]["denoiser_sigma"]
                          for k in (0, 7, 14, 30)]
    assert levels[10] == levels[40]
    assert levels[10][0] == pytest.approx(0.05) and levels[10][2] == pytest.approx(0.005)
    assert levels[10][3] == pytest.approx(0.005)


def test_bfloat16_denoising_stays_close_to_float32(capture):
    """The shipped network in bfloat16 (the default where the CPU computes it natively) against float32."""
    full, r32 = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, denoiser_precision="float32", **DENOISED)
    half, r16 = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, denoiser_precision="bfloat16", **DENOISED)
    assert r32["params"]["denoiser_dtype"] == "float32" and r16["params"]["denoiser_dtype"] == "bfloat16"
    assert np.abs(full.image - half.image).max() < 5e-3
    assert np.sqrt(np.mean((full.image - half.image) ** 2)) < 1e-3


def test_auto_precision_is_bfloat16_only_where_native():
    assert denoiser_dtype("float32", torch.device("cpu")) == torch.float32
    assert denoiser_dtype("bfloat16", torch.device("cpu")) == torch.bfloat16
    auto = denoiser_dtype("auto", torch.device("cpu"))
    native = torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    assert auto == (torch.bfloat16 if native else torch.float32)
