"""``capssim reconstruct``'s checks before the first method runs (issue 34, classes 9, 11 and 12).

* :func:`check_method_options`: every method of the command line parses its ``-p`` options before any
  method runs, so ``-m caps -m dofp-eari -p c1=0.003`` is refused before ``recon/caps.tiff`` is written.
* :func:`check_track_psnr`: ``-p track_psnr=true`` needs a ground truth (``gt.tiff``) and an untiled run.
* :func:`warn_raw_range`: float raw frames outside ``[black, white]``: one warning with the count.
"""

from __future__ import annotations

import logging
from pathlib import Path

from capssim.errors import CapssimError, InputError

log = logging.getLogger("capssim.reconstruct")


def check_method_options(name: str, options: dict, *, shared: bool = False) -> None:
    """Method ``name`` parses and checks ``options`` before any method runs
    (:func:`capssim.reconstruct.option_probe.check_method_options`).

    Raises
    ------
    CapssimError
        The method's own one-line error (an unknown option, a value out of range); an unknown option names
        ``-m NAME`` when several methods share the ``-p`` options (``shared``).
    """
    from capssim.reconstruct.option_probe import check_method_options as probe  # start-up time

    try:
        probe(name, options)
    except CapssimError as exc:
        if shared and "unknown option" in str(exc):
            raise InputError(f"-m {name}", str(exc).rstrip("."), "-p options that every -m method takes",
                             "The -p options go to every method: run the methods in separate commands.") from None
        raise


def check_track_psnr(options: dict, folders: list[Path], *, tiled: bool) -> None:
    """``-p track_psnr=true`` takes effect or is refused: every capture needs its ``gt.tiff`` (read with the
    frames, PSNR per iteration in the record), and the run must be untiled (tiles carry no ground truth)."""
    if "track_psnr" not in options:
        return
    from capssim.captures.capture import read_meta  # start-up time
    from capssim.reconstruct.pipeline.options import coerce_option

    if not coerce_option("track_psnr", options["track_psnr"], bool):
        return
    if tiled:
        raise InputError("-p track_psnr", "true with --tile, --workers or a folder of captures",
                         "an untiled run of one capture (tiles carry no ground truth)",
                         "Leave -p track_psnr out, or reconstruct one capture without --tile.")
    for folder in folders:
        gt = read_meta(folder).get("files", {}).get("gt")
        if not gt or not (Path(folder) / gt).is_file():
            raise InputError("-p track_psnr", f"true for {str(folder)!r}, which has no gt.tiff",
                             "a capture with its ground truth (from capssim simulate or render)",
                             "Leave -p track_psnr out: a real camera's capture cannot be scored.")


def warn_raw_range(folder: Path, kinds: set[str]) -> None:
    """One warning per float raw frame file of ``folder`` with values outside the sensor's
    ``[black_level, white_level]`` (meta.json): its count. Integer frames are clipped by their ADC and
    marked saturated at the white level; float frames carry no saturation mask, so such values are used
    as they are."""
    import numpy as np

    from capssim.captures.capture import read_capture, read_meta  # start-up time
    from capssim.runtime.data_range import warn_out_of_range

    if not _has_float_frames(Path(folder), read_meta(folder), kinds):
        return  # integer frames (the usual case): nothing to warn about, and the frames are read once, by the method
    capture = read_capture(folder, load_gt=False)
    sensor = capture.meta.get("sensor", {})
    low, high = float(sensor.get("black_level", 0.0)), float(sensor.get("white_level", 1.0))
    frames = {"caps": ("caps_raw", capture.caps_raw), "dofp": ("dofp_raw", capture.dofp_raw)}
    for kind in sorted(kinds):
        name, raw = frames.get(kind, (None, None))
        if raw is not None and np.issubdtype(np.asarray(raw).dtype, np.floating):
            warn_out_of_range(f"{Path(folder).name}/{name}", raw, low=low, high=high, unit="the white level",
                              below_means="below the black level", above_means="above the white level",
                              consequence="float frames carry no saturation mask: these values are used as they "
                                          "are (check the sensor's black_level/white_level in meta.json)")


def _has_float_frames(folder: Path, meta: dict, kinds: set[str]) -> bool:
    """Whether a raw frame file of ``kinds`` (``caps``, ``dofp``) is stored as floats, from its TIFF header alone;
    ``True`` when a header cannot be read (the full read then reports the file)."""
    import numpy as np
    import tifffile

    names = {"caps": "caps_raw", "dofp": "dofp_raw"}
    files = meta.get("files") or {}
    quiet = logging.getLogger("tifffile")
    level, quiet.level = quiet.level, logging.CRITICAL  # a probe: read_capture reports a damaged file
    try:
        for kind in sorted(kinds):
            name = files.get(names.get(kind, ""))
            if not name:
                continue
            try:
                with tifffile.TiffFile(folder / name) as tif:
                    if np.issubdtype(np.dtype(tif.series[0].dtype), np.floating):
                        return True
            except Exception:  # noqa: BLE001 - missing or damaged: let read_capture name it
                return True
    finally:
        quiet.setLevel(level)
    return False
