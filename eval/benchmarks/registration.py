"""Registration benchmark: the error of the estimated warps against the true ones, and the time, per capture.

Each capture's 16 sub-image homographies are estimated from its Bayer sub-images alone by
:func:`capssim.reconstruct.registration.estimate_lr_homographies` (paper section 3.1) with the
parameters of a named registration mode, and compared with the homographies stored in its
``meta.json`` by :func:`capssim.camera.homography.registration_error_hr_px` (HR pixels). Captures
simulated from a real ground truth can also be compared with their *content* warps: the stored
warps composed with the offsets between the ground truth's analyzer images that
``capssim gt-check --json`` measured (:func:`content_lr_homographies`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from capssim.camera.array_geometry import lr_homographies
from capssim.camera.homography import registration_error_hr_px
from capssim.captures.capture import Capture, read_capture
from capssim.conventions import N_APERTURES
from capssim.errors import InputError
from capssim.reconstruct.registration import estimate_lr_homographies
from capssim.reconstruct.registration.parameters import registration_parameters


def content_lr_homographies(capture: Capture, alignment_matrices) -> np.ndarray:
    """``(16, 3, 3)`` *content* warps of a capture simulated from a real ground truth.

    ``alignment_matrices``: the three ``(3, 3)`` matrices of ``capssim gt-check --json``
    (``alignment_matrices``: where the 45/90/135 deg ground-truth images' content lies relative to the
    0 deg image). Aperture n's content warp is its stored warp composed with that offset.
    """
    g = np.asarray(alignment_matrices, dtype=np.float64)
    if g.shape != (N_APERTURES - 1, 3, 3) or not np.all(np.isfinite(g)):
        raise InputError("alignment_matrices", f"shape {g.shape}", "three finite 3x3 matrices from gt-check --json")
    aperture = capture.aperture_homographies().copy()
    for n in range(1, N_APERTURES):
        aperture[n] = aperture[n] @ g[n - 1]
    return lr_homographies(aperture)


def load_alignment_record(content_alignment) -> dict:
    """A ``capssim gt-check --json`` record given as a dict or a JSON file path; it must hold
    ``alignment_matrices``."""
    record = content_alignment
    if not isinstance(record, dict):
        try:
            record = json.loads(Path(record).read_text())
        except (OSError, ValueError) as exc:
            raise InputError("content_alignment", str(content_alignment),
                             "a readable JSON file written by capssim gt-check --json") from exc
    if "alignment_matrices" not in record:
        raise InputError("content_alignment", "a record without 'alignment_matrices'",
                         "the JSON of capssim gt-check --json")
    return record


def check_alignment_record(record: dict, capture: Capture, label) -> None:
    """The gt-check ``record`` must describe ``capture``'s ground truth: same size, same source, same crop."""
    shape = record.get("shape")
    if shape is not None and tuple(shape) != tuple(capture.hr_shape):
        raise InputError("content_alignment", f"a gt-check record of a {shape[0]}x{shape[1]} ground truth",
                         f"one of the {capture.hr_shape[0]}x{capture.hr_shape[1]} ground truth capture {label} was "
                         "simulated from", "Run capssim gt-check with the capture's --crop.")
    source = capture.meta.get("source") or {}
    if source.get("renderer"):
        raise InputError("content_alignment", f"a gt-check record for the rendered capture {label}",
                         "captures simulated by capssim simulate from a real ground truth",
                         "Leave it out: a rendered capture's stored warps are its content warps.")
    gt, crop = record.get("gt"), record.get("crop")
    if gt is not None and source.get("path") and Path(gt).name != Path(source["path"]).name:
        raise InputError("content_alignment", f"a gt-check record of {gt}",
                         f"one of {source['path']}, the ground truth of {label}",
                         "Run capssim gt-check on the capture's ground truth.")
    if gt is not None and source.get("path") and crop != source.get("crop"):
        raise InputError("content_alignment", f"a gt-check record with --crop {crop}",
                         f"--crop {source.get('crop')}, the crop capture {label} was simulated with")


