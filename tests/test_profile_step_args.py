"""benchmarks/profile_step.py: the baseline twin of a plugin run's arguments."""

from benchmarks.profile_step import baseline_argv


def test_the_plugin_and_its_config_give_way_to_the_family_default():
    argv = ["-s", "data/x", "-r", "4", "--plugin", "reflow", "--configs", "arguments/nvidia/reflow.py", "--eval"]
    assert baseline_argv(argv) == ["-s", "data/x", "-r", "4", "--configs", "arguments/nvidia/default.py", "--eval"]


def test_plain_arguments_and_a_default_config_are_kept():
    argv = ["--plugin=reflow", "--configs", "arguments/synthetic/default.py", "--iterations", "10"]
    assert baseline_argv(argv) == ["--configs", "arguments/synthetic/default.py", "--iterations", "10"]


def test_the_plugin_s_own_flags_and_switches_are_dropped_with_their_values():
    argv = ["-s", "data/x", "--plugin", "reflow", "--static_decoder", "field", "--flow_blur_sigmas", "2", "4",
            "--disable", "cam_flow", "--no-canonical_align", "--lambda_ff=0.5", "--iterations", "10"]
    assert baseline_argv(argv) == ["-s", "data/x", "--iterations", "10"]
