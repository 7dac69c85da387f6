"""Fuzz suite, command line: every numeric option of every command survives odd values (issue 21).

For each command, each numeric option (``-p KEY=VALUE`` method options of ``capssim reconstruct``
included) gets odd values (non-finite, negative, zero, huge, tiny, not a number at all) while
every other argument is valid and small (a 32 px ground truth and capture, ``--iterations 1``).
The outcome must be exit 0 or exit 2 with one line (:func:`support.fuzz.invoke`): never a
traceback, never another exit status; ``nan`` and ``-inf`` are never accepted. The memory limit
is 2 GiB (``CAPSSIM_MEMORY_LIMIT_GB``) and the module's growth of the peak memory is checked, so
an option that allocates past the resource guard fails here instead of taking the machine.

Issue 21's cases reproduced at the command line (the other cases' tests are listed in
tests/test_fuzz_cases.py): :data:`ISSUE_CASES`.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.fuzz import NEVER_VALID, PEAK_GROWTH_LIMIT, fuzz_settings, invoke, odd_values, peak_rss_bytes

from capssim.camera.sensor import make_sensor
from capssim.captures.capture import write_capture
from capssim.eval.star import sinusoidal_star
from capssim.files.imageio import write_tiff
from capssim.reconstruct.methods.caps import CapsOptions
from capssim.reconstruct.registry import run_method
from capssim.runtime.resources import MEMORY_LIMIT_ENV
from capssim.simulate import simulate_capture

#: the numeric -p options of the CAPS methods (their types from the defaults)
CAPS_OPTIONS = [f"-p {name}" for name, value in CapsOptions().to_dict().items()
                if isinstance(value, (int, float)) and not isinstance(value, bool)]
#: the numeric -p options of the DoFP baselines, as METHOD:KEY
DOFP_OPTIONS = [f"-p dofp-eari:{k}" for k in ("eps", "weight_floor", "edge_eps", "bayer_sigma")] + \
               [f"-p dofp-igri2:{k}" for k in ("eps", "weight_floor", "bayer_sigma")]

#: every numeric option of every compute command
OPTIONS = {
    "simulate": ["--crop", "--seed", "--sigma", "--psf-sigma-hr-px", "--shift-max", "--rotation-max", "--scale-max",
                 "--extinction-ratio", "--threads"],
    "render": ["--size", "--spp", "--target-noise", "--max-spp", "--seed", "--sigma", "--psf-sigma-hr-px", "--f-number",
               "--wavelength-nm", "--pixel-um", "--oversample", "--extinction-ratio", "--preview-white",
               "--preview-dolp-max", "--threads"],
    "reconstruct": ["--iterations", "--threads", "--tile", "--memory-gb", *CAPS_OPTIONS, *DOFP_OPTIONS],
    "evaluate": ["--min-s0", "--min-dolp", "--border"],
    "mtf": ["--cycles", "--radius", "--reference-pitch", "--modulation", "--threshold", "--residual-limit"],
    "demosaic": ["--white-level", "--black-level", "--dolp-max", "--threads"],
    "gt-check": ["--crop", "--dolp-max"],
    "design": ["--focal-length-mm", "--f-number", "--pixel-um", "--wavelength-nm", "--apertures", "--baseline-mm",
               "--depth-m", "--width-px", "--height-px"],
    "dataset": ["--workers", "--threads"],
}
#: the benchmarks (each valid run takes seconds): swept with values that are all invalid
BENCH_OPTIONS = {
    "bench reconstruct": ["--size", "--iterations", "--repeats"],
    "bench dofp": ["--psf-sigma-hr-px", "--border", "--repeats"],
    "bench render": ["--size", "--spp", "--target-noise", "--warp-spp"],
    "bench registration": ["--stokes-weight"],
}
#: fixed values every option gets, besides the drawn ones
SWEEP = ["nan", "inf", "-inf", "-1", "0", "1e300", "1000000000", "abc", "2.5"]
#: options for which -1 is valid: the caps methods' psf_sigma (-1 = the capture's PSF)
MINUS_ONE_VALID = {"-p psf_sigma"}


class World:
    """Small valid inputs for every command, made once per module, and a fresh output path per call."""

    def __init__(self, root: Path, *, write_gt_folder, smooth_random_scene):
        self.root = root
        self.gt = write_gt_folder(root / "gt", size=32, seed=1)
        (root / "gt-root").mkdir()
        write_gt_folder(root / "gt-root" / "tiny", size=64, seed=2)
        capture = simulate_capture(smooth_random_scene(32, seed=3), make_sensor("gaussian", sigma=0.01), seed=1)
        self.cap = write_capture(root / "cap", capture)
        self.scored = write_capture(root / "scored", capture)
        run_method(self.scored, "dofp-bilinear")
        self.star = root / "star.tiff"
        write_tiff(self.star, sinusoidal_star((64, 64), 36, radius=30.0).astype(np.float32))
        self.raw = root / "raw.png"
        cv2.imwrite(str(self.raw), (np.random.default_rng(0).random((32, 32)) * 255).astype(np.uint8))
        self.config = root / "dataset.yaml"
        self.config.write_text(f"seed: 1\nsamples: 1\nsources:\n  - gt: {self.gt}\n    size: 16\n")
        self._count = itertools.count()

    def fresh(self) -> Path:
        return self.root / "out" / str(next(self._count))

    def base(self, command: str) -> list:
        """The valid, cheap command line ``command``'s options are fuzzed on."""
        out = self.fresh()
        return {
            "simulate": ["simulate", self.gt, "-o", out, "--crop", 32],
            "render": ["render", "siemens-star", "-o", out, "--size", 32, "--spp", 1],
            "reconstruct": ["reconstruct", self.cap, "-m", "caps", "--iterations", 1, "--true-warps", "--no-progress"],
            "evaluate": ["evaluate", self.scored, "--no-mtf"],
            "mtf": ["mtf", self.star, "--cycles", 36],
            "demosaic": ["demosaic", self.raw, "-o", out],
            "gt-check": ["gt-check", self.gt],
            "design": ["design"],
            "dataset": ["dataset", self.config, "-o", out, "--workers", 0],
            "bench reconstruct": ["bench", "reconstruct", self.gt, "--size", 32, "--iterations", 1],
            "bench dofp": ["bench", "dofp", self.root / "gt-root", "--scene", "tiny", "-m", "dofp-bilinear"],
            "bench render": ["bench", "render", "--scene", "siemens-star", "--size", 32, "--spp", 1],
            "bench registration": ["bench", "registration", self.cap],
        }[command]

    def command_line(self, command: str, option: str, value: str) -> list:
        """``command``'s valid line with ``option`` set to ``value`` (and what makes the option act)."""
        args = [str(a) for a in self.base(command)]
        if option.startswith("-p "):
            method, _, key = option[3:].rpartition(":")
            if method:
                args[args.index("caps")] = method
            if key == "iterations":  # --iterations would replace it
                del args[args.index("--iterations"):args.index("--iterations") + 2]
            return [*args, "-p", f"{key}={value}"]
        extra = {"--sigma": ["--noise", "gaussian"], "--f-number": ["--psf", "airy"], "--wavelength-nm": ["--psf", "airy"],
                 "--pixel-um": ["--psf", "airy"], "--preview-white": ["--preview", str(self.fresh()) + ".png"],
                 "--preview-dolp-max": ["--preview", str(self.fresh()) + ".png"],
                 "--warp-spp": ["--warp-accuracy", "siemens-star"]}.get(option, [])
        if command == "render" and option in ("--target-noise", "--max-spp"):
            del args[args.index("--spp"):args.index("--spp") + 2]
        if option in args:
            args[args.index(option) + 1] = value
            return [*args, *extra]
        return [*args, *extra, option, value]


