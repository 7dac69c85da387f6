"""Fuzz suite, the dataset config reader: any YAML value in any field gives a valid config or a one-line error.

A valid config (a ground-truth source and a rendered scene, every field set) has one field set to
a drawn YAML value per example (scalars of every type, NaN, inf, huge numbers, lists, mappings and
distributions with odd arguments) or deleted; or the whole file is replaced by drawn text.
:func:`capssim.dataset.load_config` must return a config or raise a
:class:`~capssim.errors.CapssimError` with one line; for a config it returns, drawing the first
samples' parameters and checking them (:func:`capssim.dataset.sample.check_sample`, what
``capssim dataset --dry-run`` does) must also succeed or give a one-line error.
"""

from __future__ import annotations

import copy

import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st
from support.fuzz import PEAK_GROWTH_LIMIT, address_space_headroom, fuzz_settings, one_line_error, peak_rss_bytes

from capssim.dataset import load_config
from capssim.dataset.sample import check_sample
from capssim.runtime.resources import MEMORY_LIMIT_ENV

VALID = {
    "name": "fuzz", "seed": 3, "samples": 2, "selection": "cycle",
    "defaults": {"sensor": {"noise": "gaussian", "sigma": 0.01, "bit_depth": 12}, "dofp_layout": "sony",
                 "pose": {"shift_max_px": 1.0, "rotation_max_deg": 0.5, "scale_max": 0.005},
                 "psf_sigma_hr_px": 0.5, "extinction_ratio": None},
    "sources": [
        {"gt": "gt", "name": "g", "size": 16, "crop_position": "random", "augment": {"rot90": 1, "flip": True},
         "sensor": {"noise": "poisson-gaussian", "preset": "imx250myr", "exposure": 1.0}, "dofp_layout": "0-45-135-90",
         "pose": {"shift_max_px": {"uniform": [0.5, 2.0]}}, "psf_sigma_hr_px": {"log_uniform": [0.3, 1.0]},
         "extinction_ratio": 300.0},
        {"scene": "siemens-star", "name": "s", "size": 16, "spp": 1, "variant": "scalar_rgb", "target_noise": None,
         "scene_params": {"cycles": {"choice": [36, 72]}}, "geometry_params": {"baseline_m": 0.04},
         "psf_sigma_hr_px": 0.5},
    ],
}


def _paths(value, prefix=()) -> list[tuple]:
    out = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, item in value.items():
            out += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            out += _paths(item, (*prefix, index))
    return out


scalars = st.one_of(st.none(), st.booleans(), st.integers(min_value=-10**30, max_value=10**30),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                    st.sampled_from([0, -1, 2**63, 1e308, 4096, 100000, "1e-3", ".nan", "center", "gaussian",
                                     "sony", "siemens-star", "gt"]))
distributions = st.builds(lambda kind, args: {kind: args},
                          st.sampled_from(["const", "choice", "uniform", "log_uniform", "int_uniform", "normal",
                                           "weights", "clip", "bogus"]),
                          st.one_of(scalars, st.lists(scalars, max_size=3)))
yaml_values = st.recursive(st.one_of(scalars, distributions),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner,
                                                                                       max_size=3),
                           max_leaves=6)


@pytest.fixture(scope="module")
def folder(write_gt_folder, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz-config")
    write_gt_folder(root / "gt", size=32, seed=1)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(MEMORY_LIMIT_ENV, "1")
        start = peak_rss_bytes()
        yield root
    grown = peak_rss_bytes() - start
    assert grown < PEAK_GROWTH_LIMIT, f"the config fuzz raised the peak memory by {grown / 2**20:.0f} MiB"


def _load_and_check(path) -> None:
    try:
        config = load_config(path)
        for index in range(min(config.samples, 2)):
            check_sample(config.sample_spec(index))
    except Exception as exc:  # noqa: BLE001 - the point: which exceptions come out
        one_line_error(exc)


def test_the_valid_config_is_valid(folder):
    path = folder / "valid.yaml"
    path.write_text(yaml.safe_dump(VALID))
    config = load_config(path)
    for index in range(config.samples):
        check_sample(config.sample_spec(index))


@fuzz_settings(max_examples=250)
@given(data=st.data())
def test_any_value_in_any_field_loads_or_is_a_one_line_error(folder, data):
    path = data.draw(st.sampled_from(_paths(VALID)), label="path")
    config = copy.deepcopy(VALID)
    parent = config
    for key in path[:-1]:
        parent = parent[key]
    if data.draw(st.booleans(), label="delete"):
        del parent[path[-1]]
    else:
        parent[path[-1]] = data.draw(yaml_values, label="value")
    file = folder / "config.yaml"
    file.write_text(yaml.safe_dump(config))
    with address_space_headroom(3):
        _load_and_check(file)


@fuzz_settings(max_examples=150)
@given(text=st.one_of(st.text(max_size=120), st.builds(yaml.safe_dump, yaml_values)))
def test_any_text_loads_or_is_a_one_line_error(folder, text):
    file = folder / "text.yaml"
    file.write_text(text, encoding="utf-8", errors="surrogatepass")
    with address_space_headroom(3):
        _load_and_check(file)
