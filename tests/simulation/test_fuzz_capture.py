"""Fuzz suite, the capture reader: mutated ``meta.json`` and odd TIFFs give a valid capture or a one-line error.

A valid 16 px capture is mutated one way per example: a ``meta.json`` field set to another JSON
value (wrong type, null, NaN, inf, huge numbers, lists for objects, objects for lists) or
deleted, the whole ``meta.json`` replaced, or one of its TIFFs replaced by an array of another
shape or dtype, by truncated or corrupted bytes, or by bytes that are not a TIFF. Reading it
(:func:`capssim.captures.capture.read_capture`) and using what was read (raw frames as floats, Bayer
sub-images, homographies; then ``dofp-bilinear`` and one iteration of ``caps``) must succeed or
raise a :class:`~capssim.errors.CapssimError` with a one-line message. The process's address
space is capped (:func:`support.fuzz.address_space_headroom`), so a huge allocation fails here.
"""

from __future__ import annotations

import copy
import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import tifffile
from hypothesis import given
from hypothesis import strategies as st
from support.fuzz import PEAK_GROWTH_LIMIT, address_space_headroom, fuzz_settings, one_line_error, peak_rss_bytes

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import read_capture, write_capture
from capssim.errors import CapssimError
from capssim.reconstruct.registry import reconstruct
from capssim.runtime.resources import MEMORY_LIMIT_ENV
from capssim.simulate import simulate_capture

FILES = ("caps_raw.tiff", "dofp_raw.tiff", "gt.tiff")


@pytest.fixture(scope="module")
def valid(smooth_random_scene, tmp_path_factory) -> Path:
    """A valid 16 px capture (uint16 DN, Gaussian noise), read once; the fuzz works on copies."""
    capture = simulate_capture(smooth_random_scene(16, seed=2), make_sensor("gaussian", sigma=0.01), seed=1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(MEMORY_LIMIT_ENV, "1")
        start = peak_rss_bytes()
        yield write_capture(tmp_path_factory.mktemp("fuzz-capture") / "valid", capture)
    grown = peak_rss_bytes() - start
    assert grown < PEAK_GROWTH_LIMIT, f"the capture fuzz raised the peak memory by {grown / 2**20:.0f} MiB"


def _paths(value, prefix=()) -> list[tuple]:
    """Every key path into a JSON value (lists: their first, a middle and their last item)."""
    out = [prefix]
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, (*prefix, key))
    elif isinstance(value, list) and value:
        for index in sorted({0, len(value) // 2, len(value) - 1}):
            out += _paths(value[index], (*prefix, index))
    return out


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(min_value=-10**30, max_value=10**30),
              st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
              st.sampled_from([0, -1, 1, 2**63, 65535, 1e308, float("nan"), "gaussian", "none", "caps_raw.tiff"])),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=8)


def _set(meta, path: tuple, value, delete: bool):
    if not path:
        return value
    parent = meta
    for key in path[:-1]:
        parent = parent[key]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return meta


def _use(folder: Path) -> None:
    """Read the capture and use it as the reconstruction does: a result or a one-line CapssimError."""
    try:
        capture = read_capture(folder)
        geometry = capture.meta["geometry"]
        assert capture.caps_raw.shape == (4, geometry["raw_height"], geometry["raw_width"])
        capture.caps_float()
        capture.lr_images()
        capture.true_lr_homographies()
        for method, options in (("dofp-bilinear", {}), ("caps", {"iterations": 1})):
            if method == "dofp-bilinear" and capture.dofp_raw is None:
                continue
            reconstruct(capture, method, true_warps=True, **options)
    except Exception as exc:  # noqa: BLE001 - the point: which exceptions come out
        one_line_error(exc)


@fuzz_settings(max_examples=200)
@given(data=st.data())
def test_mutated_meta_json_reads_or_is_a_one_line_error(valid, tmp_path_factory, data):
    meta = json.loads((valid / "meta.json").read_text())
    path = data.draw(st.sampled_from(_paths(meta)), label="path")
    delete = bool(path) and data.draw(st.booleans(), label="delete")
    value = None if delete else data.draw(json_values, label="value")
    mutated = _set(copy.deepcopy(meta), path, value, delete)
    folder = tmp_path_factory.mktemp("meta")
    for name in FILES:
        shutil.copy(valid / name, folder / name)
    (folder / "meta.json").write_text(json.dumps(mutated))  # NaN and Infinity as Python writes them
    with address_space_headroom(3):
        _use(folder)