@pytest.fixture(scope="module")
def world(tmp_path_factory, write_gt_folder, smooth_random_scene):
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv(MEMORY_LIMIT_ENV, "2")
        start = peak_rss_bytes()
        yield World(tmp_path_factory.mktemp("fuzz-cli"), write_gt_folder=write_gt_folder,
                    smooth_random_scene=smooth_random_scene)
    grown = peak_rss_bytes() - start
    assert grown < PEAK_GROWTH_LIMIT, f"the CLI fuzz raised the peak memory by {grown / 2**20:.0f} MiB"


def _check(world: World, command: str, option: str, value: str) -> str:
    outcome, message = invoke(world.command_line(command, option, value))
    if value in NEVER_VALID or (value == "-1" and option not in MINUS_ONE_VALID):
        assert outcome != "ok", f"capssim {command} {option} {value!r} was accepted"
    return outcome


@pytest.mark.parametrize("command, option", [(c, o) for c, opts in {**OPTIONS, **BENCH_OPTIONS}.items() for o in opts])
def test_every_numeric_option_refuses_or_takes_fixed_odd_values(world, command, option):
    values = SWEEP
    if command.startswith("bench"):  # only values no benchmark accepts: each valid run takes seconds
        values = ["nan", "-inf", "-1", "abc"] + (["1000000000"] if option != "--stokes-weight" else [])
    for value in values:
        _check(world, command, option, value)


