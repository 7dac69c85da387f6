"""Plug-in methods and priors (issue 59 item 1): entry points ``capssim.methods`` / ``capssim.priors``.

A package made in a temporary folder (a module and a ``.dist-info`` with ``entry_points.txt``, on
``PYTHONPATH`` of a subprocess) is listed, runs under ``capssim reconstruct -m NAME`` with ``caps-naive``'s
image exactly, and runs in ``capssim bench suite`` and ``bench budget``; broken plug-ins give one line and
never stop the other methods. The Python API (:func:`add_method`, :func:`add_prior`) is checked in process.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import tifffile
from support.fuzz import one_error_line, run_cli

from capssim.errors import PluginError
from capssim.reconstruct import plugins, reconstruct, registry
from capssim.reconstruct.pipeline import slots

PLUGIN_MODULE = '''
import numpy as np

from capssim.reconstruct import reconstruct
from capssim.reconstruct.plugins import method


@method(input_kind="caps", description="caps-naive again, through the public API", reference="this test")
def naive_again(capture, **options):
    out, _ = reconstruct(capture, "caps-naive", physical_projection=False, **options)
    return out  # a MethodOutput; capssim projects it as it does caps-naive's


def raises(capture):
    raise RuntimeError("boom\\nsecond line")


def wrong_shape(capture):
    return np.zeros((3, 8, 8), np.float32)


def no_capture():
    return None
'''

ENTRY_POINTS = """
[capssim.methods]
naive-again = tmp_capssim_plugin:naive_again
plug-raises = tmp_capssim_plugin:raises
plug-shape = tmp_capssim_plugin:wrong_shape
plug-signature = tmp_capssim_plugin:no_capture
plug-missing = no_such_module_here:fn
"""

SUITE = """
name: plugin-suite
seeds: [0]
noise:
  - {name: gauss-0.01, model: gaussian, sigma: 0.01}
methods: [caps-naive, naive-again, plug-raises, plug-shape]
scenes:
  - {name: texture, source: synthetic, generator: texture, size: 32}
