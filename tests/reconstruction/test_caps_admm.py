"""ADMM with adaptive parameters (paper section 4, eq. 27-30) and its convergence record."""

import numpy as np
import pytest
import torch

from capssim.errors import InputError
from capssim.reconstruct.solvers.admm import ADMMParameters, admm, mu_schedule


def tiny_capture(size=48, sigma=0.01, seed=0):
    from scipy.ndimage import gaussian_filter

    from capssim.camera.sensor import make_sensor
    from capssim.simulate import simulate_capture
    from capssim.stokes.polarization import twelve_from_stokes

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    s0 = np.stack([0.3 + 0.3 * (np.sin(2 * np.pi * 4 * xx + 2 * yy) > 0) * g
                   + 0.1 * gaussian_filter(rng.random((size, size)), 2) for g in (1.0, 0.7, 0.5)])
    d = 0.3 * gaussian_filter(rng.random((size, size)), 5) / 0.5
    a = np.pi * yy
    gt = twelve_from_stokes(np.stack([s0, s0 * d * np.cos(2 * a), s0 * d * np.sin(2 * a)])).astype(np.float32)
    return simulate_capture(gt, make_sensor("gaussian", sigma=sigma), seed=seed)


def test_mu_schedule_eq27():
    p = ADMMParameters()
    assert [mu_schedule(i, p) for i in (0, 4, 5, 9, 10, 24)] == pytest.approx([0.5, 0.5, 0.6, 0.6, 0.7, 0.9])
    assert mu_schedule(100, p) == 1.0


def test_parameter_validation():
    # the block-matching schedule's own checks: tests/test_caps_nlstr.py (MatchSchedule)
    for bad in (ADMMParameters(iterations=-1), ADMMParameters(dt=0), ADMMParameters(grow_step=0),
                ADMMParameters(mu0=float("nan"))):
        with pytest.raises(InputError):
            bad.validate()


def _changed(history, i):
    """True where iteration i changed a parameter: re-matched blocks, new (lazily updated) dictionaries
    after reused ones (``dictionary_gap``), or stepped mu."""
    new_dictionaries = history[i].get("new_dictionaries", False) and i > 0 \
        and not history[i - 1].get("new_dictionaries", True)
    return (history[i].get("rematched", False) or new_dictionaries
            or (i > 0 and history[i]["mu"] != history[i - 1]["mu"]))


@pytest.mark.parametrize("method", ["caps", "caps-no-cagf"])
def test_objective_decreases(method):
    from capssim.reconstruct.registry import reconstruct

    cap = tiny_capture()
    _, record = reconstruct(cap, method, true_warps=True)
    hist = record["history"]
    assert len(hist) == 25
    obj = np.array([h["objective"] for h in hist])
    assert np.all(np.isfinite(obj))
    assert obj[-1] < 0.01 * obj[0]
    # non-increasing while mu and the groups stay the same (the jumps are where they change)
    for i in range(2, len(hist)):
        if not _changed(hist, i) and not _changed(hist, i - 1):
            assert obj[i] <= obj[i - 1] * (1 + 1e-3), (i, obj[i - 1], obj[i])
    # the history shows the schedule: 40 similar blocks, 5 fewer at each re-matching, not every iteration
    n_sim = [h["n_similar"] for h in hist]
    assert n_sim[0] == 40 and all(b in (a, a - 5) for a, b in zip(n_sim, n_sim[1:]))
    rematched = sum(h["rematched"] for h in hist)
    assert 2 <= rematched <= 10
    assert [h["mu"] for h in hist][::5] == pytest.approx([0.5, 0.6, 0.7, 0.8, 0.9])
    assert hist[-1]["primal_residual"] < 0.2 * hist[0]["primal_residual"]


def test_data_only_descent_decreases_every_iteration():
    from capssim.reconstruct.registry import reconstruct

    _, record = reconstruct(tiny_capture(), "caps-no-nlstr", true_warps=True)
    data = [h["data"] for h in record["history"]]
    assert all(b < a for a, b in zip(data, data[1:]))
    assert record["history"][0]["energy_before"] > data[0]


def test_admm_rejects_bad_init():
    from capssim.reconstruct.model.data_term import ConfidenceDataTerm

    class Dummy:
        image_shape = (12, 8, 8)

    with pytest.raises(InputError):
        admm(Dummy(), torch.zeros(12, 4, 4), None)
    with pytest.raises(InputError):
        admm(Dummy(), torch.full((12, 8, 8), float("nan")), None)
    del ConfidenceDataTerm