def _bench_row(capture: Capture, label: str, parameters, *, device, matrices) -> dict:
    """One capture registered and scored: errors in HR px against the true (and content) warps."""
    images, saturated = capture.lr_images()
    t0 = time.perf_counter()
    result = estimate_lr_homographies(images.astype(np.float32), hr_shape=capture.hr_shape, saturated=saturated,
                                      parameters=parameters, device=device)
    elapsed = time.perf_counter() - t0
    true = capture.true_lr_homographies()
    err = registration_error_hr_px(result.lr_homographies, true, capture.hr_shape)
    row = {"capture": label, "median_hr_px": float(np.median(err)), "max_hr_px": float(err.max()),
           "per_aperture_hr_px": [float(v) for v in err.reshape(N_APERTURES, 4).mean(1)], "time_s": elapsed}
    if matrices is not None:
        content = content_lr_homographies(capture, matrices)
        err_c = registration_error_hr_px(result.lr_homographies, content, capture.hr_shape)
        gap = registration_error_hr_px(content, true, capture.hr_shape)
        row.update({"content_median_hr_px": float(np.median(err_c)), "content_max_hr_px": float(err_c.max()),
                    "content_vs_true_median_hr_px": float(np.median(gap))})
    return row


def run_registration_bench(captures, *, mode: str = "local-correlation", content_alignment=None,
                           stokes_weight: float | None = None, device="cpu") -> dict:
    """Registration error (HR px) and time of each capture.

    Parameters
    ----------
    captures
        capture folders (paths) or :class:`~capssim.captures.capture.Capture` objects with true homographies
        (simulated or rendered).
    mode
        a :data:`capssim.reconstruct.registration.parameters.REGISTRATION_MODES` name.
    content_alignment
        a ``capssim gt-check --json`` record (path or dict) of the ground truth the captures were
        simulated from; rows then also give the error against the content warps
        (:func:`content_lr_homographies`).
    stokes_weight
        overrides the mode's weight of the Stokes-consistency term (None: the mode's).
    device
        torch device of the registration.

    Returns
    -------
    dict
        ``mode``, ``device``, ``parameters`` (the registration parameters used) and ``rows``: one per
        capture with ``capture``, ``median_hr_px`` / ``max_hr_px`` over the 16 images,
        ``per_aperture_hr_px`` (4 means), ``time_s``; with ``content_alignment`` also
        ``content_median_hr_px``, ``content_max_hr_px`` and ``content_vs_true_median_hr_px``.
    """
    parameters = registration_parameters(mode)
    if stokes_weight is not None:
        parameters = dataclasses.replace(parameters, stokes_weight=stokes_weight)
    parameters.validate()
    record = None if content_alignment is None else load_alignment_record(content_alignment)
    labelled = [(c, str(c.path) if c.path is not None else f"capture {i}") if isinstance(c, Capture)
                else (read_capture(c, load_gt=False), str(c)) for i, c in enumerate(captures)]
    if record is not None:
        for capture, label in labelled:
            check_alignment_record(record, capture, label)
    matrices = None if record is None else record["alignment_matrices"]
    rows = [_bench_row(capture, label, parameters, device=device, matrices=matrices) for capture, label in labelled]
    return {"mode": mode, "device": str(device), "parameters": dataclasses.asdict(parameters), "rows": rows}


def format_registration_bench(result: dict) -> str:
    """The table of :func:`run_registration_bench`'s result: one line per capture (errors in HR px, time in s)."""
    lines = [f"{'capture':<40} {'median':>8} {'max':>8} {'ap0':>7} {'ap1':>7} {'ap2':>7} {'ap3':>7} {'time s':>7}"]
    for r in result["rows"]:
        lines.append(f"{r['capture']:<40} {r['median_hr_px']:8.4f} {r['max_hr_px']:8.4f} "
                     + " ".join(f"{v:7.4f}" for v in r["per_aperture_hr_px"]) + f" {r['time_s']:7.2f}")
        if "content_median_hr_px" in r:
            lines.append(f"{'  against the content warps':<40} {r['content_median_hr_px']:8.4f} "
                         f"{r['content_max_hr_px']:8.4f}   (content vs stored warps: "
                         f"{r['content_vs_true_median_hr_px']:.4f})")
    return "\n".join(lines)
