"""benchmarks/cli.py: the split at the first "--" every benchmark script uses."""
from benchmarks.cli import split_passthrough


def test_everything_after_the_first_double_dash_is_passed_unread():
    assert split_passthrough(["--iters", "2", "--", "-s", "x", "--", "y"]) == (["--iters", "2"], ["-s", "x", "--", "y"])
    assert split_passthrough(["--iters", "2"]) == (["--iters", "2"], [])
    assert split_passthrough(["--"]) == ([], [])
    argv = ["a", "--", "b"]
    own, passed = split_passthrough(argv)
    own.append("c")
    assert argv == ["a", "--", "b"]  # the caller's list is not changed
