"""Design maps (``capssim bench map``, issue 56): the physics of the apertures' phases, a cell against a direct
run, resume, serial against Dask, and the spec's validation naming every bad key and value."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from capssim.camera.camera_setup import CameraSetup
from capssim.camera.homography import registration_error_hr_px
from capssim.camera.psf import DEFAULT_PSF
from capssim.camera.sensor import make_sensor
from capssim.cli import app
from capssim.eval.benchmarks.results import results_text
from capssim.eval.evaluate import CaptureScorer
from capssim.eval.maps.cells import MapCaptureFactory, cell_scene, perturbed_warps
from capssim.eval.maps.margins import cell_margin
from capssim.eval.maps.report import write_map_report
from capssim.eval.maps.spec import check_map, depth_params, load_map
from capssim.eval.maps.sweep import run_map
from capssim.eval.maps.theory import local_poses, regular_offsets, sampling_conditioning
from capssim.eval.synthetic import synthetic_scene
from capssim.files.schema import ConfigError
from capssim.reconstruct.registry import reconstruct
from capssim.simulate import PoseRanges, simulate_capture

#: a Siemens star at the apertures' regular offsets 0 (one phase) and 1 HR px (half a raw pixel), true warps;
#: caps-naive upsamples each aperture alone (each polarization channel is seen by one aperture only), and
#: caps-no-nlstr fuses the four through the confidence-guided data term
PHASE_MAP = {
    "name": "phase-test",
    "scene": {"name": "star", "source": "synthetic", "generator": "star", "size": 96, "cycles": 24},
    "methods": [{"name": "caps-naive", "true_warps": True}, {"name": "caps-no-nlstr", "true_warps": True},
                "dofp-bilinear"],
    "axes": {"offset_px": [0, 1]},
    "fixed": {"sigma": 0.005},
    "seeds": [0],
}
#: a small map of random poses (shift_max), estimated warps, a noise axis
SHIFT_MAP = {
    "name": "shift-test",
    "scene": {"name": "texture", "source": "synthetic", "generator": "texture", "size": 48},
    "methods": ["caps-naive", "dofp-bilinear"],
    "axes": {"shift_max": [0, 1.0], "sigma": [0.01]},
    "seeds": [0],
}


def _write(tmp_path: Path, spec: dict, name: str = "map.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(spec))
    return path


def _stable(path: Path) -> list[dict]:
    """The lines of a map.jsonl without what differs from run to run (times, worker, timestamps, paths)."""
    drop = {"wall_time_s", "stages_s", "peak_rss_mb", "peak_rss_delta_mb", "cuda_peak_mb", "worker", "finished",
            "environment", "capture_info", "registration", "reused_registration_s", "recon", "capture"}
    return [{k: v for k, v in json.loads(line).items() if k not in drop} for line in path.read_text().splitlines()]


@pytest.fixture(scope="module")
def phase_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("phase")
    spec = load_map(_write(out, PHASE_MAP, "phase.yaml"))
    return run_map(spec, out / "run", threads=1)


def test_zero_offsets_carry_no_sr_information_and_half_pixel_the_most():
    kernel = DEFAULT_PSF.kernel()
    fractions = {}
    for d in (0.0, 0.25, 0.5, 1.0, 1.5, 2.0):
        cond = sampling_conditioning(local_poses(regular_offsets(d), (64, 64)), kernel)
        fractions[d] = cond["resolved_fraction"]
        if d == 0.0:
            assert cond["sigma_min_rel"] < 1e-12 and cond["condition"] == float("inf")
    assert fractions[0.0] == pytest.approx(0.25)  # the four apertures repeat one: rank N / 4
    assert max(fractions, key=fractions.get) == 1.0  # half a raw pixel resolves the most


def test_map_shows_the_phase_physics_on_a_star(phase_run):
    recs = {(r["axes"]["offset_px"], r["method"]): r for r in phase_run.records}
    assert all(r["status"] == "ok" for r in recs.values())
    mag = {k: r["metrics"]["mtf_magnification_hv"] for k, r in recs.items()}
    # co-phased apertures: fusing them resolves no more than upsampling one aperture
    assert mag[0.0, "caps-no-nlstr"] <= mag[0.0, "caps-naive"] + 1e-9
    # at half-pixel phases the fused array resolves more than at one phase
    assert mag[1.0, "caps-no-nlstr"] > mag[0.0, "caps-no-nlstr"]
    assert recs[0.0, "caps-naive"]["theory"]["resolved_fraction"] == pytest.approx(0.25)
    assert recs[1.0, "caps-naive"]["theory"]["resolved_fraction"] > 0.5
    assert recs[0.0, "caps-naive"]["kind"] == "array" and recs[0.0, "dofp-bilinear"]["kind"] == "dofp"


def test_a_cell_equals_a_direct_simulate_reconstruct_evaluate(phase_run):
    gt, meta = synthetic_scene("star", size=96, seed=0, cycles=24)
    capture = simulate_capture(gt, CameraSetup(sensor=make_sensor("gaussian", sigma=0.005)), seed=0,
                               aperture_homographies=regular_offsets(1.0), extra_meta={"scene": {"name": "s", **meta}})
    scorer = CaptureScorer(capture)
    for method in ("caps-no-nlstr", "dofp-bilinear"):
        out, _ = reconstruct(capture, method, true_warps=method.startswith("caps"))
        direct = scorer.score(out.image).flat()
        cell = next(r for r in phase_run.records if r["axes"]["offset_px"] == 1.0 and r["method"] == method)
        assert cell["metrics"] == direct  # to the last digit


def test_a_random_pose_cell_equals_the_direct_run_and_resume_runs_only_the_missing(tmp_path):
    spec = load_map(_write(tmp_path, SHIFT_MAP))
    first = run_map(spec, tmp_path / "run", threads=1)
    gt, _ = synthetic_scene("texture", size=48, seed=0)
    capture = simulate_capture(gt, CameraSetup(sensor=make_sensor("gaussian", sigma=0.01)), seed=0,
                               pose_ranges=PoseRanges(shift_max_px=1.0))
    out, _ = reconstruct(capture, "dofp-bilinear")
    cell = next(r for r in first.records if r["axes"]["shift_max"] == 1.0 and r["method"] == "dofp-bilinear")
    assert cell["metrics"] == CaptureScorer(capture).score(out.image).flat()
    results = tmp_path / "run" / "map.jsonl"
    before = _stable(results)
    lines = results.read_text().splitlines()
    results.write_text("\n".join(lines[:2]) + "\n" + lines[2][:40])  # killed while writing the third line
    started = []
    again = run_map(spec, tmp_path / "run", threads=1,
                    events=lambda kind, **info: started.append(info["label"]) if kind == "case" else None)
    assert len([s for s in started if not s.endswith(": capture")]) == 2  # only the two missing cases ran
    assert _stable(results) == before and len(again.records) == 4


def test_the_registration_error_moves_each_aperture_by_that_many_hr_pixels():
    gt, _ = synthetic_scene("texture", size=48, seed=0)
    capture = simulate_capture(gt, CameraSetup(sensor=make_sensor("none")), seed=3)
    moved = perturbed_warps(capture, 0.5, seed=3)
    error = registration_error_hr_px(moved.true_lr_homographies(), capture.true_lr_homographies(), capture.hr_shape)
    assert np.allclose(error[:4], 0.0) and np.allclose(error[4:], 0.5, atol=1e-6)
    assert np.array_equal(moved.caps_raw, capture.caps_raw)
    again = perturbed_warps(capture, 0.5, seed=3)  # seeded: the same directions
    assert np.array_equal(again.aperture_homographies(), moved.aperture_homographies())


def test_the_margin_says_who_wins_and_undecided_within_one_standard_error():
    kinds = {"a": "array", "d": "dofp", "d2": "dofp"}
    win = cell_margin({"a": {0: 30, 1: 31, 2: 32}, "d": {0: 28, 1: 28.5, 2: 29}, "d2": {0: 20, 1: 20, 2: 20}},
                      kinds, True)
    assert win["verdict"] == "array" and win["best_dofp"] == "d" and win["margin"] == pytest.approx(2.5)
    close = cell_margin({"a": {0: 30, 1: 31}, "d": {0: 31, 1: 30.2}}, kinds, True)
    assert close["verdict"] == "undecided"
    lower = cell_margin({"a": {0: 5.0}, "d": {0: 4.0}}, kinds, False)  # AoP error: lower is better
    assert lower["verdict"] == "dofp" and lower["margin"] == pytest.approx(-1.0) and lower["se"] is None


def _fake_records(axes: dict) -> list[dict]:
    """Records of a map with every axis combination, 2 seeds, one array and one DoFP method (no run)."""
    records = []
    for combo in itertools.product(*axes.values()):
        cell = dict(zip(axes, combo))
        for seed in (0, 1):
            for method, kind, psnr in (("caps-naive", "array", 30 + sum(combo) + seed), ("dofp-eari", "dofp", 31)):
                records.append({"case_id": f"{cell}{seed}{method}", "status": "ok", "method": method, "kind": kind,
                                "seed": seed, "axes": cell, "wall_time_s": 1.0, "metrics": {"psnr_mean": psnr},
                                "theory": {"resolved_fraction": 0.25 + 0.1 * cell.get("offset_px", 0)}})
    return records


@pytest.mark.parametrize("axes", [{"offset_px": [0.0, 1.0, 2.0]},
                                  {"offset_px": [0.0, 1.0], "sigma": [0.01, 0.02], "psf_sigma_hr_px": [0.0, 1.0]}])
def test_the_report_draws_curves_for_one_axis_and_a_set_of_maps_for_three(tmp_path, axes):
    (tmp_path / "map.jsonl").write_text(results_text(_fake_records(axes)))
    spec = {"name": "fake", "scene": {"name": "s"}, "axes": axes, "fixed": {}, "seeds": [0, 1],
            "methods": [{"label": "caps-naive"}, {"label": "dofp-eari"}]}
    report = write_map_report(tmp_path, spec, command="capssim bench map fake -o out").read_text()
    pictures = sorted(p.name for p in tmp_path.glob("psnr_mean*.png"))
    assert pictures == (["psnr_mean.png"] if len(axes) == 1 else
                        ["psnr_mean_psf_sigma_hr_px=0.png", "psnr_mean_psf_sigma_hr_px=1.png"])
    assert "capssim bench map fake -o out" in report and "| offset_px |" in report


@pytest.mark.parametrize("change, key, received", [
    ({"axes": {"shift_maxx": [0, 1]}}, "axes.shift_maxx", "an unknown axis"),
    ({"axes": {"sigma": [0.01, -0.02]}}, "axes.sigma[1]", "-0.02"),
    ({"axes": {"sigma": [0.01, 0.01]}}, "axes.sigma[1]", "0.01 again"),
    ({"axes": {"sigma": 0.01}}, "axes.sigma", "0.01"),
    ({"axes": {}}, "axes", "no axis"),
    ({"axes": {"offset_px": [0, 1]}, "fixed": {"shift_max": 1}}, "offset_px", "offset_px with shift_max"),
    ({"axes": {"depth_m": [1, 2]}}, "axes.depth_m", "depth_m with a synthetic scene"),
    ({"axes": {"sigma": [0.01]}, "fixed": {"sigma": 0.02}}, "fixed.sigma", "0.02"),
    ({"axes": {"full_well_e": [1000]}}, "axes.full_well_e", "full_well_e with noise 'none'"),
    ({"axes": {"noise": ["gaussian", "speckle"]}}, "axes.noise[1]", "speckle"),
    ({"methods": ["caps-naiv"]}, "methods[0]", "caps-naiv"),
    ({"seeds": [0, 0]}, "seeds", "[0, 0]"),
    ({"scene": {"name": "s", "source": "synthetic", "generator": "star", "crop": 64}}, "scene.crop", "unknown key"),
    ({"colour": 1}, "colour", "an unknown key"),
    ({"scene": {"name": "m", "source": "render", "scene": "water-glare", "size": 64}, "axes": {"depth_m": [2, 4]}},
     "axes.depth_m", "render scene 'water-glare'"),
    ({"scene": {"name": "m", "source": "render", "scene": "window-reflection", "size": 64},
      "axes": {"depth_m": [0.1, 6]}}, "axes.depth_m", "0.1 (scene_params.scale"),
    ({"axes": {"baseline_m": [0.02, 0.04]}}, "axes.baseline_m", "baseline_m with a synthetic scene"),
    ({"scene": {"name": "m", "source": "render", "scene": "textured", "size": 64},
      "axes": {"baseline_m": [0.04, 1.5]}}, "axes.baseline_m[1]", "1.5"),
    ({"scene": {"name": "m", "source": "render", "scene": "textured", "size": 64},
      "axes": {"baseline_m": [-0.01]}}, "axes.baseline_m[0]", "-0.01"),
    ({"scene": {"name": "m", "source": "render", "scene": "textured", "size": 64}, "axes": {"shift_max": [0]}},
     "axes.shift_max", "shift_max with a rendered scene"),
])
def test_spec_validation_names_the_bad_key_and_value(change, key, received):
    spec = {**SHIFT_MAP, **change}
    with pytest.raises(ConfigError) as info:
        check_map(spec)
    message = str(info.value)
    assert key in message and received in message, message
    assert "\n" not in message


def test_the_baseline_axis_reaches_the_render(tmp_path):
    """A cell's baseline_m is the renderer's array baseline: recorded in the capture's meta, and the apertures'
    homographies move with it (an ideal parallel array, no convergence: a plane's disparity is B f / Z, so four
    times the baseline gives four times the offset)."""
    pytest.importorskip("mitsuba")
    ideal = {"tilt_max_deg": 0, "roll_max_deg": 0, "focal_scale_max": 0, "converge": False}
    spec = check_map({"scene": {"name": "star", "source": "render", "scene": "siemens-star", "size": 32, "spp": 1,
                                "geometry_params": ideal},
                      "methods": ["caps-naive"], "axes": {"baseline_m": [0.02, 0.08]}, "fixed": {"depth_m": 0.5}})
    factory = MapCaptureFactory(tmp_path, lambda *a, **k: None)
    offsets = {}
    for value in spec["axes"]["baseline_m"]:
        cell = {"axes": {"baseline_m": value}, "fixed": spec["fixed"]}
        scene = cell_scene(spec["scene"], cell)
        assert scene["geometry_params"] == {**ideal, "baseline_m": value}
        assert scene["scene_params"] == {"depth_m": 0.5}
        entry = factory.get(scene, {}, 0)
        meta = json.loads((entry.path / "meta.json").read_text())
        assert meta["render"]["array"]["parameters"]["baseline_m"] == pytest.approx(value)
        assert entry.info["render"]["geometry_params"]["baseline_m"] == value
        assert entry.info["parallax_p95_hr_px"] < 0.05  # a plane: the homographies are exact
        offsets[value] = np.array([np.hypot(*np.asarray(h)[:2, 2]) for h in meta["aperture_homographies"]])
    assert offsets[0.02][0] == offsets[0.08][0] == 0
    assert offsets[0.02][1] > 0.1
    np.testing.assert_allclose(offsets[0.08], 4 * offsets[0.02], rtol=1e-6)


def test_depth_of_a_3d_scene_scales_it_so_its_reference_depth_is_that_depth():
    pytest.importorskip("mitsuba")
    assert depth_params("window-reflection", 6.0) == {"scale": pytest.approx(4.0)}
    assert depth_params("window-reflection", 3.0) == {"scale": pytest.approx(2.0)}
    assert depth_params("textured", 3.0) == {"depth_m": 3.0}
    assert depth_params("water-glare", 3.0) is None


def test_the_cli_runs_a_map_writes_the_report_and_heatmaps_and_refuses_a_bad_spec(tmp_path, monkeypatch):
    monkeypatch.setenv("CAPSSIM_THREADS", "1")
    spec = _write(tmp_path, {**SHIFT_MAP, "methods": ["caps-naive", "dofp-bilinear"]})
    result = CliRunner().invoke(app, ["bench", "map", str(spec), "-o", str(tmp_path / "out"), "--threads", "1"])
    assert result.exit_code == 0, result.output
    report = (tmp_path / "out" / "report.md").read_text()
    assert "| shift_max | sigma | best array | best DoFP | margin |" in report
    assert (tmp_path / "out" / "psnr_mean.png").is_file()
    bad = _write(tmp_path, {**SHIFT_MAP, "axes": {"sigmaa": [0.01]}}, "bad.yaml")
    result = CliRunner().invoke(app, ["bench", "map", str(bad), "-o", str(tmp_path / "bad")])
    # the console entry point prints a ConfigError as one line and exits 2 (capssim.cli.main)
    assert isinstance(result.exception, ConfigError) and "axes.sigmaa" in str(result.exception)
    assert not (tmp_path / "bad").exists()


def test_the_shipped_maps_load():
    for name in ("phase-noise", "phase-noise-real", "phase-offsets", "registration-noise", "psf-noise", "depth-noise",
                 "depth-baseline"):
        spec = load_map(name)
        assert spec["axes"] and all(m["label"] for m in spec["methods"])


@pytest.mark.slow
def test_dask_gives_the_serial_map(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setenv("CAPSSIM_THREADS", "1")
    spec = load_map(_write(tmp_path, SHIFT_MAP))
    run_map(spec, tmp_path / "serial", threads=1)
    run_map(spec, tmp_path / "dask", threads=1, workers=2)
    assert _stable(tmp_path / "serial" / "map.jsonl") == _stable(tmp_path / "dask" / "map.jsonl")
