"""One whole `train.py` run, timed phase by phase (wall and CPU seconds), as JSON.

    python benchmarks/whole_run.py OUT.json -- [train.py flags]

Used by `benchmarks/reflow_overhead.py` (one process per variant, back to back). The run is an
ordinary train.py run (build, both stages, evaluation, video); functions are wrapped in place to
attribute its time. Phases (seconds; nested ones are part of their parent):

    load                  argument parsing, dataset loading and checks (build_trainer)
    setup                 initial cloud and model (Trainer.build)
      masks+canonical     ReFlow: motion masks, complete canonical space, keyframe seeds (initial_point_cloud)
    training steps        every train_step, of which the host's phases (trainer.timer) and:
      partner projection  ReFlow pair_mode partner: projecting the partner frames (their deformation
                          is in the view's call: dynamic deformation)
      flow channels       full-flow channels per Gaussian (flow_features)
      flow maps+losses    flow maps, warps and photometric terms, forward (flow_losses)
      dynamic deformation ReFlow's separated deformation forward (keyframe copies, anchored)
      densification pass  the baseline-only gradient pass for the densification statistic
    test events           intermediate evaluations (quick_eval) and saving
    flow evaluation       ReFlow: flow EPE against the ground truth at the end (on_stage_end)
    final evaluation      test views, metrics, novel-time video (finish_run)
    total                 the whole process after imports
"""
from __future__ import annotations

import json
import sys
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from baselines.thread_policy import apply_thread_policy  # noqa: E402

apply_thread_policy()

TIMES: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])  # phase -> [wall, cpu]


def timed(owner, name: str, phase: str) -> None:
    """Wrap owner.name so its wall and CPU time add to `phase`."""
    inner = getattr(owner, name)

    def wrapper(*args, **kwargs):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            TIMES[phase][0] += time.perf_counter() - wall
            TIMES[phase][1] += time.process_time() - cpu

    setattr(owner, name, wrapper)


def instrument() -> None:
    from baselines.fourdgs import app, trainer

    timed(app, "build_trainer", "load")
    timed(app, "finish_run", "final evaluation")
    timed(trainer.Trainer, "build", "setup")
    timed(trainer.Trainer, "train_step", "training steps")
    timed(trainer.Trainer, "quick_eval", "test events")
    timed(trainer.Trainer, "save_point_cloud", "test events")
    timed(trainer.Trainer, "_baseline_screen_grads", "densification pass")
    from baselines.fourdgs import renderer

    prepare = renderer.prepare_view  # prepare_views calls it per camera, with the deformed state

    def prepare_view(model, camera, stage, backend="auto", colors=True, state=None):
        if colors:
            return prepare(model, camera, stage, backend, colors, state)
        wall, cpu = time.perf_counter(), time.process_time()
        view = prepare(model, camera, stage, backend, colors, state)
        TIMES["partner projection"][0] += time.perf_counter() - wall
        TIMES["partner projection"][1] += time.process_time() - cpu
        return view

    renderer.prepare_view = prepare_view
    original_init = trainer.Trainer.__init__

    def init(self, *args, **kwargs):
        original_init(self, *args, **kwargs)
        RUNNING.append(self)

    trainer.Trainer.__init__ = init
    try:
        import reflow_plugin.plugin as plugin
        from reflow_plugin.separation import SeparatedDeformation
    except ImportError:
        return
    timed(plugin.ReFlowPlugin, "initial_point_cloud", "masks+canonical")
    timed(plugin.ReFlowPlugin, "on_stage_end", "flow evaluation")
    timed(plugin, "flow_features", "flow channels")
    timed(plugin, "flow_losses", "flow maps+losses")
    timed(SeparatedDeformation, "forward", "dynamic deformation")


RUNNING: list = []


def main() -> None:
    own = sys.argv[1:sys.argv.index("--")] if "--" in sys.argv else sys.argv[1:]
    if any(a in ("-h", "--help") for a in own):
        print(__doc__)
        sys.exit(0)
    if len(own) != 1 or "--" not in sys.argv:
        sys.exit("whole_run.py: usage: python benchmarks/whole_run.py OUT.json -- [train.py flags] "
                 "(the ratio ReFlow / baseline: benchmarks/reflow_overhead.py)")
    out, argv = Path(own[0]), sys.argv[sys.argv.index("--") + 1:]
    instrument()
    from baselines.fourdgs.app import train_from_argv

    wall, cpu = time.perf_counter(), time.process_time()
    summary = train_from_argv(argv)
    TIMES["total"] = [time.perf_counter() - wall, time.process_time() - cpu]
    trainer = RUNNING[0]
    host = dict(trainer.timer.total)  # seconds per host phase of train_step
    mean = summary.evaluation.mean if summary.evaluation is not None else {}
    out.write_text(json.dumps({"phases": dict(TIMES), "host_phases": host, "iterations": trainer.ctx.iteration,
                               "gaussians": trainer.ctx.model.num_gaussians,
                               "psnr": mean.get("PSNR"), "psnr_dynamic": mean.get("PSNR-dynamic")}, indent=1))


if __name__ == "__main__":
    main()
