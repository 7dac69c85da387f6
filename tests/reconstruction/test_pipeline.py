"""The CAPS pipeline and its slots (issue 36, item 1): methods are configurations; priors and data terms plug in.

A Gaussian-blur denoiser prior and a damped data term are defined and registered in this file alone,
then run through ``reconstruct(capture, "caps", prior=...)`` with no edit of the pipeline or a solver.
The ablations are the pipeline with one slot changed: ``caps -p prior=none`` is ``caps-no-nlstr`` and
``caps -p data_term=plain`` is ``caps-no-cagf``, bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from capssim.camera.sensor import make_sensor
from capssim.errors import InputError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.data_term import ConfidenceDataTerm
from capssim.reconstruct.pipeline import (
    CapsOptions,
    available_priors,
    caps_option_names,
    coerce_option,
    register_data_term,
    register_prior,
)
from capssim.simulate import simulate_capture

SIZE = 48
ITERATIONS = 4


# -- a new prior, in this file alone ----------------------------------------------------------------
@dataclass(frozen=True)
class BlurParameters:
    """The blur prior's own option ``-p blur_sigma=S`` (HR pixels)."""

    blur_sigma: float = 1.0

    def validate(self) -> None:
        if not (self.blur_sigma > 0 and math.isfinite(self.blur_sigma)):
            raise InputError("blur_sigma", self.blur_sigma, "a finite number > 0")


class GaussianBlurPrior:
    """A denoiser as ADMM's prior step: ``X = G_sigma * Z`` per channel (mirror-padded separable Gaussian)."""

    def __init__(self, sigma: float):
        radius = max(1, math.ceil(3 * sigma))
        taps = torch.exp(-0.5 * (torch.arange(-radius, radius + 1, dtype=torch.float32) / sigma) ** 2)
        self.taps, self.radius, self.calls = taps / taps.sum(), radius, 0

    def begin(self) -> None:
        self.calls = 0

    def estimate(self, z, *, mu, iteration, stage):
        self.calls += 1
        with stage("blur_prox"):
            x = z[:, None]
            r = self.radius
            x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), self.taps.to(z)[None, None, None, :])
            x = F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), self.taps.to(z)[None, None, :, None])
        return x[:, 0], {"blur_calls": self.calls}

    def after_step(self, *, iteration, change):
        return {}

    def record(self):
        return {"blur_radius": self.radius}


def blur_prior(shape, *, parameters: BlurParameters, options, device):
    """The factory the pipeline calls once per image shape."""
    return GaussianBlurPrior(parameters.blur_sigma)


register_prior("test-gaussian-blur", blur_prior, parameters=BlurParameters,
               description="Gaussian blur as a denoiser (a test prior)")


# -- a new data term, in this file alone ------------------------------------------------------------
class DampedDataTerm(ConfidenceDataTerm):
    """The plain data term with half its descent direction."""

    def descent_direction(self, x):
        direction, value = super().descent_direction(x)
        return 0.5 * direction, value


register_data_term("test-damped", lambda problem, *, options, stage: DampedDataTerm(
    problem.obs, problem.operator, mixing=problem.mixing), description="half-step data term (a test data term)")


# -- fixtures -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def capture(smooth_random_scene):
    return simulate_capture(smooth_random_scene(SIZE, seed=4), make_sensor("gaussian", sigma=0.01), seed=4)


def run(capture, method="caps", **options):
    out, record = reconstruct(capture, method, true_warps=True, iterations=ITERATIONS, **options)
    return out.image, record


def test_a_prior_registered_in_a_test_file_runs_through_the_pipeline(capture):
    blurred, record = run(capture, prior="test-gaussian-blur")
    nlstr, _ = run(capture)
    assert blurred.shape == (12, SIZE, SIZE) and blurred.dtype == np.float32 and np.isfinite(blurred).all()
    assert np.abs(blurred - nlstr).max() > 1e-3  # another prior, another image
    assert [h["blur_calls"] for h in record["history"]] == list(range(1, ITERATIONS + 1))  # ADMM ran it
    assert record["params"]["prior"] == "test-gaussian-blur" and record["params"]["blur_sigma"] == 1.0
    assert record["params"]["blur_radius"] == 3 and "n_groups" not in record["params"]
    assert "blur_prox" in record["stages_s"] and "test-gaussian-blur_setup" in record["stages_s"]
    wider, wider_record = run(capture, prior="test-gaussian-blur", blur_sigma="2.5")
    assert wider_record["params"]["blur_radius"] == 8 and np.abs(wider - blurred).max() > 1e-3


def test_the_new_prior_fills_the_slot_of_the_cascade_too(capture):
    image, record = run(capture, "caps-iccp", prior="test-gaussian-blur")
    assert image.shape == (12, SIZE, SIZE) and np.isfinite(image).all()
    assert [h["colour"] for h in record["history"]] == [c for c in "RGB" for _ in range(ITERATIONS)]
    assert all(h["blur_calls"] == i % ITERATIONS + 1 for i, h in enumerate(record["history"]))  # begin() per colour


