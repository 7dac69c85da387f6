"""Dataset config: validation errors name the key, draws are deterministic, augmentations are physical."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from capssim.dataset import ConfigError, load_config, parse_config
from capssim.dataset.augment import rotate_flip_twelve, scale_colours
from capssim.dataset.distributions import key_rng
from capssim.errors import InputError
from capssim.stokes.polarization import angle_difference_deg, aop_deg, dolp, stokes_from_12

REPO = Path(__file__).resolve().parents[2]
CLI = [sys.executable, "-m", "capssim.cli.__main__"]


def write_config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.yaml"
    path.write_text(textwrap.dedent(text))
    return path


@pytest.fixture
def gt_dir(tmp_path, write_gt_folder):
    write_gt_folder(tmp_path / "gt" / "a", seed=1)
    write_gt_folder(tmp_path / "gt" / "b", seed=2)
    return tmp_path / "gt"


GOOD = """
seed: 5
samples: 8
defaults:
  sensor: {noise: {choice: [none, gaussian, poisson-gaussian]}, sigma: {log_uniform: [0.002, 0.02]},
           preset: {choice: [imx250myr, python1300]}}
  dofp_layout: {choice: [sony, 0-45-135-90]}
  pose: {shift_max_px: {uniform: [0.5, 2.0]}, rotation_max_deg: {normal: [0.2, 0.1], clip: [0, 0.5]}}