"""


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    """A plug-in package ``tmp-capssim-plugin 0.3`` in a folder of its own (nothing installed)."""
    root = tmp_path_factory.mktemp("plugin")
    (root / "tmp_capssim_plugin.py").write_text(PLUGIN_MODULE)
    info = root / "tmp_capssim_plugin-0.3.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: tmp-capssim-plugin\nVersion: 0.3\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(ENTRY_POINTS))
    return root


@pytest.fixture(scope="module")
def capture_folder(tmp_path_factory):
    from capssim.camera.sensor import make_sensor
    from capssim.captures.capture import write_capture
    from capssim.eval.synthetic import texture_scene
    from capssim.simulate import simulate_capture

    folder = tmp_path_factory.mktemp("capture") / "cap"
    write_capture(folder, simulate_capture(texture_scene(32, seed=0)[0], make_sensor("gaussian", sigma=0.01), seed=0))
    return folder


def _capssim(package, *args):
    env = dict(os.environ, PYTHONPATH=f"{package}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
               CAPSSIM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "capssim", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=600)


def _errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error")]


def test_listed_with_its_package_and_broken_ones_say_why(package):
    result = _capssim(package, "reconstruct", "--list")
    assert result.returncode == 0, result.stderr
    lines = {line.split()[0]: line for line in result.stdout.splitlines()}
    assert "caps-naive again, through the public API" in lines["naive-again"]
    assert "(plug-in: tmp-capssim-plugin 0.3)" in lines["naive-again"] and "[caps]" in lines["naive-again"]
    assert "caps-naive" in lines and "(plug-in" not in lines["caps-naive"]
    assert "does not load" in lines["plug-missing"] and "no_such_module_here" in lines["plug-missing"]
    assert "cannot be called with a capture" in lines["plug-signature"]


@pytest.fixture
def installed_in_process(package, monkeypatch):
    """The plug-in package on this process's ``sys.path`` and its entry points loaded, as a console run
    loads them (:func:`plugins.load_plugins`); the registry is given back afterwards. Saves one CLI start-up
    (about 4 s: torch's import) per refused command; the discovery itself is checked in a subprocess above."""
    registry.available_methods()  # the built-in methods (and this environment's plug-ins), registered once
    before, broken, loaded = dict(registry._METHODS), dict(plugins._BROKEN), plugins._LOADED
    monkeypatch.syspath_prepend(str(package))
    plugins._LOADED = False
    plugins.load_plugins()  # the entry points, now the package's too
    yield
    registry._METHODS.clear()
    registry._METHODS.update(before)
    plugins._BROKEN.clear()
    plugins._BROKEN.update(broken)
    plugins._LOADED = loaded
    sys.modules.pop("tmp_capssim_plugin", None)


def test_reconstruct_gives_caps_naives_image_exactly(package, capture_folder):
    result = _capssim(package, "reconstruct", capture_folder, "-m", "caps-naive", "-m", "naive-again",
                      "--no-progress")
    assert result.returncode == 0, result.stderr
    recon = capture_folder / "recon"
    assert np.array_equal(tifffile.imread(recon / "naive-again.tiff"), tifffile.imread(recon / "caps-naive.tiff"))
    record = json.loads((recon / "naive-again.json").read_text())
    assert record["plugin"] == {"package": "tmp-capssim-plugin", "version": "0.3",
                                "entry_point": "tmp_capssim_plugin:naive_again"}


@pytest.mark.parametrize("name, needle", [("plug-raises", "raised RuntimeError: boom second line"),
                                          ("plug-shape", "returned shape (3, 8, 8); expected (12, 32, 32)"),
                                          ("plug-missing", "does not load"),
                                          ("plug-signature", "cannot be called with a capture")])
def test_a_broken_plugin_is_one_line(name, needle, installed_in_process, capture_folder, capsys, monkeypatch):
    status, text = run_cli(["reconstruct", capture_folder, "-m", name, "--no-progress"], capsys, monkeypatch,
                           quiet=True)
    line = one_error_line(status, text, f"plug-in method '{name}' (tmp-capssim-plugin 0.3)", needle)
    assert "Traceback" not in line


def test_suite_and_budget_run_plugins_and_keep_the_other_methods(package, tmp_path):
    suite = tmp_path / "suite.yaml"
    suite.write_text(SUITE)
    out = tmp_path / "out"
    result = _capssim(package, "bench", "suite", suite, "-o", out, "--no-plots", "-m", "caps-naive",
                      "-m", "naive-again", "-m", "plug-raises", "-m", "plug-shape")
    assert result.returncode == 1, result.stderr  # two cases failed, the run finished
    records = {r["method"]: r for r in map(json.loads, (out / "results.jsonl").read_text().splitlines())}
    assert records["caps-naive"]["status"] == records["naive-again"]["status"] == "ok"
    assert records["naive-again"]["metrics"] == records["caps-naive"]["metrics"]
    assert records["naive-again"]["plugin"]["version"] == "0.3" and "plugin" not in records["caps-naive"]
    for name in ("plug-raises", "plug-shape"):
        assert records[name]["status"] == "error" and "\n" not in records[name]["reason"]
        assert f"plug-in method '{name}' (tmp-capssim-plugin 0.3)" in records[name]["reason"]

    budget = _capssim(package, "bench", "budget", suite, "-o", tmp_path / "budget", "-m", "naive-again",
                      "--no-plots")
    assert budget.returncode == 0, budget.stderr
    (line,) = (tmp_path / "budget" / "budget.jsonl").read_text().splitlines()
    record = json.loads(line)
    assert record["status"] == "ok" and record["plugin"]["package"] == "tmp-capssim-plugin"
    assert [r["rung"] for r in record["rungs"]] == ["as-captured", "true-warps", "model-exact", "noise-free"]


# -- the Python API, in this process ----------------------------------------------------------------
@pytest.fixture
def registered():
    """Names this test registers, removed afterwards (the registry is the process's)."""
    names: list[str] = []
    yield names
    for name in names:
        registry._METHODS.pop(name, None)
        slots._PRIORS.pop(name, None)


@pytest.fixture(scope="module")
def capture():
    from capssim.camera.sensor import make_sensor
    from capssim.eval.synthetic import texture_scene
    from capssim.simulate import simulate_capture

    return simulate_capture(texture_scene(32, seed=1)[0], make_sensor("gaussian", sigma=0.01), seed=1)


def test_add_method_runs_a_function_and_checks_its_output(capture, registered):
    def mean_image(capture, *, level=0.5):
        """Every channel the constant ``level``."""
        return np.full((12, *capture.hr_shape), float(level), np.float64)

    registered.append("plug-constant")
    plugins.add_method("plug-constant", mean_image, input_kind="caps")
    spec = registry.get_method("plug-constant")
    assert spec.description == "Every channel the constant ``level``." and spec.plugin.package is None
    out, record = reconstruct(capture, "plug-constant", level="0.25")
    assert out.image.dtype == np.float32 and np.all(out.image == 0.25)
    assert record["plugin"]["entry_point"].endswith("mean_image")
    with pytest.raises(Exception, match="'bogus'.*plug-in method 'plug-constant'.*level"):
        reconstruct(capture, "plug-constant", bogus=1)

    bad = {"plug-nan": lambda c: np.full((12, *c.hr_shape), np.nan, np.float32),
           "plug-int": lambda c: np.zeros((12, *c.hr_shape), np.int64),
           "plug-list": lambda c: [0.0] * 12}
    needles = {"plug-nan": "non-finite values", "plug-int": "dtype int64", "plug-list": "returned a list"}
    for name, fn in bad.items():
        registered.append(name)
        plugins.add_method(name, fn)
        with pytest.raises(PluginError, match=needles[name]) as err:
            reconstruct(capture, name)
        assert f"plug-in method '{name}'" in str(err.value) and "\n" not in str(err.value)


def test_add_method_refuses_a_builtin_name_and_a_function_without_a_capture(registered):
    with pytest.raises(PluginError, match="built-in method"):
        plugins.add_method("caps-naive", lambda capture: None)
    assert registry.get_method("caps-naive").plugin is None  # the built-in is kept
    with pytest.raises(PluginError, match="cannot be called with a capture"):
        plugins.add_method("plug-none", lambda: None)
    assert "plug-none" not in registry.available_methods()


def test_a_prior_plugin_fills_the_caps_pipelines_prior_slot(capture, registered):
    """The same Tikhonov factory registered as a plug-in prior gives the built-in's image exactly; a factory
    that raises gives one line naming the plug-in."""
    from capssim.reconstruct.pipeline.slots import TikhonovParameters

    calls = []

    def my_prior(shape, *, parameters, options, device):
        calls.append(shape)
        return slots.tikhonov_prior(shape, parameters=parameters, options=options, device=device)

    registered.extend(["plug-tikhonov", "plug-broken-prior"])
    plugins.add_prior("plug-tikhonov", my_prior, description="Tikhonov, as a plug-in", parameters=TikhonovParameters)
    assert slots.get_prior("plug-tikhonov").description == "Tikhonov, as a plug-in"
    mine, _ = reconstruct(capture, "caps", true_warps=True, iterations=2, prior="plug-tikhonov")
    builtin, _ = reconstruct(capture, "caps", true_warps=True, iterations=2, prior="tikhonov")
    assert calls and np.array_equal(mine.image, builtin.image)

    def broken(shape, *, parameters, options, device):
        raise ValueError("no prior today")

    plugins.add_prior("plug-broken-prior", broken)
    with pytest.raises(PluginError, match="plug-in prior 'plug-broken-prior'.*raised ValueError: no prior today"):
        reconstruct(capture, "caps", true_warps=True, iterations=2, prior="plug-broken-prior")
    with pytest.raises(PluginError, match="built-in prior"):
        plugins.add_prior("nlstr", my_prior)
