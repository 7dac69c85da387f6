"""The Stokes-consistency test that ``caps-plus``'s selection layer asks first (``-p polarization_filter=auto``)
(:mod:`capssim.reconstruct.selection.polarization_evidence`): the ratio ``T`` of the local variance of
``I_0 - I_45 + I_90 - I_135`` to that of the polarization differences, below 1 where the analyzers show
polarization structure."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.observation_model import unmix_analyzer
from capssim.reconstruct.selection import SELECTED_NOTHING, format_filter
from capssim.reconstruct.selection.polarization_evidence import STRUCTURE_THRESHOLD, stokes_inconsistency_ratio
from capssim.reconstruct.selection.polarization_filter import (
    POLARIZATION_FILTERS,
    UNSTRUCTURED_FILTER,
    filter_polarization,
)
from capssim.simulate import simulate_capture

#: the selection record of a run whose every choice was given as an option

ANGLES = torch.tensor([0.0, 45.0, 90.0, 135.0]) * torch.pi / 180


def _analyzer_images(s0: torch.Tensor, s1: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """``(12, H, W)`` ideal analyzers' images ``(S0 + S1 cos 2t + S2 sin 2t) / 2`` of ``(3, H, W)`` Stokes images."""
    c, s = torch.cos(2 * ANGLES)[:, None, None, None], torch.sin(2 * ANGLES)[:, None, None, None]
    return (0.5 * (s0[None] + c * s1[None] + s * s2[None])).reshape(12, *s0.shape[1:])


def _texture(size: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.interpolate(torch.rand(1, 3, size // 4, size // 4, generator=g, dtype=torch.float64),
                                           size=(size, size), mode="bicubic", align_corners=False)[0]


def test_exact_stokes_images_are_consistent_and_unpolarized_errors_give_about_one():
    size = 96
    s0 = 0.4 + 0.4 * _texture(size, 0)
    s1, s2 = 0.3 * (_texture(size, 1) - 0.5), 0.3 * (_texture(size, 2) - 0.5)
    polarized = _analyzer_images(s0, s1, s2)
    assert stokes_inconsistency_ratio(polarized) < 1e-12  # c = 0 exactly; d carries S1, S2
    g = torch.Generator().manual_seed(3)
    errors = 0.02 * torch.randn(12, size, size, generator=g, dtype=torch.float64)  # independent per analyzer
    unpolarized = _analyzer_images(s0, 0 * s1, 0 * s2) + errors
    assert 0.9 < stokes_inconsistency_ratio(unpolarized) < 1.1  # E var(c) = E var(d): the test's null value
    noisy_polarized = polarized + errors
    assert stokes_inconsistency_ratio(noisy_polarized) < 0.5 * STRUCTURE_THRESHOLD  # structure above the errors


def test_analyzers_that_do_not_differ_tell_nothing_and_a_bad_shape_is_refused():
    same = _texture(32, 4).repeat(4, 1, 1)
    assert stokes_inconsistency_ratio(same.float()) == 1.0
    with pytest.raises(InputError, match="channels"):
        stokes_inconsistency_ratio(same[:6])


def test_the_ratio_of_a_calibrated_analyzer_is_that_of_the_ideal_images_after_unmixing():
    size = 64
    ideal = _analyzer_images(0.5 + 0.3 * _texture(size, 5), 0.2 * (_texture(size, 6) - 0.5), 0 * _texture(size, 7))
    rng = np.random.default_rng(8)
    block = np.eye(4) + 0.05 * rng.standard_normal((4, 4))  # angle errors and finite extinction, mixed
    analyzer = np.zeros((12, 12))
    for k in range(3):
        analyzer[np.ix_(range(k, 12, 3), range(k, 12, 3))] = block
    seen = torch.einsum("ij,jhw->ihw", torch.as_tensor(analyzer), ideal)
    assert stokes_inconsistency_ratio(seen) > 1e-3  # the mixing reads as inconsistency ...
    assert stokes_inconsistency_ratio(unmix_analyzer(seen, analyzer)) < 1e-12  # ... which unmixing removes


def _unpolarized_capture(size: int, seed: int):
    """A rendered-like texture whose four analyzers see the same image (S1 = S2 = 0), sigma 0.01."""
    s0 = (0.2 + 0.6 * _texture(size, seed)).float()
    fine = torch.Generator().manual_seed(seed + 1)
    s0 = (s0 + 0.15 * torch.rand(1, size, size, generator=fine) * (torch.arange(size) % 3 == 0)).clamp(0, 1)
    gt = s0.repeat(4, 1, 1).numpy()  # channel 3 p + k: every analyzer p sees the same colour image
    return simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=seed)


def test_caps_plus_smooths_the_polarization_of_a_capture_without_polarization_structure():
    capture = _unpolarized_capture(64, seed=9)
    common = {"true_warps": True, "iterations": 8, "physical_projection": False}
    out, record = reconstruct(capture, "caps-plus", polarization_filter="auto", **common)
    params, selection = record["params"], record["params"]["selection"]
    evidence = selection["polarization_evidence"]
    assert evidence["stokes_inconsistency"] >= STRUCTURE_THRESHOLD and evidence["structure"] is False
    assert selection["polarization_filter_from"] == "stokes-consistency" and "holdout_error" not in selection
    assert params["polarization_filter"] == format_filter(UNSTRUCTURED_FILTER) == record["resolved_options"][
        "polarization_filter"]
    plain, plain_record = reconstruct(capture, "caps-plus", polarization_filter="none", **common)
    plain_selection = plain_record["params"]["selection"]  # no filter asked: the test still sets the direction
    assert plain_selection["polarization_filter_from"] == "options" and "holdout_error" not in plain_selection
    assert plain_selection["data_term_from"] == plain_selection["init_from"] == "stokes-consistency"
    assert plain_record["params"]["data_term"] == "cagf" and plain_record["params"]["init"] == "fusion"
    expected = filter_polarization(torch.from_numpy(plain.image), *UNSTRUCTURED_FILTER).numpy()
    np.testing.assert_allclose(out.image, expected, atol=1e-6, rtol=0)
    given, given_record = reconstruct(capture, "caps-plus", polarization_filter=format_filter(UNSTRUCTURED_FILTER),
                                      **common)
    np.testing.assert_array_equal(given.image, out.image)
    assert given_record["params"]["selection"]["polarization_filter_from"] == "options"
    fully_given, fully_record = reconstruct(capture, "caps-plus", polarization_filter="none", data_term="cagf",
                                            init="fusion", **common)
    assert fully_record["params"]["selection"] == SELECTED_NOTHING  # nothing left for the test to set
    np.testing.assert_array_equal(fully_given.image, plain.image)


def test_polarization_structure_is_left_to_the_held_out_pixels(smooth_random_scene):
    capture = simulate_capture(smooth_random_scene(48, seed=5), make_sensor("gaussian", sigma=0.01), seed=5)
    _, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, polarization_filter="auto")
    selection = record["params"]["selection"]
    assert selection["polarization_evidence"]["structure"] is True
    assert selection["polarization_evidence"]["stokes_inconsistency"] < STRUCTURE_THRESHOLD
    assert selection["polarization_filter_from"] == "holdout"
    assert len(selection["polarization_filter_candidates"]) == len(POLARIZATION_FILTERS)


