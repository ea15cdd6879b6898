"""Shared test set-up: headless plotting, figures closed after each test, and which tests
count as slow (``make test-fast`` runs ``-m "not slow"``; ``make test`` runs them all)."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("TQDM_DISABLE", "1")

import pytest  # noqa: E402

#: Tests that take 0.5 s or more each, by file (a name covers all its parametrisations).
#: Measured in session 20 over the whole ``-m "not slow"`` set on the shared 2-core machine:
#: per test, wall time less the time its thread waited for a CPU (``/proc`` schedstat) - an
#: upper bound on its time on an idle machine. They are the end-to-end and inherently slow
#: ones: CLI runs of whole commands, fresh interpreters (import checks, examples,
#: ``nodlidar emulate``), emulator streams paced in real time, calibration fits and reports
#: on simulated captures, Dask clusters, fuzzers, first imports of open3d/rosbags. What is
#: left (~680 tests) takes ~28 s of CPU with collection: ``make test-fast`` ~30 s when idle.
#: A name that matches no test only makes ``make test-fast`` slower; a whole-suite run warns.
SLOW_TESTS: dict[str, tuple[str, ...]] = {
    "test_bag.py": (
        "test_round_trip_with_rosbags_reader",
    ),
    "test_bench_harness.py": (
        "test_cli_parser_imports_no_numpy",
        "test_failing_benchmark_and_bad_arguments",
    ),
    "test_calibration.py": (
        "test_bound_hit_is_reported",
        "test_bounds_from_the_design_file",
        "test_calibrate_from_recordings_end_to_end",
        "test_calibrated_beam_model_puts_points_on_the_wall",
        "test_capture_from_runtime_scans_and_nod_samples",
        "test_cli_json_on_simulated_sensor",
        "test_cli_live_guided_capture_on_the_simulated_sensor",
        "test_cli_paper_model_is_refused_by_the_gates",
        "test_cli_sim_distance_per_wall",
        "test_cli_walls_from_capture_files",
        "test_noise_free_data_recovers_the_truth",
        "test_paper_model_cannot_fit",
        "test_refuses_ill_conditioned_fit",
        "test_sigma_matches_the_scatter_over_seeds",
        "test_simulated_sensor_table1_recovered",
        "test_simulated_sensor_walls_at_mixed_distances",
    ),
    "test_calibration_room.py": (
        "test_ambiguous_beams_cover_the_map_errors_and_the_runtime_drops_them",
        "test_full_covariance_in_the_file_and_json",
        "test_range_offset_alone_has_no_bias",
    ),
    "test_cli_conventions.py": (
        "test_bare_nodlidar_prints_help_and_exits_2",
        "test_report_json",
    ),
    "test_cli_design.py": (
        "test_console_script_has_no_traceback",
        "test_default_design_is_found_from_any_directory",
        "test_design_table_and_json",
        "test_import_nodlidar_stays_light",
        "test_out_is_refused_when_it_exists_unless_forced",
    ),
    "test_cloud_io.py": (
        "test_open3d_reads_points_and_fields",
    ),
    "test_dxl_emulator.py": (
        "test_driver_over_tcp_and_pty",
        "test_nod_ramp_follows_profile",
        "test_sdk_ping_and_model_number",
    ),
    "test_emulate_cli.py": (
        "test_emulate_port_in_use_is_one_line",
        "test_emulate_refuses_bad_options_in_one_line",
    ),
    "test_examples.py": (
        "test_calibrate_recovers_table_i",
        "test_design_sweep_table",
    ),
    "test_fuzz_dxl.py": (
        "test_decode_packet_raises_only_protocol_error",
        "test_emulator_answers_anything_without_raising",
        "test_instruction_packets_round_trip",
        "test_item_values_round_trip_or_typed_error",
        "test_parser_only_typed_errors_bounded_buffer_and_finds_valid_frames",
        "test_status_packets_round_trip",
        "test_stuffing_round_trips",
    ),
    "test_fuzz_scip.py": (
        "test_framer_bounded_and_resyncs_after_any_junk",
        "test_mutation_corpus_checksum_invisible_substitutions",
        "test_parse_reply_raises_only_protocol_error",
    ),
    "test_lift_angle.py": (
        "test_emulate_reports_the_design_lift_angles",
        "test_servo_math_imports_without_pyserial",
        "test_session_capture_lifted_at_the_design_angle",
        "test_simulated_servos_reach_the_design_lift_and_the_assembly_calls_them_lifted",
    ),
    "test_public_api.py": (
        "test_import_nodlidar_and_its_names_list_stay_light",
        "test_names_imported_across_modules_are_declared",
    ),
    "test_report.py": (
        "test_drift_figures_have_a_panel_for_every_mirror",
        "test_import_stays_light",
        "test_report_default_out_dir",
        "test_report_files_exist",
    ),
    "test_runtime_cli.py": (
        "test_commands_with_explicit_ports",
        "test_info_simulated",
        "test_plausibility_filter_reaches_the_driver",
        "test_record_replay_same_cloud",
        "test_record_seconds_and_frames",
        "test_sweep_matches_ground_truth",
        "test_sweep_with_mirrors_lifted",
    ),
    "test_scip_codec.py": (
        "test_verify_block_every_single_byte_change_as_the_per_line_reference",
    ),
    "test_scip_emulator.py": (
        "test_faults_garble_but_framer_never_yields_corrupt",
        "test_tcp_timestamps_rate_1",
    ),
    "test_sim_sensor.py": (
        "test_device_error_codes_for_no_return_far_and_near",
        "test_emulate_command_prints_urls_and_serves",
        "test_nodding_head_scans_see_the_ramp_beam_by_beam",
        "test_noise_and_perturbations_reach_the_wire",
        "test_runtime_drivers_against_the_simulated_sensor",
    ),
    "test_solver.py": (
        "test_each_core_module_imports_alone_in_a_fresh_interpreter",
    ),
    "test_tolerance.py": (
        "test_existing_cluster_by_address",
        "test_identical_with_one_or_two_dask_workers",
        "test_own_cluster_workers_keep_glibc_malloc_defaults",
        "test_reproducible_from_seed_and_chunked",
    ),
    "test_tracking.py": (
        "test_cli_study_writes_outputs",
        "test_scanpoints_is_neutral_and_live_path_does_not_import_the_simulated_source",
        "test_segmentation_and_motion_on_synthetic_scene",
    ),
    "test_tracking_recording.py": (
        "test_live_scans_equal_the_whole_capture_assembled_at_once",
        "test_live_scans_with_pruned_samples_equal_the_whole_capture",
        "test_recording_becomes_scan_points",
        "test_track_live_simulated_sensor",
        "test_track_recording_json",
    ),
    "test_tracking_study.py": (
        "test_final_estimates_within_paper_bounds",
        "test_robot_driving_with_known_pose",
    ),
    "test_urg_driver.py": (
        "test_disconnect_and_recover",
        "test_drop_count_exact_with_slow_consumer",
        "test_garbled_and_dropped_bytes",
        "test_garbled_pp_is_asked_again_vv_is_tolerated_with_a_warning",
        "test_gives_up_when_device_stays_away",
        "test_lost_md_acknowledgement_is_not_fatal",
        "test_plausibility_filter_in_the_driver",
        "test_port_that_never_answers",
        "test_power_cycle_resyncs_clock_and_counts_the_outage",
        "test_random_faults_everywhere",
        "test_stall",
        "test_statuses_inside_a_stream_are_resynced",
        "test_stream_finite_interval_cluster",
        "test_stream_n_scans",
        "test_sync_clock_and_stamps",
        "test_timestamp_unwraps_beyond_24_bits",
    ),
    "test_validation.py": (
        "test_scheduler_refusals_are_quick_and_name_the_address",
    ),
    "test_wheel.py": (
        "test_wheel_contents",
    ),
}

#: Module-scoped fixtures that take seconds (a whole report, a tracking study, a calibration
#: fit on simulated walls, a recorded session): every test using one is slow, whichever of
#: them happens to run first and pay for it.
SLOW_FIXTURES: dict[str, tuple[str, ...]] = {
    "test_calibration.py": ("sim_result",),
    "test_calibration_room.py": ("table1_fit",),
    "test_report.py": ("report_dir",),
    "test_tracking_recording.py": ("recording",),
    "test_tracking_study.py": ("renyi_study",),
    # whole simulated scenes through the live tracker (0.7-2 s a test)
    "test_tracking_apart.py": ("scene_runs",),
    "test_tracking_gaps.py": ("scene_runs",),
    "test_tracking_occluded.py": ("scene_runs",),
    "test_tracking_cut.py": ("scene_runs",),
    "test_tracking_round.py": ("scene_runs",),
    "test_tracking_furniture.py": ("scene_runs",),
}

#: Files every test of which is slow by construction (a module-level ``cad`` mark, and no
#: marks but ``cad``/``slow``): when ``-m`` deselects those tests the file is not even
#: imported - test_cad.py's cadquery import alone costs 2-4 s of a ``make test-fast``.
SLOW_FILES = ("test_cad.py",)


def _deselects_slow(config: pytest.Config) -> bool:
    """``-m`` leaves out a test marked slow (and cad), e.g. ``make test-fast``'s ``not slow``."""
    expr = config.getoption("markexpr", "")
    if not expr:
        return False
    try:
        from _pytest.mark.expression import Expression
    except ImportError:  # pragma: no cover - a pytest that moved it: just collect the file
        return False
    return not Expression.compile(expr).evaluate(lambda name, **_: name in ("slow", "cad"))


