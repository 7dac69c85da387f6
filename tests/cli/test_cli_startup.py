"""The command line starts without torch: ``capssim --help``, every group's help and every refusal of bad
input before a command's work begin in about a second, because the modules that pull torch are imported
inside the command functions (``capssim.cli``'s module docstring)."""

from __future__ import annotations

import subprocess
import sys

PROBE = ("import sys, capssim.cli; "
         "print(','.join(sorted(m for m in ('torch', 'mitsuba', 'drjit', 'cv2', 'skimage') if m in sys.modules)))")


def test_importing_the_command_line_imports_no_heavy_library():
    proc = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "", f"imported at start-up: {proc.stdout.strip()}"
