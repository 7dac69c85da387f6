"""The polarization filter of ``caps-plus`` (``-p polarization_filter=auto``, the default): a guided filter of each
analyzer's deviation from its colour's analyzer mean, chosen per frame by held-out raw pixels where the analyzers show
polarization structure. The Stokes-consistency test that ``auto`` asks first:
tests/reconstruction/test_polarization_evidence.py; a given ``R,EPS``: tests/reconstruction/test_caps_plus_model.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.selection import SELECTED_NOTHING
from capssim.reconstruct.selection.holdout import HoldoutValidation
from capssim.reconstruct.selection.polarization_filter import (
    POLARIZATION_FILTERS,
    apply_chosen_filter,
    choose_polarization_filter,
    filter_polarization,
)
from capssim.simulate import simulate_capture

#: the selection record of a run whose every choice was given as an option


def _intensity(size: int = 64, seed: int = 0) -> torch.Tensor:
    """``(3, size, size)`` a smooth intensity with one sharp edge, in [0.1, 0.9]."""
    g = torch.Generator().manual_seed(seed)
    base = torch.nn.functional.interpolate(torch.rand(1, 3, 8, 8, generator=g), size=(size, size), mode="bicubic",
                                           align_corners=False)[0]
    base[:, :, size // 2:] += 0.3
    return base.clamp(0.0, 1.0) * 0.8 + 0.1


def _twelve(intensity: torch.Tensor, deviation: torch.Tensor) -> torch.Tensor:
    """``(12, H, W)`` from the analyzer mean ``(3, H, W)`` and the deviations ``(4, 3, H, W)``."""
    deviation = deviation - deviation.mean(dim=0, keepdim=True)
    return (intensity[None] + deviation).reshape(12, *intensity.shape[1:])


def _polarization_star(size: int = 64) -> torch.Tensor:
    """``(4, 3, H, W)`` analyzer deviations of a star of polarization angles under a flat intensity."""
    y, x = torch.meshgrid(torch.arange(size) - size / 2, torch.arange(size) - size / 2, indexing="ij")
    angle = 8 * torch.atan2(y, x)
    analyzers = torch.tensor([0.0, 0.25, 0.5, 0.75]) * torch.pi
    return 0.2 * torch.cos(2 * (analyzers[:, None, None, None] - angle[None, None])).expand(4, 3, size, size)


def test_the_filter_keeps_the_analyzer_mean_and_radius_zero_is_the_identity():
    g = torch.Generator().manual_seed(1)
    image = _twelve(_intensity(), 0.05 * torch.randn(4, 3, 64, 64, generator=g))
    out = filter_polarization(image, 2, 1e-4)
    torch.testing.assert_close(out.reshape(4, 3, 64, 64).mean(0), image.reshape(4, 3, 64, 64).mean(0),
                               atol=1e-6, rtol=0)
    assert not torch.allclose(out, image)
    torch.testing.assert_close(filter_polarization(image, 0, 1e-4), image)
    assert apply_chosen_filter(image, {"radius": 0, "eps": 0.0}) is image
    assert apply_chosen_filter(image, None) is image
    with pytest.raises(InputError, match="image"):
        filter_polarization(image[:6], 2, 1e-4)


def test_noise_in_an_unpolarized_scene_is_filtered_and_the_filter_is_chosen():
    """Truth unpolarized, estimate with noisy deviations: every filter lowers the error, and the choice (errors
    against the truth standing in for held-out samples) is a filter."""
    intensity = _intensity()
    truth = _twelve(intensity, torch.zeros(4, 3, 64, 64))
    g = torch.Generator().manual_seed(2)
    estimate = _twelve(intensity, 0.03 * torch.randn(4, 3, 64, 64, generator=g))
    for radius, eps in ((1, 1e-4), (2, 1e-3), (4, 1e-2)):
        assert float((filter_polarization(estimate, radius, eps) - truth).square().mean()) < \
            0.5 * float((estimate - truth).square().mean())
    choice = choose_polarization_filter(lambda x: (x - truth).square().flatten(), estimate)
    assert choice["radius"] > 0 and len(choice["candidates"]) == 6
    assert all(row["relative_change"] < 0 for row in choice["candidates"])


def test_polarization_only_structure_refuses_every_filter():
    """A polarization star under flat intensity, estimated exactly but for faint noise: every filter smooths the
    star, so none is chosen."""
    intensity = torch.full((3, 64, 64), 0.5)
    truth = _twelve(intensity, _polarization_star())
    g = torch.Generator().manual_seed(3)
    estimate = truth + 1e-3 * torch.randn(truth.shape, generator=g)
    choice = choose_polarization_filter(lambda x: (x - truth).square().flatten(), estimate)
    assert choice["radius"] == 0 and choice["eps"] == 0.0
    assert all(row["relative_change"] > 0 for row in choice["candidates"])


def test_a_gain_within_the_noise_of_the_samples_is_not_taken():
    """Held-out samples whose errors are noise that no filter changes: no candidate beats one standard error."""
    g = torch.Generator().manual_seed(4)
    image = _twelve(_intensity(), torch.zeros(4, 3, 64, 64))
    noise = torch.rand(image.numel(), generator=g, dtype=torch.float64)
    choice = choose_polarization_filter(lambda x: noise + 1e-9 * x.flatten().double(), image)
    assert choice["radius"] == 0


def test_the_validation_records_its_choice_only_when_asked():
    target = torch.zeros(12, 8, 8)
    for ask in (False, True):
        rule = HoldoutValidation(lambda x: x, target, torch.ones_like(target), choose_filter=ask)
        rule.begin(torch.rand(12, 8, 8))
        assert ("polarization_filter_choice" in rule.record()) is ask


def test_caps_plus_records_and_applies_the_choice(smooth_random_scene):
    """The held-out pixels' choice (made on the count's validation) is recorded, and the final image is the
    unfiltered solve with that filter applied."""
    capture = simulate_capture(smooth_random_scene(48, seed=5), make_sensor("gaussian", sigma=0.02), seed=5)
    common = {"true_warps": True, "physical_projection": False}
    out, record = reconstruct(capture, "caps-plus", polarization_filter="auto", **common)
    selection = record["params"]["selection"]
    assert selection["polarization_evidence"]["structure"] is True
    assert selection["polarization_filter_from"] == "holdout"
    candidates = selection["polarization_filter_candidates"]
    assert [(row["radius"], row["eps"]) for row in candidates] == [tuple(f) for f in POLARIZATION_FILTERS]
    chosen = record["params"]["polarization_filter"]
    assert chosen == record["resolved_options"]["polarization_filter"]
    plain, _ = reconstruct(capture, "caps-plus", iterations=record["params"]["iterations"], polarization_filter="none",
                           **common)
    if chosen == "none":
        np.testing.assert_array_equal(out.image, plain.image)
    else:
        radius, eps = chosen.split(",")
        assert (int(radius), float(eps)) in POLARIZATION_FILTERS
        expected = filter_polarization(torch.from_numpy(plain.image), int(radius), float(eps)).numpy()
        np.testing.assert_allclose(out.image, expected, atol=1e-6, rtol=0)


def test_a_given_count_still_chooses_the_filter_and_none_turns_it_off(smooth_random_scene):
    capture = simulate_capture(smooth_random_scene(32, seed=5), make_sensor("gaussian", sigma=0.02), seed=5)
    _, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=3, polarization_filter="auto")
    selection = record["params"]["selection"]
    assert selection["iterations_from"] == "options" and record["params"]["iterations"] == 3
    assert selection["polarization_filter_from"] in ("holdout", "stokes-consistency")
    _, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=3, polarization_filter="none",
                            data_term="cagf-stokes", init="agree")
    assert record["params"]["selection"] == SELECTED_NOTHING and record["params"]["polarization_filter"] == "none"


@pytest.mark.parametrize("mode", ["gaussian", "holdout"])
def test_a_bad_mode_is_refused_with_the_option_named(smooth_random_scene, mode):
    """``holdout`` (the held-out pixels without the Stokes-consistency test) is no mode any more."""
    capture = simulate_capture(smooth_random_scene(32, seed=6), make_sensor("gaussian", sigma=0.01), seed=6)
    with pytest.raises(InputError, match="option polarization_filter"):
        reconstruct(capture, "caps-plus", true_warps=True, polarization_filter=mode)