def pytest_ignore_collect(collection_path, config):
    if collection_path.name in SLOW_FILES and _deselects_slow(config):
        return True
    return None


class SceneRuns:
    """The live tracker on a scene of ``design/scenes`` with the paper's design (solved
    once): ``scene_runs(name, scans, seed, mirrors, segment=None, **tracker_config)``
    (``segment``: a dict of :class:`~nodlidar.tracking.segment.SegmentConfig` fields) returns
    :func:`nodlidar.tracking.evaluate.evaluate`'s per-mover rows by mover name."""

    def __init__(self):
        from nodlidar.paper import PAPER_DESIGN
        from nodlidar.solver import solve
        from nodlidar.spec import load_design

        self.design = solve(load_design(PAPER_DESIGN))

    def __call__(self, name: str, scans: int, seed: int, mirrors: bool,
                 segment: dict | None = None, **tracker) -> dict:
        from nodlidar.sim.scene import load_scene
        from nodlidar.tracking.evaluate import evaluate, run_online
        from nodlidar.tracking.segment import SegmentConfig
        from nodlidar.tracking.tracker import TrackerConfig

        scene = load_scene(Path(__file__).resolve().parents[1] / "design" / "scenes" / name)
        res = run_online(self.design, scene, scans, mirrors_deployed=mirrors, seed=seed,
                         tracker=TrackerConfig(**tracker),
                         segment=SegmentConfig(**(segment or {})))
        return {m["mover"]: m for m in evaluate(res)["movers"]}

    @staticmethod
    def assert_kept(movers: dict, tentative_ok: bool = False) -> None:
        """Each mover kept one track of its own (no switch, purity >= 0.99), converged,
        with the final velocity within the issue's tolerances (0.03 m/s, 5 deg).
        ``tentative_ok``: tracks never confirmed (never reported) aside."""
        from nodlidar.tracking.evaluate import HEADING_TOL_DEG, V_TOL_M_S

        for m in movers.values():
            tracks = [t for t in m["tracks"] if not (tentative_ok and t in m["tentative_tracks"])]
            assert m["id_switches"] == 0 and len(tracks) == 1 and m["purity"] >= 0.99, m
            assert m["conv"] is not None, m
            assert abs(m["final_err_v_m_s"]) <= V_TOL_M_S, m
            assert abs(m["final_err_heading_deg"]) <= HEADING_TOL_DEG, m
        tracks = [[t for t in m["tracks"] if not (tentative_ok and t in m["tentative_tracks"])][0]
                  for m in movers.values()]
        assert len(set(tracks)) == len(tracks), movers


