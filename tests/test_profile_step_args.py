"""benchmarks/profile_step.py: the baseline twin of a plugin run's arguments."""

from benchmarks.profile_step import baseline_argv


def test_the_plugin_and_its_config_give_way_to_the_family_default():
    argv = ["-s", "data/x", "-r", "4", "--plugin", "reflow", "--configs", "arguments/nvidia/reflow.py", "--eval"]
    assert baseline_argv(argv) == ["-s", "data/x", "-r", "4", "--configs", "arguments/nvidia/default.py", "--eval"]


def test_plain_arguments_and_a_default_config_are_kept():
    argv = ["--plugin=reflow", "--configs", "arguments/synthetic/default.py", "--iterations", "10"]
    assert baseline_argv(argv) == ["--configs", "arguments/synthetic/default.py", "--iterations", "10"]
