"""The solvers against their two interfaces: a data-fidelity term and a prior (issue 19, item 4)."""

import ast
import importlib.util

import pytest
import torch

from capssim.errors import InputError
from capssim.reconstruct.priors.tikhonov import TikhonovPrior
from capssim.reconstruct.solvers.admm import ADMMParameters, admm
from capssim.reconstruct.solvers.descent import steepest_descent


class Denoising:
    """``f(x) = 1/2 ||x - y||^2``: the simplest data term (``D = y - x = -grad f``)."""

    def __init__(self, y: torch.Tensor):
        self.y = y

    @property
    def image_shape(self):
        return tuple(self.y.shape)

    def value(self, x):
        return 0.5 * float((x - self.y).square().sum())

    def descent_direction(self, x):
        r = self.y - x
        return r, 0.5 * float(r.square().sum())


def noisy_smooth_image(seed=0, shape=(3, 32, 32), sigma=0.05):
    g = torch.Generator().manual_seed(seed)
    truth = torch.nn.functional.avg_pool2d(torch.rand(shape[0], 1, *shape[1:], generator=g, dtype=torch.float64),
                                           5, 1, 2)[:, 0]
    return truth, truth + sigma * torch.randn(shape, generator=g, dtype=torch.float64)


def imported_modules(module: str) -> set[str]:
    tree = ast.parse(open(importlib.util.find_spec(module).origin).read())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module or "")
    return names


@pytest.mark.parametrize("module", ["capssim.reconstruct.solvers.admm", "capssim.reconstruct.solvers.descent",
                                    "capssim.reconstruct.solvers.interfaces"])
def test_solvers_import_neither_nlstr_nor_the_data_term(module):
    for name in imported_modules(module):
        assert "nlstr" not in name and "data_term" not in name, (module, name)


def test_admm_with_a_tikhonov_prior_reaches_the_minimizer():
    truth, y = noisy_smooth_image()
    prior = TikhonovPrior(2.0)
    exact = prior.proximal(y, 1.0)  # argmin 1/2||x - y||^2 + R(x), in closed form
    x, hist = admm(Denoising(y), y.clone(), prior, ADMMParameters(iterations=60, dt=0.5))
    assert len(hist) == 60
    assert float((x - exact).norm() / exact.norm()) < 1e-8
    assert hist[-1]["objective"] < 1e-12 * hist[0]["objective"]
    converging = hist[:45]  # then the combined residual is at the rounding floor (~1e-32)
    assert all(b["objective"] < a["objective"] for a, b in zip(converging, converging[1:]))
    assert {"regularizer", "data", "primal_residual", "dual_residual"} <= set(hist[-1])
    assert hist[-1]["regularizer"] == pytest.approx(prior.value(exact), rel=1e-6)
    assert float((x - truth).norm()) < 0.9 * float((y - truth).norm())  # it denoises


def test_prior_runs_are_independent_and_timed():
    _, y = noisy_smooth_image(seed=1)
    stages = []

    def stage(name):
        stages.append(name)
        return torch.autograd.profiler.record_function(name)

    prior = TikhonovPrior(0.5)
    first, _ = admm(Denoising(y), y.clone(), prior, ADMMParameters(iterations=5), stage=stage)
    again, _ = admm(Denoising(y), y.clone(), prior, ADMMParameters(iterations=5))
    assert torch.equal(first, again)
    assert {"tikhonov_prox", "data_term", "admm_update"} <= set(stages)


def test_steepest_descent_decreases_the_data_term_and_records_like_admm():
    _, y = noisy_smooth_image(seed=2)
    x, hist = steepest_descent(Denoising(y), torch.zeros_like(y), ADMMParameters(iterations=4, dt=0.5))
    assert [list(h) for h in hist] == [["iteration", "mu", "data", "change", "energy_before", "energy_after",
                                        "objective"]] * 4
    data = [h["data"] for h in hist]
    assert all(b < a for a, b in zip(data, data[1:]))
    assert torch.allclose(x, y * (1 - 0.5**4))  # x_k = (1 - (1 - dt)^k) y


def test_bad_input_is_refused():
    _, y = noisy_smooth_image()
    with pytest.raises(InputError):
        TikhonovPrior(-1.0)
    with pytest.raises(InputError):
        admm(Denoising(y), torch.zeros(3, 4, 4, dtype=torch.float64), TikhonovPrior(1.0))
    with pytest.raises(InputError):
        steepest_descent(Denoising(y), torch.full_like(y, float("nan")))
    with pytest.raises(FloatingPointError, match="diverged"):
        admm(Denoising(y), y.clone(), TikhonovPrior(1.0), ADMMParameters(iterations=2000, dt=1.9))