@pytest.fixture(scope="session")
def scene_runs() -> SceneRuns:
    return SceneRuns()


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    import sys

    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Mark slow: CAD exports and notebook runs (tens of seconds each), the tests listed in
    :data:`SLOW_TESTS` and those using a :data:`SLOW_FIXTURES` fixture. Runs first, before
    ``-m``/``-k`` deselect anything."""
    seen = set()
    for item in items:
        path, _, name = item.nodeid.partition("::")
        base = name.partition("[")[0]
        file = path.removeprefix("tests/")
        seen.add((file, base))
        if (item.get_closest_marker("cad") or item.get_closest_marker("notebook")
                or base in SLOW_TESTS.get(file, ())
                or set(SLOW_FIXTURES.get(file, ())) & set(getattr(item, "fixturenames", ()))):
            item.add_marker(pytest.mark.slow)
    # a whole-suite run (no paths given) names the SLOW_TESTS entries that match no test
    if [Path(a).resolve() for a in config.args] == [config.rootpath / "tests"]:
        stale = [f"{f}::{t}" for f, ts in SLOW_TESTS.items() for t in ts if (f, t) not in seen]
        if stale:
            warnings.warn(pytest.PytestConfigWarning(
                f"tests/conftest.py SLOW_TESTS names no test (renamed?): {', '.join(stale)}"),
                stacklevel=1)