shapes = st.lists(st.integers(min_value=0, max_value=20), min_size=0, max_size=4).map(tuple)
dtypes = st.sampled_from(["uint8", "uint16", "int16", "int32", "float16", "float32", "float64", "bool", "complex64"])


@st.composite
def odd_tiff_bytes(draw, valid_bytes: bytes) -> bytes:
    """A TIFF of another shape or dtype, a valid one truncated or with bytes overwritten, or not a TIFF."""
    kind = draw(st.sampled_from(["array", "truncated", "overwritten", "noise"]))
    if kind == "array":
        shape, dtype = draw(shapes), draw(dtypes)
        fill = draw(st.sampled_from([0, 1, 65535, -1, float("nan"), float("inf")]))
        with np.errstate(invalid="ignore", over="ignore"):
            array = np.full(shape, fill).astype(dtype)
        from io import BytesIO

        buffer = BytesIO()
        try:
            with warnings.catch_warnings():  # "writing zero-size array to nonconformant TIFF": on purpose
                warnings.simplefilter("ignore")
                tifffile.imwrite(buffer, array, photometric="minisblack", metadata=None)
        except Exception:  # noqa: BLE001 - a shape tifffile cannot write: use the noise instead
            return draw(st.binary(max_size=64))
        return buffer.getvalue()
    if kind == "truncated":
        return valid_bytes[:draw(st.integers(min_value=0, max_value=len(valid_bytes) - 1))]
    if kind == "overwritten":
        out = bytearray(valid_bytes)
        for _ in range(draw(st.integers(min_value=1, max_value=8))):
            out[draw(st.integers(min_value=0, max_value=min(len(out) - 1, 400)))] = draw(st.integers(0, 255))
        return bytes(out)
    return draw(st.binary(max_size=200))


@fuzz_settings(max_examples=200)
@given(data=st.data())
def test_odd_tiffs_read_or_are_a_one_line_error(valid, tmp_path_factory, data):
    name = data.draw(st.sampled_from(FILES), label="file")
    folder = tmp_path_factory.mktemp("tiff")
    for other in (*FILES, "meta.json"):
        shutil.copy(valid / other, folder / other)
    (folder / name).write_bytes(data.draw(odd_tiff_bytes((valid / name).read_bytes()), label="bytes"))
    with address_space_headroom(3):
        _use(folder)


def test_a_forged_huge_tiff_header_is_refused_before_reading(valid, tmp_path):
    """meta.json and the TIFF header agree on 50000 x 50000 raw frames (20 GB) that the file does not hold."""
    folder = tmp_path / "forged"
    shutil.copytree(valid, folder)
    meta = json.loads((folder / "meta.json").read_text())
    side = 50000
    meta["geometry"].update(raw_height=side, raw_width=side, hr_height=2 * side, hr_width=2 * side,
                            sub_height=side // 2, sub_width=side // 2)
    (folder / "meta.json").write_text(json.dumps(meta))
    with tifffile.TiffFile(folder / "caps_raw.tiff", mode="r+b") as tif:
        for page in tif.pages:
            page.tags["ImageWidth"].overwrite(side)
            page.tags["ImageLength"].overwrite(side)
    with tifffile.TiffFile(folder / "caps_raw.tiff") as tif:
        assert tif.series[0].shape == (4, side, side)
    start = peak_rss_bytes()
    with address_space_headroom(3), pytest.raises(CapssimError, match="meta.json geometry: reading caps_raw.tiff"):
        read_capture(folder)
    assert peak_rss_bytes() - start < 256 * 2**20


def test_infinite_extinction_ratio_is_written_as_ideal(smooth_random_scene, tmp_path):
    """inf (an ideal polarizer, as in the analyzer) is stored as null: meta.json stays standard JSON."""
    capture = simulate_capture(smooth_random_scene(16, seed=2), make_sensor("none"), seed=1,
                               extinction_ratio=float("inf"))
    folder = write_capture(tmp_path / "cap", capture)
    text = (folder / "meta.json").read_text()
    assert "Infinity" not in text and json.loads(text)["extinction_ratio"] is None
    json.loads(text, parse_constant=lambda token: pytest.fail(f"non-standard JSON token {token}"))
