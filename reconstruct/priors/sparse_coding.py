"""Sparse coding in torch: batched orthogonal matching pursuit, the analytic joint dictionary, MOD learning.

Used by ``dofp-jcpd`` (:mod:`capssim.reconstruct.methods.dofp_jcpd`); nothing here knows about mosaics.

Shapes and conventions:

* a dictionary is ``(n, K)``: ``K`` atoms (columns) of signals of length ``n``;
* signals are rows: ``(B, n)``; codes are dense ``(B, K)`` with at most ``len(forced) + sparsity``
  non-zeros per row, so that ``signals ~ codes @ dictionary.T``.

Batched OMP (:func:`omp`) is orthogonal matching pursuit (Pati, Rezaiifar, Krishnaprasad 1993) in
its modified Gram-Schmidt form: the selected (column-normalized) atoms are orthonormalized one at a
time (``Q``, ``R``), so the residual, the correlations ``D^T r`` and the projections ``||Q^T d_j||^2``
of every atom on the support are updated incrementally with one ``(B, n) @ (n, K)`` product per
iteration; coefficients come from the triangular system ``R a = Q^T y`` when a signal stops. All
signals of a batch advance together (a loop over iterations, never over signals); a signal stops
when its residual norm^2 is at most its tolerance, when it holds its atom budget, or when every
remaining atom lies (to 1e-4 in norm^2) in the span of its support. Atoms listed in ``forced`` are
taken first, in order, whatever their correlation (e.g. the DC atoms, so that the local mean is
always represented).

The analytic joint colour-polarization dictionary (:func:`joint_dictionary`) is
``kron(P, C, DCT2)``: polarization basis ``P`` (4x3, angles 0/45/90/135 deg) ``(1,1,1,1)/2``,
``(1,0,-1,0)/sqrt2``, ``(0,1,0,-1)/sqrt2`` (every atom has ``I0 + I90 = I45 + I135``); colour basis
``C`` (3x3, R/G/B) ``(1,1,1)/sqrt3``, ``(1,0,-1)/sqrt2``, ``(1,-2,1)/sqrt6``; and the orthonormal 2-D
DCT-II of ``p x p``. Rows are ``c * p^2 + r * p + s`` (channel ``c = 3 * pol + colour``, pixel
``(r, s)``), i.e. the lexicographic (channel, row, column) vectorization; its ``9 p^2`` columns are
orthonormal in the ``12 p^2``-dimensional space.

:func:`learn_dictionary` is the method of optimal directions (MOD; Engan, Aase, Husoy, ICASSP 1999):
alternate OMP coding and the least-squares dictionary update ``D = X^T A (A^T A + eps I)^-1``.
"""

from __future__ import annotations

import math

import torch

#: colour basis (columns), R/G/B: luminance, R-B, (R+B)/2-G
COLOUR_BASIS = ((1 / math.sqrt(3), 1 / math.sqrt(2), 1 / math.sqrt(6)),
                (1 / math.sqrt(3), 0.0, -2 / math.sqrt(6)),
                (1 / math.sqrt(3), -1 / math.sqrt(2), 1 / math.sqrt(6)))
#: polarization basis (columns), angles 0/45/90/135 deg: S0-like, S1-like, S2-like
POLARIZATION_BASIS = ((0.5, 1 / math.sqrt(2), 0.0),
                      (0.5, 0.0, 1 / math.sqrt(2)),
                      (0.5, -1 / math.sqrt(2), 0.0),
                      (0.5, 0.0, -1 / math.sqrt(2)))
#: an atom is considered in the span of a support when ``1 - ||Q^T d||^2`` is below this (unit atoms)
SPAN_FLOOR = 1e-4