sources:
  - gt: gt/*
    size: 16
    crop_position: random
    augment: {rot90: {int_uniform: [0, 3]}, flip: {choice: [false, true], weights: [1, 1]}}
"""


def test_good_config_draws_deterministically(tmp_path, gt_dir):
    cfg = load_config(write_config(tmp_path, GOOD))
    specs = [cfg.sample_spec(i) for i in range(cfg.samples)]
    again = load_config(write_config(tmp_path, GOOD))
    assert [again.sample_spec(i) for i in range(cfg.samples)] == specs
    # reversed order of evaluation gives the same draws (no shared generator state)
    assert [cfg.sample_spec(i) for i in reversed(range(cfg.samples))][::-1] == specs
    # the draws vary across samples and respect the rules
    sigmas = [s["params"]["sensor"].get("sigma") for s in specs if s["params"]["sensor"]["noise"] == "gaussian"]
    assert all(0.002 <= v < 0.02 for v in sigmas)
    assert len({s["seed"] for s in specs}) == len(specs)
    assert {s["params"]["source"]["path"] for s in specs} == {"gt/a", "gt/b"}
    assert all(0 <= s["params"]["pose"]["rotation_max_deg"] <= 0.5 for s in specs)
    for s in specs:  # only the fields of the drawn noise model are kept
        noise = s["params"]["sensor"]["noise"]
        assert set(s["params"]["sensor"]) == {"none": {"noise"}, "gaussian": {"noise", "sigma"},
                                              "poisson-gaussian": {"noise", "preset"}}[noise]
    # another master seed changes the draws; adding a key leaves the others alone
    other = load_config(write_config(tmp_path, GOOD.replace("seed: 5", "seed: 6")))
    assert other.sample_spec(0)["params"] != specs[0]["params"]
    extra = load_config(write_config(tmp_path, GOOD.replace("sources:", "  psf_sigma_hr_px: {uniform: [0.3, 0.7]}\nsources:")))
    s0 = extra.sample_spec(0)
    assert s0["params"]["sensor"] == specs[0]["params"]["sensor"] and s0["seed"] == specs[0]["seed"]
    assert 0.3 <= s0["params"]["psf_sigma_hr_px"] < 0.7
    # fingerprints ignore only `samples`
    more = load_config(write_config(tmp_path, GOOD.replace("samples: 8", "samples: 20")))
    assert more.fingerprint() == cfg.fingerprint() and more.sample_spec(3) == specs[3]
    assert other.fingerprint() != cfg.fingerprint()


def test_key_rng_is_independent_per_key_and_index():
    a = key_rng(1, 0, "x").random()
    assert a == key_rng(1, 0, "x").random()
    assert a != key_rng(1, 1, "x").random() and a != key_rng(1, 0, "y").random() and a != key_rng(2, 0, "x").random()


BAD_CASES = [
    # (description, yaml, substrings the message must contain)
    ("negative size", GOOD.replace("size: 16", "size: -64"), ["sources[0].size", "-64", ">= 16"]),
    ("size not multiple of 4", GOOD.replace("size: 16", "size: 18"), ["sources[0].size", "multiple of 4", "Try 16"]),
    ("empty choice", GOOD.replace("choice: [sony, 0-45-135-90]", "choice: []"),
     ["defaults.dofp_layout.choice", "at least one value"]),
    ("empty range", GOOD.replace("uniform: [0.5, 2.0]", "uniform: [2.0, 0.5]"),
     ["defaults.pose.shift_max_px.uniform", "low <= high", "no samples"]),
    ("zero weights", GOOD.replace("weights: [1, 1]", "weights: [0, 0]"),
     ["sources[0].augment.flip.weights", "positive sum"]),
    ("zero samples", GOOD.replace("samples: 8", "samples: 0"), ["'samples'", ">= 1"]),
    ("no sources", "seed: 1\nsamples: 2\nsources: []\n", ["'sources'", "at least 1 sources"]),
    ("unknown key", GOOD.replace("samples: 8", "sampels: 8"), ["'sampels'", "unknown key", "Did you mean 'samples'"]),
    ("missing seed", GOOD.replace("seed: 5", ""), ["'seed'", "missing"]),
    ("bad noise", GOOD.replace("choice: [none, gaussian, poisson-gaussian]", "choice: [none, gausian]"),
     ["defaults.sensor.noise.choice[1]", "gausian", "Did you mean 'gaussian'"]),
    ("negative sigma range", GOOD.replace("log_uniform: [0.002, 0.02]", "uniform: [-0.01, 0.02]"),
     ["defaults.sensor.sigma.uniform[0]", ">= 0"]),
    ("unbounded normal", GOOD.replace(", clip: [0, 0.5]", ""), ["rotation_max_deg.normal", "clip"]),
    ("gaussian without sigma", GOOD.replace(", sigma: {log_uniform: [0.002, 0.02]}", ""),
     ["defaults.sensor.sigma", "missing", "gaussian"]),
    ("both gt and scene", GOOD.replace("- gt: gt/*", "- gt: gt/*\n    scene: siemens-star"),
     ["sources[0]", "exactly one of"]),
    ("missing gt folder", GOOD.replace("gt: gt/*", "gt: ../shared/nowhere/qiu-kettle"),
     ["sources[0].gt", "does not exist", "shared data"]),
    ("glob matching nothing", GOOD.replace("gt: gt/*", "gt: nothing/*"), ["sources[0].gt", "matches nothing"]),
    ("weight with cycle", GOOD.replace("size: 16", "size: 16\n    weight: 2"), ["sources[0].weight", "selection: random"]),
    ("bad dofp layout", GOOD.replace("0-45-135-90", "0-45-90-90"), ["defaults.dofp_layout.choice[1]"]),
    ("distribution mapping typo", GOOD.replace("uniform: [0.5, 2.0]", "unifrom: [0.5, 2.0]"),
     ["defaults.pose.shift_max_px", "exactly one of"]),
    ("int uniform on sizes", GOOD.replace("size: 16", "size: {int_uniform: [16, 32]}"),
     ["sources[0].size.int_uniform", "choice"]),
    ("top level not a mapping", "- 1\n- 2\n", ["a dataset config"]),
    ("empty file", "", ["empty file"]),
]


@pytest.mark.parametrize("name,text,expected", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_configs_name_the_key(tmp_path, gt_dir, name, text, expected):
    path = write_config(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert str(path) in message
    for part in expected:
        assert part in message, f"{part!r} not in {message!r}"


def test_unreadable_yaml(tmp_path):
    path = write_config(tmp_path, "seed: 1\nsamples: [2\nsources:\n  - gt: x\n")
    with pytest.raises(ConfigError, match=r"not valid YAML at line \d+, column \d+"):
        load_config(path)
    with pytest.raises(ConfigError, match="no file at"):
        load_config(tmp_path / "missing.yaml")
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00bad")
    with pytest.raises(ConfigError, match="unreadable file|not valid YAML"):
        load_config(tmp_path / "binary.yaml")


SCENE_CONFIG = """
seed: 1
samples: 2
sources:
  - scene: {scene}
    size: 32
    spp: 4
"""


def test_scenes_are_the_registered_library(tmp_path):
    """Scene names are checked against the scene library; unknown names get a suggestion."""
    path = write_config(tmp_path, SCENE_CONFIG.format(scene="siemens-star"))
    cfg = load_config(path)
    assert cfg.sample_spec(1)["params"]["source"]["scene"] == "siemens-star"
    path = write_config(tmp_path, SCENE_CONFIG.format(scene="siemens-str"))
    with pytest.raises(ConfigError, match=r"unknown scene 'siemens-str'.*Did you mean 'siemens-star'"):
        load_config(path)
    path = write_config(tmp_path, SCENE_CONFIG.format(scene="aop-wheel") + "    pose: {shift_max_px: 1}\n")
    with pytest.raises(ConfigError, match=r"sources\[0\]\.pose.*geometry_params"):
        load_config(path)


def test_cli_bad_config_exits_2_with_the_message(tmp_path, gt_dir):
    path = write_config(tmp_path, GOOD.replace("size: 16", "size: -64"))
    proc = subprocess.run([*CLI, "dataset", str(path), "-o", str(tmp_path / "out")], capture_output=True, text=True,
                          cwd=REPO, timeout=120)
    assert proc.returncode == 2
    assert "sources[0].size" in proc.stderr and "-64" in proc.stderr
    assert not (tmp_path / "out").exists()
    proc = subprocess.run([*CLI, "dataset", str(write_config(tmp_path, GOOD)), "--dry-run"], capture_output=True,
                          text=True, cwd=REPO, timeout=120)
    assert proc.returncode == 0 and "000004: seed" in proc.stdout


def test_rot90_and_flip_move_polarization_angles(smooth_random_scene):
    scene = smooth_random_scene(24, seed=3).astype(np.float64)
    stokes = stokes_from_12(scene)[:, 1]  # green (S0, S1, S2)
    aop, dop = aop_deg(stokes), dolp(stokes)
    for k in range(4):
        for flip in (False, True):
            out = stokes_from_12(rotate_flip_twelve(scene, rot90=k, flip=flip))[:, 1]
            # where each output pixel came from
            expect_aop = -aop if flip else aop
            src_dop = dop[:, ::-1] if flip else dop
            src_aop = expect_aop[:, ::-1] if flip else expect_aop
            src_aop, src_dop = np.rot90(src_aop, k), np.rot90(src_dop, k)
            np.testing.assert_allclose(dolp(out), src_dop, atol=1e-9)
            diff = angle_difference_deg(aop_deg(out), src_aop + 90 * k)
            assert np.abs(diff).max() < 1e-6, (k, flip)
    # a horizontally polarized scene (AoP 0) turned a quarter is vertically polarized (AoP 90)
    s = np.zeros((3, 3, 8, 8))
    s[0], s[1] = 1.0, 0.5
    from capssim.stokes.polarization import twelve_from_stokes

    turned = stokes_from_12(rotate_flip_twelve(twelve_from_stokes(s), rot90=1))
    assert np.allclose(aop_deg(turned[:, 0]), 90.0)


def test_parse_config_from_a_dict(gt_dir):
    cfg = parse_config({"seed": 0, "samples": 3, "sources": [{"gt": "a"}]}, base_dir=gt_dir)
    spec = cfg.sample_spec(2)
    assert spec["name"] == "000002" and spec["params"]["source"]["size"] is None
    assert spec["params"]["sensor"] == {"noise": "none"}
    with pytest.raises(IndexError):
        cfg.sample_spec(3)


def test_colour_gains_and_exposure_keep_the_polarization_and_never_exceed_one(smooth_random_scene):
    scene = smooth_random_scene(24, seed=4).astype(np.float64)
    out, applied = scale_colours(scene, gain_red=1.5, gain_blue=0.6, exposure=3.0)
    assert out.dtype == np.float32 and out.max() <= 1.0 + 1e-6
    assert applied == pytest.approx(1.0 / (scene * np.tile([1.5, 1.0, 0.6], 4)[:, None, None]).max())
    before, after = stokes_from_12(scene), stokes_from_12(out.astype(np.float64))
    np.testing.assert_allclose(after[:, 0], before[:, 0] * 1.5 * applied, rtol=1e-5, atol=1e-6)  # red Stokes scaled
    np.testing.assert_allclose(dolp(after[:, 2]), dolp(before[:, 2]), atol=1e-5)  # blue DoLP kept
    assert np.abs(angle_difference_deg(aop_deg(after[:, 1]), aop_deg(before[:, 1]))).max() < 1e-3
    quiet, kept = scale_colours(scene, exposure=0.5)
    assert kept == 0.5 and np.allclose(quiet, scene * 0.5, atol=1e-6)
    with pytest.raises(InputError, match="gain_red"):
        scale_colours(scene, gain_red=0.0)


def test_colour_augments_are_drawn_only_where_a_source_sets_them(tmp_path, gt_dir):
    plain = load_config(write_config(tmp_path, GOOD)).sample_spec(0)["params"]["source"]
    assert not {"gain_red", "gain_blue", "exposure"} & set(plain)
    text = GOOD.replace("flip: {choice: [false, true], weights: [1, 1]}}",
                        "flip: {choice: [false, true], weights: [1, 1]},\n"
                        "              gain_red: {log_uniform: [0.7, 1.4]}, exposure: {uniform: [0.6, 1.3]}}")
    cfg = load_config(write_config(tmp_path, text))
    source = cfg.sample_spec(0)["params"]["source"]
    assert 0.7 <= source["gain_red"] < 1.4 and 0.6 <= source["exposure"] < 1.3 and "gain_blue" not in source
    bad = GOOD.replace("flip: {choice: [false, true], weights: [1, 1]}}",
                       "flip: {choice: [false, true], weights: [1, 1]}, exposure: 0}")
    with pytest.raises(ConfigError, match="exposure"):
        load_config(write_config(tmp_path, bad))
