"""``caps-plus-cv`` (issue 36): the prior's blend and the iteration count chosen per capture by held-out raw
pixels, the denoiser's per-iteration noise schedule, and the options' errors."""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError, InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.polarization_filter import apply_chosen_filter
from capssim.reconstruct.priors.nlstr_denoiser import DenoiserParameters, NLSTRDenoiserPrior, denoiser_dtype
from capssim.simulate import simulate_capture
from capssim.stokes.physical_validity import project_to_physical

SIZE = 40


@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=7), make_sensor("gaussian", sigma=0.01), seed=7)


@pytest.fixture(scope="module")
def chosen(capture, tiny_denoiser_weights):
    return reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=str(tiny_denoiser_weights))


def test_every_candidate_is_validated_and_the_lowest_held_out_error_wins(chosen):
    out, record = chosen
    params = record["params"]
    candidates = params["holdout_candidates"]
    blends, errors = [c["denoiser_blend"] for c in candidates], [c["holdout_error"] for c in candidates]
    assert len(blends) >= 2 and blends == [0.0, 0.5, 0.75][:len(blends)]
    # the walk stops one past the lowest error: every error but the last falls
    assert all(a >= b for a, b in zip(errors[:-2], errors[1:-1]))
    assert len(blends) == 3 or errors[-1] > errors[-2]
    best = min(candidates, key=lambda c: c["holdout_error"])
    assert params["holdout_choice"] == {"denoiser_blend": best["denoiser_blend"]}
    assert params["denoiser_blend"] == best["denoiser_blend"] and params["iterations"] == best["iterations"]
    assert params["holdout_error"] == pytest.approx(best["holdout_error"])
    assert out.image.shape == (12, SIZE, SIZE) and np.isfinite(out.image).all()


def test_the_start_is_the_whole_agreement_blend_and_init_agree_gives_caps_plus_start(capture, tiny_denoiser_weights,
                                                                                       chosen):
    assert chosen[1]["params"]["init"] == "agree-all"
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=5)
    agree, record = reconstruct(capture, "caps-plus-cv", true_warps=True, iterations=5, denoiser_blend=0.0,
                                init="agree", denoiser_weights=str(tiny_denoiser_weights))
    assert record["params"]["init"] == "agree"
    np.testing.assert_array_equal(agree.image, plus.image)


def test_the_final_image_is_the_chosen_blend_and_count_run_with_every_pixel(capture, tiny_denoiser_weights, chosen):
    out, record = chosen
    params = record["params"]
    fixed, _ = reconstruct(capture, "caps-plus-pnp", true_warps=True, denoiser_weights=str(tiny_denoiser_weights),
                           denoiser_sigma_steps=15, denoiser_blend=params["denoiser_blend"], init="agree-all",
                           iterations=params["iterations"], physical_projection=False)
    # then the polarization filter the held-out pixels chose, then the physical projection
    filtered = apply_chosen_filter(torch.from_numpy(fixed.image), params["polarization_filter_choice"]).numpy()
    expected, _ = project_to_physical(filtered, unobserved=fixed.unobserved)
    np.testing.assert_allclose(out.image, expected, atol=1e-6)


def test_a_candidate_validation_is_the_same_as_that_blend_validated_alone(capture, tiny_denoiser_weights, chosen):
    """The whole-frame validation of each candidate is caps-plus-pnp's own held-out stopping at that blend."""
    _, record = chosen
    for candidate in record["params"]["holdout_candidates"]:
        _, alone = reconstruct(capture, "caps-plus-pnp", true_warps=True, denoiser_weights=str(tiny_denoiser_weights),
                               denoiser_sigma_steps=15, denoiser_blend=candidate["denoiser_blend"],
                               stopping="holdout", init="agree-all")
        assert alone["params"]["holdout_error"] == pytest.approx(candidate["holdout_error"], rel=1e-5)
        assert alone["params"]["iterations"] == candidate["iterations"]


def test_blend_zero_is_caps_plus_from_the_same_start_exactly(capture, tiny_denoiser_weights):
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=5, init="agree-all")
    zero, _ = reconstruct(capture, "caps-plus-cv", true_warps=True, iterations=5, denoiser_blend=0.0,
                          denoiser_weights=str(tiny_denoiser_weights))
    np.testing.assert_array_equal(zero.image, plus.image)


