"""`python -m baselines.export`: see baselines/export/cli.py."""
from baselines.thread_policy import apply_thread_policy

apply_thread_policy()  # before torch starts

from baselines.export.cli import main  # noqa: E402
from baselines.fourdgs.app import run_cli  # noqa: E402

run_cli(main)