def test_a_data_term_registered_in_a_test_file_runs_through_the_pipeline(capture):
    damped, record = run(capture, data_term="test-damped")
    plain, _ = run(capture, data_term="plain")
    assert np.isfinite(damped).all() and np.abs(damped - plain).max() > 1e-4
    assert record["params"]["data_term"] == "test-damped" and not record["params"]["use_cagf"]


def test_the_ablations_are_the_pipeline_with_one_slot_changed(capture):
    assert np.array_equal(run(capture, prior="none")[0], run(capture, "caps-no-nlstr")[0])
    assert np.array_equal(run(capture, data_term="plain")[0], run(capture, "caps-no-cagf")[0])
    _, record = run(capture, "caps-no-nlstr")
    assert record["params"]["prior"] == "none" and not record["params"]["use_nlstr"]
    assert "nlstr_setup" not in record["stages_s"]


def test_tikhonov_is_a_built_in_prior(capture):
    image, record = run(capture, prior="tikhonov", tikhonov_weight=0.2)
    assert np.isfinite(image).all() and record["params"]["tikhonov_weight"] == 0.2
    assert all("regularizer" in h for h in record["history"])
    assert {"nlstr", "tikhonov", "none", "test-gaussian-blur"} <= set(available_priors())


def test_an_unknown_prior_is_a_one_line_input_error(capture):
    with pytest.raises(InputError) as info:
        run(capture, prior="bm3d")
    message = str(info.value)
    assert info.value.argument == "prior" and "\n" not in message
    assert "'bm3d'" in message and "nlstr, nlstr-denoiser, none, test-gaussian-blur, tikhonov" in message
    assert "-p prior=NAME" in message and "register_prior" in message
    with pytest.raises(InputError, match="data_term: got 'nope'"):
        run(capture, data_term="nope")


def test_prior_options_need_their_prior_and_valid_values(capture):
    with pytest.raises(InputError, match="Add -p prior=tikhonov"):
        CapsOptions.from_options({"tikhonov_weight": 0.1})
    with pytest.raises(InputError, match="blur_sigma"):
        run(capture, prior="test-gaussian-blur", blur_sigma=-1)
    with pytest.raises(InputError, match="option blur_sigma"):
        CapsOptions.from_options({"prior": "test-gaussian-blur", "blur_sigma": "wide"})
    assert {"blur_sigma", "tikhonov_weight", "iterations", "prior"} <= caps_option_names()


def test_a_prior_cannot_take_a_shared_option_name():
    @dataclass(frozen=True)
    class Clashing:
        iterations: int = 3

    with pytest.raises(InputError, match="iterations"):
        register_prior("test-clashing", blur_prior, parameters=Clashing)
    assert "test-clashing" not in available_priors()


@pytest.mark.parametrize("raw,kind,expected", [("3", int, 3), ("2.0", int, 2), ("off", bool, False),
                                               ("0.5", float, 0.5), (3, str, "3"), (7, int, 7)])
def test_coerce_option_is_public_and_typed(raw, kind, expected):
    value = coerce_option("x", raw, kind)
    assert value == expected and type(value) is kind


@pytest.mark.parametrize("raw,kind", [("2.5", int), ("maybe", bool), ("nan", float), (True, int)])
def test_coerce_option_refuses_values_of_another_type(raw, kind):
    with pytest.raises(InputError, match="option x"):
        coerce_option("x", raw, kind)


def test_a_method_schedule_sees_the_front_end_and_the_options_given(capture, monkeypatch):
    """PipelineConfig.schedule runs after the front end, is told which options were given, and its options
    are the ones the solver runs (a method's own choice of options from what its front end measured)."""
    from dataclasses import replace

    from capssim.reconstruct import registry
    from capssim.reconstruct.pipeline import PipelineConfig, run_pipeline

    seen = []

    def two_iterations(front, options, given):
        seen.append((tuple(front.problems[0].obs.images.shape), given))
        return replace(options, admm=replace(options.admm, iterations=2))

    config = PipelineConfig(schedule=two_iterations)
    registry.available_methods()  # the registry is loaded before the test method is added
    monkeypatch.setitem(registry._METHODS, "test-scheduled", registry.MethodSpec(
        "test-scheduled", lambda cap, *, context: run_pipeline(cap, context, config), "caps", "a test", "none",
        __name__))
    out, record = reconstruct(capture, "test-scheduled", true_warps=True, iterations=5, mu0=0.4)
    assert len(out.history) == 2 and record["params"]["iterations"] == 2 and record["params"]["mu0"] == 0.4
    assert seen == [((16, SIZE // 4, SIZE // 4), frozenset({"iterations", "mu0"}))]