@pytest.mark.parametrize("options", [{"denoiser_blend": 0.5}, {"iterations": 4}, {"stopping": "noise"}])
def test_a_fixed_blend_count_or_rule_turns_the_choice_off(capture, tiny_denoiser_weights, options):
    _, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=str(tiny_denoiser_weights), **options)
    params = record["params"]
    assert "holdout_candidates" not in params and params["denoiser_blend"] == options.get("denoiser_blend", 0.5)
    assert ("blend_note" in params) == ("denoiser_blend" not in options)  # the record says no blend was chosen


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


@pytest.mark.parametrize("options, match", [
    ({"blend_candidates": "0.5"}, "blend_candidates"),
    ({"blend_candidates": "0,2"}, "blend_candidates"),
    ({"blend_candidates": "a,b"}, "blend_candidates"),
    ({"blend_candidates": "0,0.5", "prior": "nlstr"}, "blend_candidates"),
    ({"denoiser_sigma_steps": -1}, "denoiser_sigma_steps"),
    ({"denoiser_precision": "float16"}, "denoiser_precision"),
])
def test_bad_options_name_themselves(capture, tiny_denoiser_weights, options, match):
    extra = {} if options.get("prior") == "nlstr" else {"denoiser_weights": str(tiny_denoiser_weights)}
    with pytest.raises(InputError, match=match):
        reconstruct(capture, "caps-plus-cv", true_warps=True, **extra, **options)


def test_caps_plus_does_not_take_the_candidates(capture):
    with pytest.raises(CapssimError, match="blend_candidates"):
        reconstruct(capture, "caps-plus", true_warps=True, iterations=2, blend_candidates="0,0.5")


def test_the_walk_stops_once_the_held_out_error_rises(capture, tiny_denoiser_weights):
    """Candidates ordered 1, 0.5, 0: with the untrained network the largest blend validates worst, so the walk
    stops at the second candidate unless its error fell."""
    _, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=str(tiny_denoiser_weights),
                            blend_candidates="0,1,0.5")
    candidates = record["params"]["holdout_candidates"]
    assert [c["denoiser_blend"] for c in candidates][:2] == [0.0, 1.0]
    if candidates[1]["holdout_error"] > candidates[0]["holdout_error"]:
        assert len(candidates) == 2 and record["params"]["denoiser_blend"] == 0.0


def test_bfloat16_denoising_stays_close_to_float32(capture):
    """The shipped network in bfloat16 (the default where the CPU computes it natively) against float32."""
    full, r32 = reconstruct(capture, "caps-plus-pnp", true_warps=True, iterations=4, denoiser_precision="float32")
    half, r16 = reconstruct(capture, "caps-plus-pnp", true_warps=True, iterations=4, denoiser_precision="bfloat16")
    assert r32["params"]["denoiser_dtype"] == "float32" and r16["params"]["denoiser_dtype"] == "bfloat16"
    assert np.abs(full.image - half.image).max() < 5e-3
    assert np.sqrt(np.mean((full.image - half.image) ** 2)) < 1e-3


def test_another_prior_drops_the_choice_and_the_denoiser_defaults(capture):
    """-p prior=nlstr: caps-plus-cv's denoiser defaults and its blend candidates fall away: caps-plus from its
    start exactly."""
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, init="agree-all")
    other, record = reconstruct(capture, "caps-plus-cv", true_warps=True, iterations=4, prior="nlstr")
    np.testing.assert_array_equal(other.image, plus.image)
    assert record["params"]["prior"] == "nlstr" and "denoiser_sigma_steps" not in record["params"]


def test_auto_precision_is_bfloat16_only_where_native():
    assert denoiser_dtype("float32", torch.device("cpu")) == torch.float32
    assert denoiser_dtype("bfloat16", torch.device("cpu")) == torch.bfloat16
    auto = denoiser_dtype("auto", torch.device("cpu"))
    native = torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
    assert auto == (torch.bfloat16 if native else torch.float32)
