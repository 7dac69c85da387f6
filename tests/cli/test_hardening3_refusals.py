"""Issue 60 ("Hardening, third round"): inputs refused up front, in one line that names the real cause.

Every row names its item of the issue. A refused command exits 2 with exactly one ``error:`` line and no
traceback, holding the row's fragments, before any output folder is created (``absent``) and before the
command's work starts (``forbid``: the function that would do it is replaced by one that fails the test).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
from support.fuzz import refused_before_work, run_cli

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.simulate import simulate_capture

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

SUITE = "name: tiny\nmethods: [dofp-bilinear]\nscenes:\n  - {name: tex, source: synthetic, size: 32}\n"


def _suite(root: Path) -> None:
    (root / "tiny.yaml").write_text(SUITE)


def _capture(side: int = 32, *, name: str = "cap", seed: int = 1) -> Callable[[Path], None]:
    def setup(root: Path) -> None:
        rng = np.random.default_rng(0)
        gt = (0.2 + 0.5 * rng.random((12, side, side))).astype(np.float32)
        write_capture(root / name, simulate_capture(gt, make_sensor("gaussian", sigma=0.01), seed=seed))
    return setup


def _cache_file(root: Path) -> None:
    _suite(root)
    (root / "cachefile").write_text("not a folder\n")


def _wide_psf_dataset(root: Path) -> None:
    """A ground-truth source of 64 px samples and a PSF of sigma 20 HR px (a 141 px kernel)."""
    import cv2

    rng = np.random.default_rng(0)
    (root / "gt").mkdir()
    for angle in (0, 45, 90, 135):
        cv2.imwrite(str(root / "gt" / f"{angle}.png"), (rng.random((80, 80, 3)) * 200).astype(np.uint8))
    (root / "ds.yaml").write_text("name: wide\nseed: 0\nsamples: 2\ndefaults: {psf_sigma_hr_px: 20}\n"
                                  "sources:\n  - {gt: gt, size: 64}\n")


def _rig_file(gain=(1.0, 1.0, 1.0, 1.0), constant: float = 1.0) -> Callable[[Path], None]:
    """A capture, a 12-channel ground truth and ``rig.json``: the ideal rig with ``gain`` and vignetting ``constant``."""
    def setup(root: Path) -> None:
        import json

        import cv2

        from capssim.camera.rig import RigModel

        _capture()(root)
        (root / "gt").mkdir()
        for angle in (0, 45, 90, 135):
            cv2.imwrite(str(root / "gt" / f"{angle}.png"), np.full((32, 32, 3), 100, np.uint8))
        rig = RigModel().to_dict()
        rig["gain"] = list(gain)
        rig["vignetting"]["coefficients"] = [[constant] + row[1:] for row in rig["vignetting"]["coefficients"]]
        (root / "rig.json").write_text(json.dumps({"format": "capssim-rig", "version": 1, "rig": rig}))
    return setup


def _train(model: str, kind: str) -> Callable[[Path], None]:
    def setup(root: Path) -> None:
        (root / "dataset.yaml").write_text("seed: 0\n")
        (root / "train.yaml").write_text(f"model: {model}\ninput: {kind}\ndata: {{dataset: dataset.yaml}}\n")
    return setup


@dataclass(frozen=True)
class Row:
    item: int
    name: str
    args: list  #: the command line; ``{root}`` is the test's folder
    fragments: tuple = ()  #: words the one error line holds
    forbid: tuple = ()  #: "module:function" of the command's work (one or several): it must not run
    absent: tuple = ()  #: paths under the test's folder that must not exist afterwards
    env: dict = field(default_factory=dict)
    setup: Callable[[Path], None] = field(default=lambda root: None)
    not_in: tuple = ()  #: words the error line must not hold (a fix that would be refused in turn)


BAD_ADDRESSES = [("bogus", "'bogus' (no HOST:PORT)"), ("", "got nothing"), ("localhost:abc", "(port 'abc')"),
                 ("tcp://:8786", "(no HOST:PORT)"), ("foo://host:8786", "(scheme 'foo')"),
                 ("localhost:99999", "(port '99999')")]
SCHEDULER_COMMANDS = [
    ("reconstruct", ["reconstruct", "{root}/cap", "-m", "caps"], ("cap/recon",), _capture()),
    ("bench suite", ["bench", "suite", "{root}/tiny.yaml", "-o", "{root}/out"], ("out",), _suite),
    ("bench budget", ["bench", "budget", "{root}/tiny.yaml", "-o", "{root}/out"], ("out",), _suite),
    ("dataset", ["dataset", str(EXAMPLES / "dataset-small.yaml"), "-o", "{root}/out"], ("out",), lambda root: None),
]
TRAIN = ["train", "{root}/train.yaml", "-o", "{root}/run"]
TRAINER = ("capssim.reconstruct.training.trainer:train",)
#: registration (the first work of a tiled run) and the Dask cluster of --workers
TILED_WORK = ("capssim.reconstruct.tiles.run:frame_warps", "capssim.reconstruct.tiles.distributed:DaskSession")
BIG = _capture(256)  # 0.5 GiB untiled: --memory-gb 0.45 makes tiles
RECON = ["reconstruct", "{root}/cap", "-m", "caps"]

ROWS = [
    *[Row(3, f"{command} --scheduler {address!r}", [*args, "--scheduler", address],
          ("--scheduler", shown, "HOST:PORT", "tcp://localhost:8786"), ("distributed:Client",),
          absent, setup=setup)
      for command, args, absent, setup in SCHEDULER_COMMANDS for address, shown in BAD_ADDRESSES],
    Row(3, "train a denoiser of 4 channels", TRAIN, ("'model.channels'", "got 4", "expected 12", "noisy-gt"),
        TRAINER, ("run",), setup=_train("{network: denoiser, channels: 4}", "noisy-gt")),
    Row(3, "train a denoiser of 1 channel", TRAIN, ("'model.channels'", "got 1", "expected 12"),
        TRAINER, ("run",), setup=_train("{network: denoiser, channels: 1}", "noisy-gt")),
    Row(3, "train an edsr of 12 channels", TRAIN, ("'model.channels'", "got 12", "expected 3", "aperture"),
        TRAINER, ("run",), setup=_train("{network: edsr, channels: 12}", "aperture")),
    Row(4, "design --depth-m 0.001 (inside the focal length)", ["design", "--depth-m", "0.001"],
        ("--depth-m", "got 0.001", "beyond the focal length (35 mm", "Use --depth-m")),
    Row(4, "design --depth-m 0.035 (at the focal length)", ["design", "--depth-m", "0.035"],
        ("--depth-m", "got 0.035", "beyond the focal length")),
    Row(4, "design --depth-m 0.2 (views do not overlap)", ["design", "--depth-m", "0.2"],
        ("--depth-m", "got 0.2", "views overlap", "more than 0.2848 m", "smaller --baseline-mm")),
    Row(4, "design --baseline-mm 1e6", ["design", "--baseline-mm", "1e6", "--json"],
        ("--depth-m", "views overlap", "--baseline-mm 1e+06")),
    Row(4, "design --focal-length-mm 1e308", ["design", "--focal-length-mm", "1e308"],
        ("--depth-m", "beyond the focal length", "shorter --focal-length-mm")),
    # item 5: a refusal of --tile or --memory-gb names the option that makes the margin
    Row(5, "--tile 64 -p search_radius=1000000", [*RECON, "--tile", "64", "-p", "search_radius=1000000"],
        ("search_radius:", "1e+06", "at most 128", "128x128"), TILED_WORK, setup=_capture(128)),
    Row(5, "--tile 64 -p block=200 (past the frame)", [*RECON, "--tile", "64", "-p", "block=200"],
        ("block: got 200", "at most the 128x128 frame's smaller side"), TILED_WORK, setup=_capture(128)),
    Row(5, "--tile 64 -p block=100 (a margin wider than the tile)", [*RECON, "--tile", "64", "-p", "block=100"],
        ("block: got 100 with --tile 64", "128 HR px", "block 100 +", "Use --tile 128 or more", "smaller -p block"),
        TILED_WORK, setup=_capture(128)),
    Row(5, "--tile 64 -p search_radius=60", [*RECON, "--tile", "64", "-p", "search_radius=60"],
        ("search_radius: got 60 with --tile 64", "search_radius 60", "smaller -p search_radius"), TILED_WORK,
        setup=_capture(128)),
    Row(5, "--tile 64 -p cagf_radius=1000", [*RECON, "--tile", "64", "-p", "cagf_radius=1000"],
        ("cagf_radius: got 1000", "[1, 32]"), TILED_WORK, setup=_capture(128)),
    Row(5, "--tile 64 -p psf_sigma=100", [*RECON, "--tile", "64", "-p", "psf_sigma=100"],
        ("psf_sigma:", "128x128 image"), TILED_WORK, setup=_capture(128)),
    Row(5, "--memory-gb 0.45 -p search_radius=1000000", [*RECON, "--memory-gb", "0.45", "-p", "search_radius=1000000"],
        ("search_radius:", "at most 256"), TILED_WORK, setup=BIG),
    Row(5, "--memory-gb 0.45 -p block=200", [*RECON, "--memory-gb", "0.45", "-p", "block=200"],
        ("--memory-gb", "block 200 +", "or a smaller -p block"), TILED_WORK, setup=BIG),
    Row(5, "--tile 63", [*RECON, "--tile", "63"], ("--tile: got 63", ">= 64"), TILED_WORK, setup=_capture(128)),
    # item 7: checks that came late
    Row(7, "--memory-gb 0.45 -w 2 (no cluster is started)", [*RECON, "--memory-gb", "0.45", "-w", "2"],
        ("--memory-gb", "2 tile(s)", "fewer --workers"), TILED_WORK, setup=BIG),
    Row(7, "bench suite --cache FILE", ["bench", "suite", "{root}/tiny.yaml", "-o", "{root}/out", "--cache",
                                        "{root}/cachefile"], ("--cache", "an existing file", "a folder path"),
        ("capssim.eval.benchmarks.suite:run_suite",), ("out",), setup=_cache_file),
    Row(7, "bench budget --cache FILE", ["bench", "budget", "{root}/tiny.yaml", "-o", "{root}/out", "--cache",
                                         "{root}/cachefile"], ("--cache", "an existing file", "a folder path"),
        ("capssim.eval.error_budget.runner:run_budget",), ("out",), setup=_cache_file),
    Row(7, "dataset --dry-run with a PSF wider than the samples", ["dataset", "{root}/ds.yaml", "--dry-run"],
        ("psf_sigma_hr_px", "141", "at most 64"), setup=_wide_psf_dataset),
    Row(7, "dataset with a PSF wider than the samples", ["dataset", "{root}/ds.yaml", "-o", "{root}/out"],
        ("psf_sigma_hr_px", "141", "at most 64"), ("capssim.dataset.generate:generate_dataset",), ("out",),
        setup=_wide_psf_dataset),
    # item 8: a gain past any camera's response is refused naming the gain
    Row(8, "simulate --rig with a gain of 1e300", ["simulate", "{root}/gt", "-o", "{root}/out", "--rig",
                                                   "{root}/rig.json"],
        ("--rig", "rig gain", "1e+300", "[0.001, 1000]"), ("capssim.simulate:simulate_capture",), ("out",),
        setup=_rig_file((1e300, 1, 1, 1))),
    Row(8, "reconstruct --calibration with a gain of 1e300", [*RECON, "--calibration", "{root}/rig.json"],
        ("--calibration", "rig gain", "1e+300"), ("capssim.reconstruct.registry:reconstruct",), ("cap/recon",),
        setup=_rig_file((1e300, 1, 1, 1))),
    Row(8, "reconstruct --calibration with a gain of 1001", [*RECON, "--calibration", "{root}/rig.json"],
        ("rig gain", "1001", "[0.001, 1000]"), ("capssim.reconstruct.registry:reconstruct",), ("cap/recon",),
        setup=_rig_file((1, 1, 1001, 1))),
    Row(8, "simulate --rig with a flat field of 2000", ["simulate", "{root}/gt", "-o", "{root}/out", "--rig",
                                                        "{root}/rig.json"],
        ("vignetting", "2e+03", "<= 1000"), ("capssim.simulate:simulate_capture",), ("out",),
        setup=_rig_file(constant=2000.0)),
    Row(8, "bench suite with a scene rig gain of 1e300", ["bench", "suite", "{root}/gain.yaml", "-o", "{root}/out"],
        ("gain.yaml", "rig.gain", "1e+300"), ("capssim.eval.benchmarks.suite:run_suite",), ("out",),
        setup=lambda root: (root / "gain.yaml").write_text(SUITE.replace(
            "size: 32}", "size: 32, rig: {preset: realistic, gain: [1.0e+300, 1, 1, 1]}}"))),
    # item 9: smaller ones
    Row(9, "calibrate -o an existing folder", ["calibrate", "{root}/cap", "-o", "{root}/cap"],
        ("-o/--output", "an existing folder", "a file path"), ("capssim.reconstruct.calibration:calibrate_captures",),
        setup=_capture(), not_in=("--overwrite",)),
    Row(9, "calibrate -o an existing file still suggests --overwrite", ["calibrate", "{root}/cap", "-o",
                                                                        "{root}/cap/meta.json"],
        ("-o/--output", "--overwrite"), ("capssim.reconstruct.calibration:calibrate_captures",), setup=_capture()),
    Row(9, "simulate a 64x1 ground truth", ["simulate", "{root}/gt.tiff", "-o", "{root}/out"],
        ("gt: got size 64x1", "at least 16x16"), ("capssim.simulate:simulate_capture",), ("out",),
        setup=lambda root: __import__("tifffile").imwrite(root / "gt.tiff", np.full((12, 64, 1), 0.5, np.float32)),
        not_in=("crop",)),
]


@pytest.mark.parametrize("row", ROWS, ids=lambda r: f"item{r.item}-{r.name}")
def test_refused_up_front_in_one_line(row, tmp_path, capsys, monkeypatch):
    logging.disable(logging.CRITICAL)  # the set-up's own log lines (simulate, write) are not the command's
    try:
        row.setup(tmp_path)
    finally:
        logging.disable(logging.NOTSET)
    capsys.readouterr()
    refused_before_work(row.args, tmp_path, capsys, monkeypatch, fragments=row.fragments, forbid=row.forbid,
                        env=row.env, not_in=row.not_in, absent=row.absent)


def test_well_formed_scheduler_addresses_pass_the_check():
    from capssim.dataset.generate import check_scheduler_address

    for address in (None, "localhost:8786", "tcp://10.0.0.1:8786", "tls://host.example:1", "[::1]:8786",
                    "ws://h:65535", " tcp://host:8786 "):
        check_scheduler_address(address)


def test_the_matching_channel_counts_load(tmp_path):
    from capssim.reconstruct.training.config import load_train_config

    for model, kind, channels in (("denoiser", "noisy-gt", 12), ("edsr", "aperture", 3)):
        _train(f"{{network: {model}, channels: {channels}}}", kind)(tmp_path)
        assert load_train_config(tmp_path / "train.yaml").network_params["channels"] == channels


def test_design_at_the_edge_of_the_overlap():
    """Just beyond the depth where the views start to overlap every quantity is finite and positive; just
    inside it the command refuses (the bound is the formula's, not a constant)."""
    from capssim.camera.design import DesignInputs, system_design
    from capssim.errors import InputError

    edge = 40.0 * (35.0 / 4.8e-3) / 1024 * 1e-3  # B f_P / min(N_x, N_y), metres
    d = system_design(DesignInputs(depth_m=edge * 1.001))
    assert 0 < d["overlap_height_m"] < d["overlap_width_m"] and 0 < d["fov_v_deg"] < d["fov_h_deg"] < 180
    with pytest.raises(InputError, match="views overlap"):
        system_design(DesignInputs(depth_m=edge * 0.999))


def test_resuming_a_folder_of_captures_redoes_an_empty_tiff(tmp_path, capsys, monkeypatch):
    """Item 9: recon/METHOD.json of the same job beside an empty METHOD.tiff is not a finished frame."""
    (tmp_path / "many").mkdir()
    for name in ("a", "b"):
        _capture(name=name)(tmp_path / "many")
    args = ["reconstruct", tmp_path / "many", "-m", "dofp-bilinear"]
    assert run_cli(args, capsys, monkeypatch)[0] == 0
    (tmp_path / "many" / "b" / "recon" / "dofp-bilinear.tiff").write_bytes(b"")
    status, text = run_cli(args, capsys, monkeypatch)
    assert status == 0, text
    assert "a: dofp-bilinear already finished" in text and "b: dofp-bilinear already finished" not in text, text
    import tifffile

    assert tifffile.imread(tmp_path / "many" / "b" / "recon" / "dofp-bilinear.tiff").shape == (12, 32, 32)


def test_cagf_radius_refusal_suggests_a_radius_the_image_takes():
    """Item 9: on sub-images smaller than the paper's radius 4 the fix names one that is in range."""
    import torch

    from capssim.errors import InputError
    from capssim.reconstruct.model.cagf import pairwise_confidence

    with pytest.raises(InputError) as small:
        pairwise_confidence(torch.rand(3, 2, 2), radius=5)
    assert "[1, 2]" in str(small.value) and "cagf_radius=2" in str(small.value), small.value
    with pytest.raises(InputError) as large:
        pairwise_confidence(torch.rand(3, 8, 8), radius=9)
    assert "The paper uses 4" in str(large.value), large.value


def test_gains_within_the_bound_load():
    from capssim.camera.rig import RigModel

    assert RigModel(gain=np.array([0.001, 1.0, 999.0, 1000.0])).gain.max() == 1000.0


def test_evaluate_warns_of_a_ground_truth_far_above_full_scale(tmp_path, capsys, monkeypatch):
    """Item 9: a ground truth of 1e30 is scored as it is, with one warning that says PSNR means nothing there."""
    import tifffile

    _capture()(tmp_path)
    assert run_cli(["reconstruct", tmp_path / "cap", "-m", "dofp-bilinear"], capsys, monkeypatch)[0] == 0
    status, text = run_cli(["evaluate", tmp_path / "cap"], capsys, monkeypatch)
    assert status == 0 and "above twice full scale" not in text, text  # a ground truth on [0, 1]: no warning
    gt = tifffile.imread(tmp_path / "cap" / "gt.tiff")
    gt[:, :4, :4] = 1e30
    tifffile.imwrite(tmp_path / "cap" / "gt.tiff", gt)
    status, text = run_cli(["evaluate", tmp_path / "cap"], capsys, monkeypatch)
    warnings = [line for line in text.splitlines() if line.startswith("WARNING") and "twice full scale" in line]
    assert status == 0 and len(warnings) == 1, text
    assert "192 of 12288 values" in warnings[0] and "1e+30" in warnings[0] and "PSNR" in warnings[0], warnings


def test_calibrate_warns_of_captures_from_another_camera(tmp_path, caplog):
    """Item 9: a flat field of one rig with a polarizer capture of another: one warning naming both; one rig: none."""
    import json
    import logging

    from capssim.camera.rig import RigModel
    from capssim.reconstruct.calibration.calibrate import load_calibration_set

    for seed, (name, target, rig) in enumerate((("flat", {"target": "flat", "level": 0.4}, None),
                              ("sweep", {"target": "polarizer", "level": 0.4, "polarizer_deg": 0.0}, None),
                              ("other", {"target": "polarizer", "level": 0.4, "polarizer_deg": 60.0},
                               RigModel(gain=np.array([1.2, 0.9, 1.0, 1.0])).to_dict()))):
        _capture(name=name, seed=seed)(tmp_path)
        meta = json.loads((tmp_path / name / "meta.json").read_text())
        meta["calibration"] = target
        if rig is not None:
            meta["rig"] = rig
            meta["setup"].pop("rig")  # derived from the top level
        (tmp_path / name / "meta.json").write_text(json.dumps(meta))
    with caplog.at_level(logging.WARNING):
        load_calibration_set([tmp_path / "flat", tmp_path / "sweep"])
    assert not [r for r in caplog.records if "another camera" in r.getMessage()]
    with caplog.at_level(logging.WARNING):
        load_calibration_set([tmp_path / "flat", tmp_path / "sweep", tmp_path / "other"])
    warned = [r.getMessage() for r in caplog.records if "another camera" in r.getMessage()]
    assert len(warned) == 1 and "1 of 3 captures" in warned[0] and str(tmp_path / "other") in warned[0], warned
