"""Issue 34 ("Hardening, second round"): every one of its 12 defect classes keeps table rows in the fuzz suite.

The rows live in ``tests/*/test_hardening2_*.py``; each row names its class first (``Row(N, ...)``, the ``cls`` field). This test reads those
files (it imports none of them) and fails when a class has lost its last row.

=====  =================================================================  ==========================================
class  what                                                               files
=====  =================================================================  ==========================================
1      resource guard on every command (demosaic, mtf, evaluate, train,   test_hardening2_guards, _commands, _bench
       bench suite scene sizes)
2      physically impossible rigs and calibrations                        test_hardening2_capture
3      the regression gate (tolerances, baselines, nothing scored)        test_hardening2_bench
4      bench outputs locked and owned by one suite                        test_hardening2_bench
5      output paths resolved before work, file-system errors              test_hardening2_paths, _path_links
6      hand-edited meta.json and calibration files                        test_hardening2_capture
7      meta.json fields honoured (CFA) or refused                         test_hardening2_capture, _cfa
8      suite files: schema checked on load                                test_hardening2_bench
9      every option takes effect or is refused                            test_hardening2_commands
10     stored registrations validated, recomputed                         test_hardening2_registration
11     out-of-range data warned about with a count                        test_hardening2_commands
12     late checks and long messages                                      test_hardening2_commands, _messages
=====  =================================================================  ==========================================
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]
ROW_CLASS = re.compile(r"\b(?:Row|Case)\(\s*(?:cls\s*=\s*)?(\d+)\s*,")


def _classes_by_file() -> dict[str, set[int]]:
    return {path.stem: {int(n) for n in ROW_CLASS.findall(path.read_text())}
            for path in sorted(TESTS.glob("*/test_hardening2_*.py"))}


@pytest.mark.parametrize("cls", range(1, 13))
def test_every_class_of_issue_34_has_rows(cls):
    files = [name for name, classes in _classes_by_file().items() if cls in classes]
    assert files, f"class {cls} of issue 34 has no row in tests/*/test_hardening2_*.py"


def test_rows_name_only_the_issues_classes():
    for name, classes in _classes_by_file().items():
        assert classes and classes <= set(range(1, 13)), (name, classes)
