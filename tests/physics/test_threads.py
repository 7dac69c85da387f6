"""``--threads`` / ``CAPSSIM_THREADS`` and the one-thread context of small-tensor phases (issue 20)."""

from __future__ import annotations

import os

import pytest
import torch
from typer.testing import CliRunner

from capssim.errors import InputError
from capssim.runtime import threads

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
    # the callback's InputError: the console entry point prints it as one line and exits 2
    assert isinstance(result.exception, InputError) and "--threads" in str(result.exception)
    assert "\n" not in str(result.exception)


@pytest.mark.parametrize("others,cores,expected", [(0.0, 2, 2), (0.49, 2, 2), (0.5, 2, 1), (1.0, 2, 1), (3.0, 2, 1),
                                                   (0.6, 4, 3), (1.6, 4, 2), (0.2, 1, 1)])
def test_adaptive_count_leaves_the_others_their_cores(others, cores, expected):
    assert threads.adaptive_count(others, cores) == expected


def test_auto_is_the_default_and_is_exported_to_children(monkeypatch):
    assert threads.is_adaptive() and threads.set_threads() == 1 and torch.get_num_threads() == 1
    assert os.environ[threads.ENV_VAR] == threads.AUTO and os.environ["OMP_NUM_THREADS"] == "1"
    monkeypatch.setenv(threads.ENV_VAR, "AUTO")
    assert threads.is_adaptive() and threads.resolve_threads() == 1
    assert not threads.is_adaptive(2)
    threads.set_threads(2)  # an explicit count is kept: no governor
    assert os.environ[threads.ENV_VAR] == "2" and threads.adapt_threads() == 2 and threads.adaptive_decisions() == []


def test_governor_follows_the_other_processes(tmp_path, monkeypatch):
    stat = tmp_path / "stat"
    clock = {"wall": 100.0, "own": 5.0, "busy": 0}  # busy: jiffies of the two CPUs together

    def write_stat():
        half = clock["busy"] // 2
        stat.write_text(f"cpu  {clock['busy']} 0 0 0 0 0 0 0 0 0\ncpu0 {half} 0 0 9 0 0 0 0 0 0\n"
                        f"cpu1 {clock['busy'] - half} 0 0 9 0 0 0 0 0 0\ncpu7 5000 0 0 0 0 0 0 0 0 0\n")

    def advance(seconds, own_cpu, others_cpu):
        ticks = os.sysconf("SC_CLK_TCK")
        clock["wall"] += seconds
        clock["own"] += own_cpu
        clock["busy"] += round((own_cpu + others_cpu) * ticks)
        write_stat()

    write_stat()
    monkeypatch.setattr(threads.time, "monotonic", lambda: clock["wall"])
    monkeypatch.setattr(threads.time, "process_time", lambda: clock["own"])
    governor = threads.ThreadGovernor(2, stat_path=str(stat))
    governor.cpus = [0, 1]  # cpu7 belongs to someone else's affinity mask
    advance(1.0, own_cpu=1.0, others_cpu=0.1)
    assert governor.update() == 2 and torch.get_num_threads() == 2  # quiet: both cores
    advance(0.1, own_cpu=0.2, others_cpu=1.0)
    assert governor.update() == 2  # too soon to decide again
    advance(1.0, own_cpu=1.0, others_cpu=0.9)
    assert governor.update() == 1 and torch.get_num_threads() == 1  # a competitor: one core left
    advance(1.0, own_cpu=1.0, others_cpu=0.0)
    assert governor.update() == 2
    assert [count for _, count in governor.decisions] == [2, 1, 2]
    missing = threads.ThreadGovernor(2, stat_path=str(tmp_path / "absent"))
    assert missing.update() == torch.get_num_threads()  # no /proc/stat: no decision
    assert missing.decisions == []


def _idle_machine(tmp_path, monkeypatch, wall: float) -> tuple[str, dict]:
    """A ``/proc/stat`` of two idle CPUs and a clock at ``wall`` s that the test advances; no own CPU time."""
    stat = tmp_path / "stat"
    stat.write_text("cpu0 0 0 0 0 0 0 0 0 0 0\ncpu1 0 0 0 0 0 0 0 0 0 0\n")
    clock = {"wall": wall}
    monkeypatch.setattr(threads.time, "monotonic", lambda: clock["wall"])
    monkeypatch.setattr(threads.time, "process_time", lambda: 0.0)
    return str(stat), clock


def test_small_tensor_phases_cap_the_governor_and_large_registrations_follow_it(tmp_path, monkeypatch):
    stat, clock = _idle_machine(tmp_path, monkeypatch, 10.0)
    threads.set_threads()  # auto
    governor = threads.ThreadGovernor(2, stat_path=stat)
    governor.cpus = [0, 1]
    monkeypatch.setattr(threads, "_governor", governor)
    clock["wall"] += 1.0
    with threads.small_tensor_threads() as count:  # quiet machine, but a small-tensor phase: one thread
        assert count == 1 and threads.adapt_threads() == 1 and torch.get_num_threads() == 1
    small = threads.LARGE_REGISTRATION_PIXELS - 1
    with threads.registration_threads(small) as count:
        assert count == 1
    clock["wall"] += 1.0
    with threads.registration_threads(threads.LARGE_REGISTRATION_PIXELS) as count:  # quiet: both cores
        assert count == 2 and torch.get_num_threads() == 2
    monkeypatch.setattr(threads, "_governor", None)
    torch.set_num_threads(2)
    with threads.registration_threads(threads.LARGE_REGISTRATION_PIXELS) as count:  # a fixed count: one thread
        assert count == 1


def test_the_first_governor_measures_from_start_up_so_the_first_stages_already_decide(tmp_path, monkeypatch):
    stat, _ = _idle_machine(tmp_path, monkeypatch, 5.0)
    monkeypatch.setattr(threads, "_import_sample", (4.0, 0.0, 0.0))  # taken 1 s before: the start-up
    torch.set_num_threads(1)
    start_up = threads._startup_sample()
    assert start_up == (4.0, 0.0, 0.0) and threads._startup_sample() is None  # handed out once
    governor = threads.ThreadGovernor(2, stat_path=stat, since=start_up)
    governor.cpus = [0, 1]
    assert governor.update() == 2 and torch.get_num_threads() == 2  # no wait for a first interval
    later = threads.ThreadGovernor(2, stat_path=stat)
    later.cpus = [0, 1]
    torch.set_num_threads(1)
    assert later.update() == 1 and later.decisions == []  # without it: the interval first
