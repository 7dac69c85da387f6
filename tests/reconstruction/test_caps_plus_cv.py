"""``caps-plus-cv`` (issue 36): ``caps-plus`` with the ``nlstr-denoiser`` prior, whose selection layer also chooses
the denoiser's blend among :data:`~capssim.reconstruct.methods.caps_plus_cv.BLEND_CANDIDATES` by held-out raw pixels;
its record and its options. The prior itself: tests/reconstruction/test_nlstr_denoiser.py."""

from __future__ import annotations

import numpy as np
import pytest

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError, InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.methods.caps_plus_cv import BLEND_CANDIDATES, DENOISER_SIGMA_STEPS
from capssim.reconstruct.registry import get_method
from capssim.reconstruct.selection import SELECTED_NOTHING
from capssim.simulate import simulate_capture

#: the selection record of a run whose every choice was given as an option

SIZE = 40


@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=7), make_sensor("gaussian", sigma=0.01), seed=7)


@pytest.fixture(scope="module")
def chosen(capture, tiny_denoiser_weights):
    return reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=str(tiny_denoiser_weights))


def test_every_candidate_is_validated_in_turn_and_the_lowest_held_out_error_wins(chosen):
    out, record = chosen
    params, selection = record["params"], record["params"]["selection"]
    candidates = selection["blend_candidates"]
    blends, errors = [c["denoiser_blend"] for c in candidates], [c["holdout_error"] for c in candidates]
    assert BLEND_CANDIDATES == (0.0, 0.5, 0.75)
    assert len(blends) >= 2 and blends == list(BLEND_CANDIDATES[:len(blends)])
    # the walk stops one past the lowest error: every error but the last falls
    assert all(a >= b for a, b in zip(errors[:-2], errors[1:-1]))
    assert len(blends) == len(BLEND_CANDIDATES) or errors[-1] > errors[-2]
    best = min(candidates, key=lambda c: c["holdout_error"])
    assert params["denoiser_blend"] == best["denoiser_blend"] and params["iterations"] == best["iterations"]
    assert selection["holdout_error"] == pytest.approx(best["holdout_error"])
    assert selection["iterations_from"] == "holdout" and params["init"] == "agree"
    assert params["prior"] == "nlstr-denoiser" and params["denoiser_sigma_steps"] == DENOISER_SIGMA_STEPS
    assert record["resolved_options"] == {"iterations": best["iterations"], "denoiser_blend": best["denoiser_blend"],
                                          "polarization_filter": params["polarization_filter"],
                                          "data_term": params["data_term"], "init": params["init"]}
    assert out.image.shape == (12, SIZE, SIZE) and np.isfinite(out.image).all()


def test_the_final_image_is_caps_plus_with_the_prior_run_with_the_resolved_choices(capture, tiny_denoiser_weights,
                                                                                    chosen):
    """caps-plus-cv is caps-plus with the nlstr-denoiser prior: caps-plus given that prior and the resolved choices
    gives its image bit for bit, and so does caps-plus-cv given them (nothing is selected again)."""
    out, record = chosen
    weights = str(tiny_denoiser_weights)
    plus, plus_record = reconstruct(capture, "caps-plus", true_warps=True, prior="nlstr-denoiser",
                                    denoiser_weights=weights, denoiser_sigma_steps=DENOISER_SIGMA_STEPS,
                                    **record["resolved_options"])
    np.testing.assert_array_equal(plus.image, out.image)
    again, again_record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=weights,
                                      **record["resolved_options"])
    np.testing.assert_array_equal(again.image, out.image)
    assert again_record["params"]["selection"] == SELECTED_NOTHING


def test_the_first_candidates_validation_is_caps_plus_own(capture, chosen):
    """Blend 0 is NLSTR alone: its held-out validation is caps-plus's, error and count."""
    first = chosen[1]["params"]["selection"]["blend_candidates"][0]
    _, plus = reconstruct(capture, "caps-plus", true_warps=True)
    assert first["denoiser_blend"] == 0.0
    assert plus["params"]["selection"]["holdout_error"] == pytest.approx(first["holdout_error"], rel=1e-6)
    assert plus["params"]["selection"]["holdout_best_iteration"] == first["iterations"]


def test_blend_zero_is_caps_plus_exactly(capture, tiny_denoiser_weights):
    fixed = {"iterations": 5, "polarization_filter": "none", "data_term": "cagf-stokes", "init": "agree"}
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, **fixed)
    zero, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_blend=0.0,
                               denoiser_weights=str(tiny_denoiser_weights), **fixed)
    np.testing.assert_array_equal(zero.image, plus.image)
    assert record["params"]["selection"] == SELECTED_NOTHING


