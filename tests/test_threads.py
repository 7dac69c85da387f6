"""``--threads`` / ``CAPSSIM_THREADS`` and the one-thread context of small-tensor phases (issue 20)."""

from __future__ import annotations

import os

import pytest
import torch
from typer.testing import CliRunner

from capssim import threads
from capssim.errors import InputError

COMMANDS = (["reconstruct"], ["simulate"], ["render"], ["demosaic"], ["dataset"], ["bench", "suite"],
            ["bench", "reconstruct"], ["bench", "registration"], ["bench", "dofp"], ["bench", "render"],
            ["bench", "dataset"])


@pytest.fixture(autouse=True)
def restore_threads(monkeypatch):
    """Each test leaves torch's thread count and the thread variables as it found them."""
    before = torch.get_num_threads()
    for var in (threads.ENV_VAR, *threads.CHILD_ENV_VARS):
        monkeypatch.setenv(var, os.environ[var]) if var in os.environ else monkeypatch.delenv(var, raising=False)
    monkeypatch.delenv(threads.ENV_VAR, raising=False)
    yield
    torch.set_num_threads(before)


def test_option_then_environment_then_default(monkeypatch):
    assert threads.resolve_threads() == threads.DEFAULT_THREADS == 1
    monkeypatch.setenv(threads.ENV_VAR, "3")
    assert threads.resolve_threads() == 3
    assert threads.resolve_threads(1) == 1
    assert threads.resolve_threads("2") == 2


@pytest.mark.parametrize("bad", [0, -1, 1.5, "two", True, ""])
def test_bad_counts_are_input_errors(bad):
    with pytest.raises(InputError, match="--threads"):
        threads.resolve_threads(bad)


def test_huge_counts_are_refused():
    from capssim.errors import ResourceError

    with pytest.raises(ResourceError, match="thread count"):
        threads.resolve_threads(100_000)


def test_bad_environment_variable_names_it(monkeypatch):
    monkeypatch.setenv(threads.ENV_VAR, " ")
    assert threads.resolve_threads() >= 1  # blank: not set
    monkeypatch.setenv(threads.ENV_VAR, "many")
    with pytest.raises(InputError, match=threads.ENV_VAR):
        threads.resolve_threads()


def test_set_threads_applies_to_torch_opencv_and_children():
    import cv2

    assert threads.set_threads(1) == 1
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
    assert os.environ[threads.ENV_VAR] == "1" and os.environ["OMP_NUM_THREADS"] == "1"
    assert threads.set_threads(2) == 2 and torch.get_num_threads() == 2


def test_small_tensor_threads_uses_one_and_restores():
    threads.set_threads(2)
    with threads.small_tensor_threads() as used:
        assert used == 1 and torch.get_num_threads() == 1
        with threads.small_tensor_threads(4) as inner:  # never more than the outer count
            assert inner == 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError):
        with threads.small_tensor_threads():
            raise RuntimeError("inside")
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_every_compute_command_takes_threads(command):
    from capssim.cli import app

    result = CliRunner().invoke(app, [*command, "--help"])
    assert result.exit_code == 0, result.output
    assert "--threads" in result.output


def test_threads_zero_is_refused_by_the_cli(tmp_path):
    from capssim.cli import app

    result = CliRunner().invoke(app, ["reconstruct", str(tmp_path), "--threads", "0"])
    assert result.exit_code == 2 and "--threads" in result.output