@pytest.mark.parametrize("command", sorted(OPTIONS))
def test_drawn_odd_values_never_crash_a_command(world, command):
    @fuzz_settings(max_examples=min(60, 4 * len(OPTIONS[command])))
    @given(option=st.sampled_from(OPTIONS[command]), value=odd_values)
    def run(option, value):
        _check(world, command, option, value)

    run()


#: issue 21's cases at the command line: (case, arguments after the command, a fragment of the message)
ISSUE_CASES = [
    ("1", ["reconstruct", "{cap}", "-m", "caps", "-p", "search_radius=1000", "--iterations", "2", "--true-warps"],
     "search_radius"),
    ("1", ["simulate", "{gt}", "-o", "{out}", "--psf-sigma-hr-px", "1000"], "psf"),
    ("1", ["render", "siemens-star", "-o", "{out}", "--psf", "airy", "--f-number", "1000", "--size", "64", "--spp", "4"],
     "airy"),
    ("1", ["render", "siemens-star", "-o", "{out}", "--size", "100000"], "size"),
    ("3", ["simulate", "{gt}", "-o", "{out}", "--shift-max", "1000"], "shift_max_px"),
    ("4", ["reconstruct", "{cap}", "-m", "caps", "-p", "dt=100", "--iterations", "3", "--true-warps"], "option dt"),
    ("4", ["reconstruct", "{cap}", "-m", "caps", "-p", "c2=1e30", "--iterations", "3", "--true-warps"], "c2"),
    ("5", ["simulate", "{gt}", "-o", "{out}", "--seed", "-1"], "--seed"),
    ("5", ["render", "siemens-star", "-o", "{out}", "--seed", "-1"], "--seed"),
    ("5", ["render", "polarization-star", "-o", "{out}", "--size", "16", "--param", "cycles=abc"], "cycles"),
    ("6", ["simulate", "{gt}", "-o", "{out}", "--psf-sigma-hr-px", "-1"], "--psf-sigma-hr-px"),
    ("6", ["simulate", "{gt}", "-o", "{out}", "--psf-sigma-hr-px", "nan"], "--psf-sigma-hr-px"),
    ("6", ["simulate", "{gt}", "-o", "{out}", "--scale-max", "2"], "scale_max"),
    ("6", ["render", "siemens-star", "-o", "{out}", "--size", "32", "--max-spp", "0"], "max_spp"),
    ("6", ["render", "siemens-star", "-o", "{out}", "--size", "32", "--geometry", "converge=maybe"], "converge"),
    ("6", ["reconstruct", "{cap}", "-m", "caps", "-p", "psf_sigma=-2", "--true-warps"], "psf_sigma"),
    ("6", ["evaluate", "{scored}", "--min-s0", "nan"], "min_s0"),
    ("6", ["demosaic", "{raw}", "-o", "{out}", "--dolp-max", "-1"], "--dolp-max"),
]


@pytest.mark.parametrize("case, args, fragment", ISSUE_CASES, ids=[f"case{c}-{a[0]}-{f}" for c, a, f in ISSUE_CASES])
def test_issue_cases_are_one_line_errors(world, case, args, fragment):
    names = {"cap": world.cap, "gt": world.gt, "out": world.fresh(), "scored": world.scored, "raw": world.raw}
    outcome, message = invoke([a.format(**names) for a in args])
    assert outcome == "error" and fragment in message, (outcome, message)
    assert not Path(names["out"]).exists()