def test_the_ratio_is_finite_when_only_the_inconsistency_varies():
    base = _texture(32, 10)
    pair = base + 0.1 * (_texture(32, 11) - 0.5)  # the 45 and 135 deg analyzers: same image, another than 0 and 90
    channels = torch.stack([base, pair, base, pair]).reshape(12, 32, 32)  # d = 0 everywhere, c varies
    ratio = stokes_inconsistency_ratio(channels)
    assert np.isfinite(ratio) and ratio > 1e6


@pytest.mark.parametrize("case", ["black", "constant", "dark", "saturated", "tiny", "odd"])
def test_the_test_on_hard_captures_gives_a_consistent_record_and_a_finite_image(case, smooth_random_scene):
    """The record's verdict is the ratio's (T < 1), and the filter follows it: the most smoothing one where there is
    no structure, else the held-out pixels' (or none, where too few held-out samples). A black frame's analyzers
    tell nothing (T exactly 1); neither it nor a constant scene shows structure."""
    size = {"tiny": 16, "odd": 40}.get(case, 32)
    gt = smooth_random_scene(size, seed=12)
    if case == "black":
        gt = np.zeros_like(gt)
    elif case == "constant":
        gt = np.full_like(gt, 0.37)
    elif case == "dark":
        gt = gt * 1e-3  # S0 near 0
    elif case == "saturated":
        gt = gt * 4.0  # most of the frame above full scale
    sigma = 0.0 if case in ("black", "constant") else 0.01
    capture = simulate_capture(gt.astype(np.float32), make_sensor("gaussian", sigma=sigma) if sigma else None, seed=12)
    out, record = reconstruct(capture, "caps-plus", true_warps=True, iterations=4, polarization_filter="auto")
    selection = record["params"]["selection"]
    evidence = selection["polarization_evidence"]
    ratio = evidence["stokes_inconsistency"]
    assert np.isfinite(ratio) and ratio >= 0 and evidence["structure"] is bool(ratio < STRUCTURE_THRESHOLD)
    if case == "black":  # four identical (zero) analyzer images tell nothing: exactly the null value
        assert ratio == 1.0
    if case in ("black", "constant"):  # no polarization in the scene
        assert evidence["structure"] is False
    if evidence["structure"]:
        assert selection.get("polarization_filter_from") == "holdout" or "fewer than" in selection.get("note", "")
    else:
        assert selection["polarization_filter_from"] == "stokes-consistency"
        assert record["params"]["polarization_filter"] == format_filter(UNSTRUCTURED_FILTER)
    assert record["params"]["iterations"] == 4 and np.isfinite(out.image).all()


def test_without_structure_the_count_is_chosen_with_caps_direction_and_start():
    """Where the test finds no polarization structure the validation runs caps's data direction and start too, so
    the chosen count is the one chosen when they are given."""
    capture = _unpolarized_capture(64, seed=9)
    out, record = reconstruct(capture, "caps-plus", true_warps=True)
    given, given_record = reconstruct(capture, "caps-plus", true_warps=True, data_term="cagf", init="fusion")
    assert record["params"]["selection"]["iterations_from"] == "holdout"
    assert record["resolved_options"] == given_record["resolved_options"]
    assert record["resolved_options"]["data_term"] == "cagf" and record["resolved_options"]["init"] == "fusion"
    np.testing.assert_array_equal(out.image, given.image)
