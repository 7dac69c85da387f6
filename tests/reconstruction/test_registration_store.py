"""Register once (issue 20): a capture's estimated warps are stored with it and reused."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from capssim.captures.capture import read_capture
from capssim.files.imageio import read_tiff, write_tiff
from capssim.reconstruct.model import observation_model
from capssim.reconstruct.registration import store as registration_store
from capssim.reconstruct.registry import RunContext, StageTimer


@pytest.fixture
def estimator(fake_registration):
    """The registration replaced by a counting fake (a 0.25 px shift of aperture 1)."""
    return fake_registration(luminance="binomial", warnings=["a warning"])


def _geometry(path, mode="local-correlation", *, reuse=True, true_warps=False):
    capture = read_capture(path, load_gt=False)
    context = RunContext(device=torch.device("cpu"), timer=StageTimer(), true_warps=true_warps, registration=mode,
                         reuse_registration=reuse)
    images, saturated = capture.lr_images()
    return observation_model.method_geometry(capture, context, images=images, saturated=saturated)


def test_second_call_reuses_the_stored_warps(small_capture_dir, estimator):
    geometry, first = _geometry(small_capture_dir)
    assert len(estimator) == 1 and first["store"] == "computed" and first["reused_from"] is None
    stored = sorted((small_capture_dir / "registration").glob("*.json"))
    assert [p.name for p in stored] == [f"local-correlation-{first['key'][:16]}.json"]
    assert first["stored_in"] == str(stored[0])
    content = json.loads(stored[0].read_text())
    assert content["identity"]["mode"] == "local-correlation" and content["identity"]["parameters"]["model"]
    again, second = _geometry(small_capture_dir)
    assert len(estimator) == 1, "the second call registered again"
    assert second["store"] == "reused" and second["reused_from"] == str(stored[0])
    np.testing.assert_array_equal(again.aperture_homographies, geometry.aperture_homographies)
    assert geometry.aperture_homographies[1, 0, 2] == 0.25
    assert second["time_s"] == first["time_s"] and second["warnings"] == ["a warning"]


def test_stored_warnings_are_logged_once_per_process(small_capture_dir, estimator, monkeypatch, caplog):
    _geometry(small_capture_dir)  # computed: the registration logs its own warnings
    with caplog.at_level(logging.WARNING):
        _geometry(small_capture_dir)
    assert "a warning" not in caplog.text
    monkeypatch.setattr(registration_store, "_repeated_warnings", set())  # as in a later run
    with caplog.at_level(logging.WARNING):
        for _ in range(2):
            _, record = _geometry(small_capture_dir)
    assert caplog.text.count("a warning (stored registration)") == 1 and record["warnings"] == ["a warning"]


def test_changed_raw_file_in_place_invalidates(small_capture_dir, estimator):
    _, first = _geometry(small_capture_dir)
    raw = read_tiff(small_capture_dir / "caps_raw.tiff")
    raw.flat[5] = raw.flat[5] + 3
    write_tiff(small_capture_dir / "caps_raw.tiff", raw)
    _, second = _geometry(small_capture_dir)
    assert len(estimator) == 2 and second["key"] != first["key"]
    assert len(list((small_capture_dir / "registration").glob("*.json"))) == 2


def test_other_mode_registers_again_and_both_are_kept(small_capture_dir, estimator):
    _geometry(small_capture_dir, "local-correlation")
    _, record = _geometry(small_capture_dir, "binomial-luminance")
    assert len(estimator) == 2 and record["store"] == "computed"
    assert estimator[1].luminance == "binomial"
    _, record = _geometry(small_capture_dir, "local-correlation")
    _, record2 = _geometry(small_capture_dir, "binomial-luminance")
    assert len(estimator) == 2 and record["store"] == record2["store"] == "reused"


def test_true_warps_and_no_reuse(small_capture_dir, estimator):
    _, record = _geometry(small_capture_dir, true_warps=True)
    assert estimator == [] and "store" not in record and not (small_capture_dir / "registration").exists()
    _geometry(small_capture_dir)
    _, record = _geometry(small_capture_dir, reuse=False)
    assert len(estimator) == 2 and record["store"] == "computed"


def test_corrupt_or_foreign_store_file_is_replaced(small_capture_dir, estimator, caplog):
    _, first = _geometry(small_capture_dir)
    path = small_capture_dir / "registration" / f"local-correlation-{first['key'][:16]}.json"
    path.write_text("{not json")
    with caplog.at_level(logging.WARNING):
        _, record = _geometry(small_capture_dir)
    assert len(estimator) == 2 and record["store"] == "computed" and "ignoring" in caplog.text
    content = json.loads(path.read_text())
    content["identity"]["input_sha256"] = "0" * 64
    path.write_text(json.dumps(content))
    _, record = _geometry(small_capture_dir)
    assert len(estimator) == 3 and record["store"] == "computed"
    _, record = _geometry(small_capture_dir)
    assert len(estimator) == 3 and record["store"] == "reused"


def test_read_only_capture_computes_without_storing(small_capture_dir, estimator, monkeypatch, caplog):
    def refuse(path, obj):
        raise PermissionError(13, "Read-only file system", str(path))

    monkeypatch.setattr(registration_store, "atomic_write_json", refuse)
    monkeypatch.setattr(registration_store, "_warned_read_only", set())
    with caplog.at_level(logging.WARNING):
        for _ in range(3):
            _, record = _geometry(small_capture_dir)
            assert record["store"] == "computed, not stored" and record["stored_in"] is None
    assert len(estimator) == 3
    assert caplog.text.count("cannot write in") == 1


def test_in_memory_capture_computes(small_capture_dir, estimator):
    capture = read_capture(small_capture_dir, load_gt=False)
    capture.path = None
    context = RunContext(device=torch.device("cpu"), timer=StageTimer())
    images, saturated = capture.lr_images()
    for _ in range(2):
        _, record = observation_model.method_geometry(capture, context, images=images, saturated=saturated)
    assert len(estimator) == 2 and record["store"] == "computed, not stored"


def test_key_covers_input_mode_parameters_and_code():
    from capssim.reconstruct.registration.parameters import registration_parameters

    images = np.zeros((16, 8, 8), np.float32)
    sat = np.zeros((16, 8, 8), bool)
    base = registration_store.registration_identity(images, sat, (32, 32), mode="local-correlation",
                                                    parameters=registration_parameters("local-correlation"))
    images2 = images.copy()
    images2[3, 2, 1] = 1e-6
    sat2 = sat.copy()
    sat2[0, 0, 0] = True
    params = registration_parameters("local-correlation")
    variants = [
        registration_store.registration_identity(images2, sat, (32, 32), mode="local-correlation", parameters=params),
        registration_store.registration_identity(images, sat2, (32, 32), mode="local-correlation", parameters=params),
        registration_store.registration_identity(images, sat, (32, 32), mode="local-correlation",
                                                 parameters=params.replace(max_iterations=59)),
        registration_store.registration_identity(images, sat, (32, 32), mode="ri-luminance", parameters=params),
    ]
    assert len({base["key"], *(v["key"] for v in variants)}) == 5
    assert len(base["code_sha256"]) == 64
    same = registration_store.registration_identity(images.copy(), sat.copy(), (32, 32), mode="local-correlation",
                                                    parameters=registration_parameters("local-correlation"))
    assert same == base


def test_cli_two_methods_register_once(small_capture_dir, estimator):
    from capssim.cli import app

    result = CliRunner().invoke(app, ["reconstruct", str(small_capture_dir), "-m", "caps-no-nlstr", "-m", "caps",
                                      "--iterations", "1", "--no-progress", "--threads", "1"])
    assert result.exit_code == 0, result.output
    assert len(estimator) == 1
    assert result.output.count("registration (local-correlation): computed in") == 1
    assert result.output.count("registration (local-correlation): reused") == 1
    records = [json.loads((small_capture_dir / "recon" / f"{m}.json").read_text()) for m in ("caps-no-nlstr", "caps")]
    assert [r["registration"]["store"] for r in records] == ["computed", "reused"]
    assert records[1]["registration"]["reused_from"] == records[0]["registration"]["stored_in"]
