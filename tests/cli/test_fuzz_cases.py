"""Issue 21's numbered cases 1-7 and 9: which test reproduces each and keeps it fixed.

=====  ==========================================================  ==================================================================
case   what the issue found                                        test (module::function)
=====  ==========================================================  ==================================================================
1      ``-p search_radius=1000`` grew to 23 GB                     test_hardening_resources::test_nlstr_search_radius_past_the_image_is_refused
1      the same at the command line, one-line error                test_fuzz_cli::test_issue_cases_are_one_line_errors
1      NLSTR working set past the memory limit                     test_hardening_resources::test_nlstr_working_set_past_the_limit_is_refused
1      ``simulate --psf-sigma-hr-px 1000`` asked for 1.6 TB              test_hardening_resources::test_psf_wider_than_the_image_is_refused
1      ``render --psf airy --f-number 1000`` asked for 44 TB       test_hardening_resources::test_render_refuses_a_huge_airy_psf
1      ``render --size 100000``: MemoryError traceback             test_hardening_resources::test_render_size_past_the_memory_limit_is_refused
1      a forged TIFF header as large as meta.json says             test_fuzz_capture::test_a_forged_huge_tiff_header_is_refused_before_reading
2      12-bit hand-written capture biased                          test_hardening_reconstruct::test_hand_written_levels_reconstruct_as_the_float_twin
2      sensor levels round trip through meta.json                  test_hardening_reconstruct::test_sensor_levels_round_trip_through_meta
3      all-saturated capture gives zeros silently                  test_hardening_reconstruct::test_an_all_saturated_capture_warns_on_the_command_line
3      one saturated aperture gives zeros silently                 test_hardening_reconstruct::test_a_saturated_aperture_is_reported_not_silent
3      ``simulate --shift-max 1000`` leaves channels at 0          test_hardening_resources::test_pose_ranges_are_checked
4      ``-p dt=100`` diverges, ``-p c2=1e30`` FloatingPointError   test_hardening_reconstruct::test_divergence_is_an_error_naming_the_option
4      divergence at the command line                              test_hardening_reconstruct::test_divergence_on_the_command_line_exits_2
4      a horizon across the image                                  test_hardening_reconstruct::test_a_horizon_across_the_image_is_refused
4      ``caps`` output below 0 on a DoLP = 1 scene                 test_physical_validity::test_caps_on_a_fully_polarized_scene_is_never_negative
5      output path under a file, under /sys                        test_hardening_messages::test_output_under_a_file_is_refused_before_any_work
5      output path in a system folder                              test_hardening_messages::test_output_in_a_system_folder_is_refused
5      ``--seed -1`` in simulate and render                        test_hardening_messages::test_negative_seed_is_refused
5      ``render --param cycles=abc``                               test_hardening_messages::test_scene_parameter_of_the_wrong_type_is_refused
5      meta.json a list, ``files: null``, homographies ``"abc"``   test_hardening_messages::test_meta_json_fields_of_the_wrong_type_are_capture_format_errors
5      any meta.json field of any type, any odd TIFF               test_fuzz_capture::test_mutated_meta_json_reads_or_is_a_one_line_error
5      (same)                                                      test_fuzz_capture::test_odd_tiffs_read_or_are_a_one_line_error
5      ``render --preview FILE/p.png`` fails after writing         test_hardening_messages::test_preview_path_is_checked_before_rendering
6      ``--psf-sigma-hr-px -1`` or ``nan`` taken as no PSF               test_fuzz_cli::test_issue_cases_are_one_line_errors
6      ``--scale-max 2``                                           test_hardening_resources::test_pose_ranges_are_checked
6      ``--max-spp 0``                                             test_hardening_resources::test_render_max_spp_is_checked
6      ``--geometry converge=maybe``                               test_hardening_resources::test_geometry_values_are_type_checked
6      ``-p psf_sigma=-1``                                         test_hardening_resources::test_psf_sigma_minus_one_is_the_capture_psf_and_other_negatives_are_refused
6      ``evaluate --min-s0 nan`` writes bare NaN                   test_hardening_resources::test_evaluate_cli_refuses_nan_min_s0
6      ``demosaic --dolp-max -1``                                  test_hardening_resources::test_demosaic_cli_refuses_bad_dolp_max
6      ground truth outside [0, 1]                                 test_hardening_resources::test_ground_truth_outside_unit_range_is_refused
6      every numeric option, odd values                            test_fuzz_cli::test_every_numeric_option_refuses_or_takes_fixed_odd_values
6      (same, drawn values)                                        test_fuzz_cli::test_drawn_odd_values_never_crash_a_command
7      a SIGKILLed writer's ``.OUT.tmp-*`` folder stays            test_hardening_messages::test_a_killed_writers_temporary_folder_is_removed_by_the_next_run
7      ``--dry-run`` accepts ``size: 4096``, ``cycles: {choice}``  test_hardening_messages::test_dry_run_checks_every_drawn_sample
7      a rerun with fewer samples                                  test_hardening_messages::test_a_rerun_with_fewer_samples_is_refused_and_changes_nothing
7      any config value in any field                               test_fuzz_config::test_any_value_in_any_field_loads_or_is_a_one_line_error
9      dark scenes: every method PSNR 100, SSIM 1                  test_hardening_outputs::test_dark_scene_scores_tell_methods_apart_and_fixed_peak_ones_are_unchanged
=====  ==========================================================  ==================================================================
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

#: (case, module, function) of every row of the table above
ROWS = [(case, module, function) for case, module, function in
        re.findall(r"^(\d)\s{2,}.*?\s{2,}(test_\w+)::(test_\w+)$", __doc__, flags=re.MULTILINE)]


def test_the_table_covers_cases_1_to_7_and_9():
    assert {case for case, _, _ in ROWS} == {"1", "2", "3", "4", "5", "6", "7", "9"}


@pytest.mark.parametrize("case, module, function", ROWS, ids=[f"case{c}-{f}" for c, _, f in ROWS])
def test_every_listed_test_exists(case, module, function):
    files = list(Path(__file__).resolve().parents[1].glob(f"*/{module}.py"))
    assert len(files) == 1, f"{module}.py (case {case}): found {files}"
    names = {node.name for node in ast.walk(ast.parse(files[0].read_text())) if isinstance(node, ast.FunctionDef)}
    assert function in names, f"{module}::{function} (case {case})"