def test_a_given_blend_is_not_chosen_and_a_given_count_leaves_the_blend_open(capture, tiny_denoiser_weights):
    weights = str(tiny_denoiser_weights)
    _, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=weights, denoiser_blend=0.5,
                            polarization_filter="none", iterations=3, data_term="cagf-stokes", init="agree")
    assert record["params"]["denoiser_blend"] == 0.5 and record["params"]["selection"] == SELECTED_NOTHING
    assert "denoiser_blend" not in record["resolved_options"]
    _, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=weights, iterations=3,
                            polarization_filter="none")
    params, selection = record["params"], record["params"]["selection"]
    assert params["iterations"] == 3 and selection["iterations_from"] == "options"
    assert [c["denoiser_blend"] for c in selection["blend_candidates"]][0] == 0.0
    assert all(c["iterations"] <= 3 for c in selection["blend_candidates"])
    assert record["resolved_options"]["denoiser_blend"] == params["denoiser_blend"]


def test_the_walk_stops_once_the_held_out_error_rises(capture, tiny_denoiser_weights, monkeypatch):
    """Candidates ordered 0, 1, 0.5 (the count fixed at 3): the validations run in that order, and once an error
    rises above the one before, no further candidate runs."""
    import capssim.reconstruct.methods.caps_plus_cv as caps_plus_cv

    monkeypatch.setattr(caps_plus_cv, "BLEND_CANDIDATES", (0.0, 1.0, 0.5))
    _, record = reconstruct(capture, "caps-plus-cv", true_warps=True, denoiser_weights=str(tiny_denoiser_weights),
                            iterations=3, polarization_filter="none")
    candidates = record["params"]["selection"]["blend_candidates"]
    assert [c["denoiser_blend"] for c in candidates] == [0.0, 1.0, 0.5][:len(candidates)]
    if candidates[1]["holdout_error"] > candidates[0]["holdout_error"]:
        assert len(candidates) == 2 and record["params"]["denoiser_blend"] == 0.0
    else:
        assert len(candidates) == 3


def test_caps_plus_cv_lists_the_denoiser_options_and_caps_plus_own():
    names = [o.name for o in get_method("caps-plus-cv").options()]
    plus = [o.name for o in get_method("caps-plus").options()]
    assert set(plus) <= set(names)
    assert set(names) - set(plus) == {"denoiser_weights", "denoiser_blend", "denoiser_sigma_start",
                                      "denoiser_sigma_end", "denoiser_sigma_steps", "denoiser_precision"}
    defaults = {o.name: o.default for o in get_method("caps-plus-cv").options()}
    assert defaults["prior"] == "nlstr-denoiser" and defaults["denoiser_sigma_steps"] == DENOISER_SIGMA_STEPS


@pytest.mark.parametrize("options, match", [
    ({"blend_candidates": "0,0.5"}, "blend_candidates"),  # no option of caps-plus-cv any more
    ({"holdout_rule": "one-se"}, "holdout_rule"),
    ({"denoiser_sigma_steps": -1}, "denoiser_sigma_steps"),
    ({"denoiser_precision": "float16"}, "denoiser_precision"),
])
def test_bad_options_name_themselves(capture, tiny_denoiser_weights, options, match):
    with pytest.raises(InputError, match=match):
        reconstruct(capture, "caps-plus-cv", true_warps=True, iterations=1, denoiser_weights=str(tiny_denoiser_weights),
                    **options)


def test_caps_plus_does_not_take_the_candidates(capture):
    with pytest.raises(CapssimError, match="blend_candidates"):
        reconstruct(capture, "caps-plus", true_warps=True, iterations=2, blend_candidates="0,0.5")


def test_another_prior_drops_the_choice(capture):
    """-p prior=nlstr: caps-plus-cv's blend choice and denoiser defaults fall away: caps-plus exactly."""
    fixed = {"iterations": 4, "polarization_filter": "none"}
    plus, _ = reconstruct(capture, "caps-plus", true_warps=True, **fixed)
    other, record = reconstruct(capture, "caps-plus-cv", true_warps=True, prior="nlstr", **fixed)
    np.testing.assert_array_equal(other.image, plus.image)
    assert record["params"]["prior"] == "nlstr" and "denoiser_sigma_steps" not in record["params"]
