"""The Stokes-subspace data term (issue 36): ``cagf-stokes``, ``cagf-agree``'s direction projected onto the images
that ideal analyzers at 0/45/90/135 deg can produce (``I_0 - I_45 + I_90 - I_135 = 0``), ``caps-plus``'s default."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capssim.camera.sensor import make_sensor
from capssim.errors import CapssimError
from capssim.reconstruct import reconstruct
from capssim.reconstruct.model.analyzer_agreement import agreement_confidence_mix
from capssim.reconstruct.model.stokes_subspace import STOKES_NULL_VECTOR, stokes_projection
from capssim.simulate import simulate_capture

SIZE = 48


def stokes_image(s0, s1, s2):
    """``(12, h, w)`` angle-major intensities of ideal analyzers at 0/45/90/135 deg, the same for three colours."""
    per_angle = [(s0 + s1) / 2, (s0 + s2) / 2, (s0 - s1) / 2, (s0 - s2) / 2]
    return torch.stack([img for img in per_angle for _ in range(3)])


def null_component(x):
    v = x.reshape(4, x.shape[0] // 4, *x.shape[1:])
    return v[0] - v[1] + v[2] - v[3]


def random_image(c=12, h=5, w=6, seed=0):
    return torch.randn(c, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def test_images_of_linear_polarization_are_left_as_they_are():
    g = torch.Generator().manual_seed(1)
    s0 = torch.rand(7, 8, generator=g, dtype=torch.float64)
    s1, s2 = [(torch.rand(7, 8, generator=g, dtype=torch.float64) - 0.5) * s0 for _ in range(2)]
    x = stokes_image(s0, s1, s2)
    assert torch.allclose(stokes_projection(x), x, atol=1e-14)


def test_the_projection_removes_the_null_vector_and_is_an_orthogonal_projection():
    a, b = random_image(seed=2), random_image(seed=3)
    qa = stokes_projection(a)
    assert float(null_component(qa).abs().max()) < 1e-13                          # eq. (1) holds after it
    assert torch.allclose(stokes_projection(qa), qa, atol=1e-14)                   # idempotent
    assert abs(float((qa * b).sum() - (a * stokes_projection(b)).sum())) < 1e-10   # self-adjoint (dot test)
    n = torch.tensor(STOKES_NULL_VECTOR, dtype=torch.float64).repeat_interleave(3).reshape(12, 1, 1)
    assert float(stokes_projection(n * torch.ones(12, 2, 2, dtype=torch.float64)).abs().max()) < 1e-14
    one_colour = random_image(4, 3, 3, seed=4)                                     # caps-iccp's per-colour problems
    assert float(null_component(stokes_projection(one_colour)).abs().max()) < 1e-13


def test_a_wrong_channel_count_is_refused():
    with pytest.raises(CapssimError, match="multiple of the 4 analyzers"):
        stokes_projection(torch.zeros(6, 3, 3))


def test_the_direction_is_symmetric_positive_semidefinite_in_the_subspace(random_confidence, per_pixel_matrix):
    """Q T Q per pixel, T cagf-agree's mixing: a descent direction of the same data term, inside the subspace."""
    conf = random_confidence(12, 3, 4, seed=6)
    alpha = torch.rand(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    t = per_pixel_matrix(lambda e: stokes_projection(agreement_confidence_mix(conf, stokes_projection(e), alpha)), 12, 3, 4)
    assert torch.allclose(t, t.transpose(-1, -2), atol=1e-12)
    assert torch.linalg.eigvalsh(t).min() > -1e-10
    n = torch.tensor(STOKES_NULL_VECTOR, dtype=torch.float64).repeat_interleave(3)
    assert float((t @ n).abs().max()) < 1e-12                                       # nothing along the null vector


@pytest.fixture(scope="module")
def polarization_only_capture():
    """Polarization-only structure: S0 flat, S1 and S2 a fine pattern (the polarization star's kind of scene)."""
    yy, xx = torch.meshgrid(torch.arange(SIZE, dtype=torch.float64), torch.arange(SIZE, dtype=torch.float64),
                            indexing="ij")
    angle = 0.5 * torch.atan2(yy - SIZE / 2 + 0.3, xx - SIZE / 2 + 0.7) * 9 + 0.02 * (xx + 2 * yy)
    s0 = torch.full_like(xx, 0.8)
    scene = stokes_image(s0, 0.7 * s0 * torch.cos(2 * angle), 0.7 * s0 * torch.sin(2 * angle))
    return simulate_capture(scene.float().numpy(), make_sensor("none"), seed=3)


def test_caps_plus_runs_it_by_default_and_it_gains_on_polarization_only_structure(polarization_only_capture):
    cap = polarization_only_capture
    gt = np.asarray(cap.gt, dtype=np.float64)
    errors = {}
    for term in ("cagf-stokes", "cagf-agree"):
        options = {} if term == "cagf-stokes" else {"data_term": term}
        out, record = reconstruct(cap, "caps-plus", true_warps=True, iterations=30, polarization_filter="none", **options)
        assert record["params"]["data_term"] == term
        assert np.isfinite(out.image).all()
        errors[term] = float(((out.image[:, 4:-4, 4:-4] - gt[:, 4:-4, 4:-4]) ** 2).mean())
    assert errors["cagf-stokes"] < 0.99 * errors["cagf-agree"], errors  # measured: 0.985 of it
