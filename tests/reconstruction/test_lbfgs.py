"""L-BFGS with a strong-Wolfe line search (reconstruct.lbfgs): iterates, stopping, no torch._dynamo."""

import subprocess
import sys

import pytest
import torch

from capssim.reconstruct.registration.lbfgs import Memory, cubic_minimizer, minimize_lbfgs


def rosenbrock(x: torch.Tensor) -> torch.Tensor:
    return (100 * (x[..., 1:] - x[..., :-1] ** 2) ** 2 + (1 - x[..., :-1]) ** 2).sum()


def value_and_gradient(x: torch.Tensor):
    x = x.detach().requires_grad_(True)
    f = rosenbrock(x)
    (g,) = torch.autograd.grad(f, x)
    return float(f.detach()), g


def torch_lbfgs(x0: torch.Tensor, max_iterations: int):
    p = x0.clone().requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=max_iterations, tolerance_grad=1e-7, tolerance_change=1e-9,
                            history_size=20, line_search_fn="strong_wolfe")
    evaluations = 0

    def closure():
        nonlocal evaluations
        evaluations += 1
        opt.zero_grad()
        loss = rosenbrock(p)
        loss.backward()
        return loss

    opt.step(closure)
    return p.detach(), opt.state[p]["n_iter"], evaluations


@pytest.mark.parametrize("shape,seed", [((2,), 0), ((5,), 1), ((3, 4), 2)])
@pytest.mark.parametrize("max_iterations", [200, 7])
def test_same_iterates_as_torch_optim(shape, seed, max_iterations):
    torch.manual_seed(seed)
    x0 = 1.5 * torch.randn(shape, dtype=torch.float64)
    x, iterations, evaluations = minimize_lbfgs(value_and_gradient, x0, max_iterations=max_iterations,
                                                tolerance_grad=1e-7, tolerance_change=1e-9)
    expected, expected_iterations, expected_evaluations = torch_lbfgs(x0, max_iterations)
    assert x.shape == x0.shape
    assert (iterations, evaluations) == (expected_iterations, expected_evaluations)
    torch.testing.assert_close(x, expected, rtol=0, atol=1e-9)
    if max_iterations == 200:
        torch.testing.assert_close(x, torch.ones_like(x), rtol=0, atol=1e-4)


def test_stops_at_once_on_a_stationary_start():
    x0 = torch.ones(4, dtype=torch.float64)
    x, iterations, evaluations = minimize_lbfgs(value_and_gradient, x0, max_iterations=50, tolerance_grad=1e-7,
                                                tolerance_change=1e-9)
    assert (iterations, evaluations) == (0, 1)
    assert torch.equal(x, x0)


def test_quadratic_converges_and_respects_evaluation_budget():
    a = torch.diag(torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64))

    def quadratic(x):
        return float(0.5 * x @ a @ x), a @ x

    x, _, _ = minimize_lbfgs(quadratic, torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64), max_iterations=100,
                             tolerance_grad=1e-10, tolerance_change=1e-14)
    assert float(x.abs().max()) < 1e-6
    _, _, evaluations = minimize_lbfgs(value_and_gradient, torch.full((6,), -1.2, dtype=torch.float64),
                                       max_iterations=8, tolerance_grad=1e-7, tolerance_change=1e-9)
    assert evaluations <= 8 * 5 // 4 + 26


def test_warm_start_from_a_related_problem_takes_fewer_iterations():
    # an ill-conditioned quadratic, then the same curvature with another minimum (the next pyramid level)
    a = torch.diag(torch.logspace(0, 3, 8, dtype=torch.float64))
    shift = torch.linspace(-1, 1, 8, dtype=torch.float64)

    def first(x):
        return float(0.5 * x @ a @ x), a @ x

    def second(x):
        return float(0.5 * (x - shift) @ a @ (x - shift)), a @ (x - shift)

    options = dict(max_iterations=200, tolerance_grad=1e-10, tolerance_change=1e-14)
    memory = Memory()
    x1, _, _ = minimize_lbfgs(first, torch.ones(8, dtype=torch.float64), memory=memory, **options)
    assert memory.steps and float(x1.abs().max()) < 1e-6
    cold, cold_iterations, _ = minimize_lbfgs(second, x1, **options)
    warm, warm_iterations, _ = minimize_lbfgs(second, x1, memory=memory, **options)
    torch.testing.assert_close(warm, shift, rtol=0, atol=1e-6)
    torch.testing.assert_close(cold, shift, rtol=0, atol=1e-6)
    assert warm_iterations < cold_iterations
    # pairs of another shape are dropped, not used
    _, _, _ = minimize_lbfgs(lambda x: (float(0.5 * x @ x), x), torch.ones(3, dtype=torch.float64), memory=memory,
                             **options)
    assert all(s.shape == (3,) for s in memory.steps)


def test_cubic_minimizer():
    # f(t) = (t - 0.3)^2 through t = 0 and 1: the exact minimiser
    assert cubic_minimizer(0.0, 0.09, -0.6, 1.0, 0.49, 1.4) == pytest.approx(0.3)
    # clipped to the bounds, and the middle of the bounds without a minimum
    assert cubic_minimizer(0.0, 0.09, -0.6, 1.0, 0.49, 1.4, bounds=(0.5, 2.0)) == 0.5
    assert cubic_minimizer(0.0, 0.0, 1.0, 1.0, 0.9, 1.0, bounds=(2.0, 4.0)) == 3.0


def test_registration_does_not_import_torch_dynamo():
    code = ("import sys, numpy as np\n"
            "from capssim.reconstruct.registration.engine import register_stack\n"
            "import torch\n"
            "g = torch.Generator().manual_seed(0)\n"
            "ref = torch.nn.functional.avg_pool2d(torch.rand(1, 72, 72, generator=g, dtype=torch.float64), 3, 1)[0]\n"
            "moving = torch.roll(ref, 1, 1)[None].repeat(3, 1, 1)\n"
            "register_stack(ref, moving, model='translation')\n"
            "print('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_registration_runs_under_no_grad():
    from capssim.reconstruct.registration.engine import register_stack

    g = torch.Generator().manual_seed(0)
    ref = torch.nn.functional.avg_pool2d(torch.rand(1, 72, 72, generator=g, dtype=torch.float64), 3, 1)[0]
    moving = torch.roll(ref, 1, 1)[None].repeat(3, 1, 1)
    with torch.no_grad():
        reg = register_stack(ref, moving, model="translation")
    # moving(x + 1) = ref(x): reference pixel x maps to moving pixel x + 1
    assert abs(reg.matrices[:, 0, 2] - 1.0).max() < 0.02
    assert abs(reg.matrices[:, 1, 2]).max() < 0.02


def test_registration_box_sum_gradient_is_exact():
    from capssim.reconstruct.registration.image_ops import box_sum

    x = torch.rand(2, 7, 9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: box_sum(t, 2), (x,))
    assert torch.autograd.gradcheck(lambda t: box_sum(t, 4), (x,))  # window larger than the image
