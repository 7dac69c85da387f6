"""Start-up stays light: ``import capssim`` imports none of the rooms (nor numpy, torch or mitsuba) until they are
asked for, and the command line (``capssim --help``, every group's help, every refusal of bad input before a
command's work) starts without torch, because the modules that pull it are imported inside the command functions
(``capssim.cli``'s module docstring)."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize("module, heavy", [
    ("capssim", ("numpy", "torch", "mitsuba", "capssim.camera", "capssim.capture", "capssim.captures")),
    ("capssim.cli", ("torch", "mitsuba", "drjit", "cv2", "skimage")),
])
def test_importing_imports_nothing_heavy(module, heavy):
    code = f"import sys, {module}; heavy = [m for m in {heavy!r} if m in sys.modules]; assert not heavy, heavy"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