def dct_matrix(n: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Orthonormal DCT-II ``(n, n)``: row ``u`` is the frequency-``u`` basis vector."""
    i = torch.arange(n, dtype=dtype, device=device)
    u = torch.arange(n, dtype=dtype, device=device)[:, None]
    m = torch.cos(math.pi * (2 * i + 1) * u / (2 * n)) * math.sqrt(2.0 / n)
    m[0] /= math.sqrt(2.0)
    return m


def channel_basis(*, dtype=torch.float64, device=None) -> torch.Tensor:
    """``(12, 9)`` = ``kron(P, C)``: row ``c = 3 * pol + colour``, column ``3 * j_pol + j_colour``."""
    pol = torch.tensor(POLARIZATION_BASIS, dtype=dtype, device=device)
    col = torch.tensor(COLOUR_BASIS, dtype=dtype, device=device)
    return torch.kron(pol, col)


def joint_dictionary(patch: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Analytic joint dictionary ``(12 p^2, 9 p^2)`` = ``kron(P, C, DCT2)``, orthonormal columns.

    Column ``j * p^2 + u * p + v``: channel atom ``j`` (:func:`channel_basis`) times the 2-D DCT
    atom of frequency ``(u, v)``; the 9 columns with ``u = v = 0`` are the spatially constant atoms.
    """
    c = dct_matrix(patch, dtype=dtype, device=device)
    ct = c.T.contiguous()
    dct2 = torch.kron(ct, ct)  # (p^2 pixels, p^2 frequencies)
    return torch.kron(channel_basis(dtype=dtype, device=device), dct2)


def constant_atoms(dictionary: torch.Tensor, channels: int = 12, *, rtol: float = 1e-6) -> torch.Tensor:
    """Indices of the atoms that are constant over the pixels of every channel (the "DC" atoms)."""
    n, k = dictionary.shape
    d = dictionary.reshape(channels, n // channels, k)
    spread = (d - d.mean(dim=1, keepdim=True)).abs().amax(dim=(0, 1))
    scale = dictionary.abs().amax(dim=0).clamp_min(torch.finfo(dictionary.dtype).tiny)
    return torch.nonzero(spread <= rtol * scale).flatten()


def normalize_columns(dictionary: torch.Tensor, *, floor: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """``(D / norms, norms)``; columns with norm below ``floor`` become zero (never selected by OMP)."""
    norms = dictionary.norm(dim=0)
    usable = norms > floor
    scale = torch.where(usable, 1.0 / torch.where(usable, norms, torch.ones_like(norms)), torch.zeros_like(norms))
    return dictionary * scale, norms


def _state_select(state: dict, keep: torch.Tensor) -> dict:
    return {key: value[keep] for key, value in state.items()}


def _finish(codes: torch.Tensor, state: dict, done: torch.Tensor, k: int, scale: torch.Tensor) -> None:
    """Solve ``R a = z`` for the finished signals and write their coefficients into ``codes``."""
    if k == 0 or not bool(done.any()):
        return
    r = state["R"][done][:, :k, :k]
    z = state["z"][done][:, :k, None]
    a = torch.linalg.solve_triangular(r, z, upper=True)[..., 0]
    sel = state["S"][done][:, :k]
    codes[state["ids"][done][:, None], sel] = a * scale[sel]


def omp(dictionary: torch.Tensor, signals: torch.Tensor, *, sparsity: int, tolerance=0.0,
        forced: torch.Tensor | None = None, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Batched OMP: codes ``(B, K)`` of ``signals`` ``(B, n)`` over ``dictionary`` ``(n, K)``.

    ``sparsity``: atoms chosen by correlation per signal, on top of the ``forced`` atom indices
    (taken first, in order). ``tolerance``: a number or ``(B,)`` tensor; a signal stops once its
    residual ``||y - D a||^2`` is at most it. The dictionary is column-normalized for the selection
    (atoms of norm < 1e-6 are never chosen); the codes are for the dictionary as given.
    ``weights`` ``(K,)``: optional selection weights, the atom chosen maximizes ``w_j |d_j^T r|``
    (a prior preferring some atoms; the least squares on the support is unweighted).
    """
    dn, norms = normalize_columns(dictionary)
    scale = torch.where(norms > 1e-6, 1.0 / norms.clamp_min(1e-30), torch.zeros_like(norms))
    forced = torch.zeros(0, dtype=torch.long, device=signals.device) if forced is None else forced.to(signals.device)
    b, n = signals.shape
    kmax = int(forced.numel()) + int(sparsity)
    tol = torch.as_tensor(tolerance, dtype=signals.dtype, device=signals.device).expand(b).clone()
    codes = signals.new_zeros((b, dictionary.shape[1]))
    state = {"ids": torch.arange(b, device=signals.device), "r": signals.clone(), "c": signals @ dn,
             "proj": signals.new_zeros((b, dictionary.shape[1])), "Q": signals.new_zeros((b, n, kmax)),
             "R": signals.new_zeros((b, kmax, kmax)), "z": signals.new_zeros((b, kmax)),
             "S": torch.zeros((b, kmax), dtype=torch.long, device=signals.device), "tol": tol}
    dead = norms <= 1e-6
    w = torch.ones_like(norms) if weights is None else weights.to(norms)
    for k in range(kmax + 1):
        if k >= forced.numel():  # the forced atoms are taken whatever the residual
            stop = (state["r"].square().sum(1) <= state["tol"]) | (k == kmax)
            if k < kmax:
                score = (state["c"].abs() * w).masked_fill((1 - state["proj"] < SPAN_FLOOR) | dead, -1.0)
                best, idx = score.max(dim=1)
                stop = stop | (best < 0)
            _finish(codes, state, stop, k, scale)
            if bool(stop.all()):
                break
            state = _state_select(state, ~stop)
            if bool(stop.any()):
                idx = idx[~stop]
        else:
            idx = forced[k].expand(state["ids"].shape[0])
        _omp_step(state, dn, idx, k)
    return codes


def _omp_step(state: dict, dn: torch.Tensor, idx: torch.Tensor, k: int) -> None:
    """Add atom ``idx`` (one per signal) to each support: Gram-Schmidt, then residual and correlations."""
    d = dn.T[idx]  # (b, n)
    q_old = state["Q"][:, :, :k]
    coef = torch.einsum("bnk,bn->bk", q_old, d)
    q = d - torch.einsum("bnk,bk->bn", q_old, coef)
    rkk = q.norm(dim=1).clamp_min(1e-12)
    q = q / rkk[:, None]
    state["Q"][:, :, k] = q
    state["R"][:, :k, k] = coef
    state["R"][:, k, k] = rkk
    state["S"][:, k] = idx
    qd = q @ dn  # (b, K)
    qr = (q * state["r"]).sum(1)
    state["z"][:, k] = qr
    state["r"] -= qr[:, None] * q
    state["c"] -= qr[:, None] * qd
    state["proj"] += qd.square()


def representation_error(dictionary: torch.Tensor, signals: torch.Tensor, codes: torch.Tensor) -> float:
    """Relative error ``||X - A D^T||_F / ||X||_F``."""
    return float((signals - codes @ dictionary.T).norm() / signals.norm().clamp_min(1e-30))


def learn_dictionary(patches: torch.Tensor, *, atoms: int, sparsity: int, iterations: int,
                     generator: torch.Generator | None = None, ridge: float = 1e-6,
                     initial: torch.Tensor | None = None) -> tuple[torch.Tensor, list[float]]:
    """MOD dictionary learning: ``(dictionary (n, atoms), errors)`` from ``patches`` ``(N, n)``.

    Starts from ``initial`` or from ``atoms`` distinct patches drawn with ``generator``
    (normalized), then alternates OMP with ``sparsity`` atoms per patch and the MOD update
    ``D^T = (A^T A + ridge I)^-1 A^T X``; unused or vanishing atoms are replaced by random patches.
    ``errors``: the relative representation error (:func:`representation_error`) before each
    update and after the last (``iterations + 1`` values). Deterministic for a given ``generator``.
    """
    x = patches
    n_patches, n = x.shape
    if atoms < 1 or sparsity < 1 or iterations < 0 or n_patches < atoms:
        raise ValueError(f"learn_dictionary: need atoms >= 1, sparsity >= 1, iterations >= 0 and at least "
                         f"atoms patches; got atoms={atoms}, sparsity={sparsity}, iterations={iterations}, "
                         f"{n_patches} patches")
    if initial is None:
        pick = torch.randperm(n_patches, generator=generator)[:atoms].to(x.device)
        d = x[pick].T.clone()
    else:
        d = initial.to(x).clone()
    d = _renew_atoms(d, x, generator)
    errors = []
    for _ in range(iterations):
        codes = omp(d, x, sparsity=sparsity)
        errors.append(representation_error(d, x, codes))
        gram = codes.T @ codes + ridge * torch.eye(atoms, dtype=x.dtype, device=x.device)
        d = torch.linalg.solve(gram, codes.T @ x).T
        d = _renew_atoms(d, x, generator)
    errors.append(representation_error(d, x, omp(d, x, sparsity=sparsity)))
    return d, errors


def _renew_atoms(d: torch.Tensor, x: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Normalize columns; replace columns of (near) zero norm by random normalized patches."""
    norms = d.norm(dim=0)
    bad = torch.nonzero(norms <= 1e-8).flatten()
    if bad.numel():
        pick = torch.randint(0, x.shape[0], (bad.numel(),), generator=generator).to(x.device)
        d = d.clone()
        d[:, bad] = x[pick].T
        norms = d.norm(dim=0)
    return d / norms.clamp_min(1e-30)
