"""Share of ReFlow's coarse-stage camera-flow pixels that lie on the moving object (issue 25, item 15).

    python benchmarks/coarse_camera_flow.py [--scene skating] [--pairs 20]

In the coarse stage the dynamic Gaussians are hidden, so the rendered dynamic-ness channel calls
every covered pixel static. Per sampled training pair (both directions) this prints how many of
the pixels camera-flow matching uses would be inside view a's motion mask, or sample view b's
mask, without the motion masks (before the fix) and with them (now: 0 by construction).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="skating")
    parser.add_argument("--pairs", type=int, default=20)
    args = parser.parse_args()
    from baselines.fourdgs.app import REPO_ROOT, build_trainer
    from baselines.synthetic import get_scene, simulate
    from reflow_plugin.matching import pair_losses
    from reflow_plugin.warp import backward_warp

    scene = Path(tempfile.mkdtemp()) / args.scene
    simulate(get_scene(args.scene), scene, progress=False)
    trainer = build_trainer(["-s", str(scene), "-m", str(scene.parent / "run"), "--plugin", "reflow", "--quiet",
                             "--disable", "comp_init,full_flow", "--cam_flow_min_motion", "0", "--pair_mode", "both",
                             "--configs", str(REPO_ROOT / "arguments" / "synthetic" / "default.py")])
    trainer.build()
    trainer._begin_stage("coarse", 1)
    plugin, ctx = trainer.hooks.plugins[0], trainer.ctx
    ctx.iteration = 1
    before = after = total = 0
    with torch.no_grad():
        for _ in range(args.pairs):
            ctx.batch = plugin.select_batch(ctx)
            ctx.views = trainer_views(trainer, ctx)
            masks = [plugin.mask_tensors[view.camera.uid].bool() for view in ctx.views]
            for moving, counter in ((None, "before"), (masks, "after")):
                result = pair_losses(ctx.views, plugin.config, False, True, moving=moving)
                for k, direction in enumerate(result.directions):
                    landed, _ = backward_warp(masks[1 - k].float().unsqueeze(-1), direction.cam_flow)
                    on_object = direction.static & (masks[k] | (landed[..., 0] > 0))
                    if counter == "before":
                        before += int(on_object.sum())
                        total += int(direction.static.sum())
                    else:
                        after += int(on_object.sum())
    print(f"{args.scene}: {args.pairs} pairs, {total} camera-flow pixels without the masks; on the moving object: "
          f"{before} ({100.0 * before / max(total, 1):.1f}%) before, {after} with the masks")
    trainer.run_log.close()
    return 0


def trainer_views(trainer, ctx):
    """The batch's views composited with the plugin's channels, as train_step does."""
    from baselines.fourdgs.renderer import composite_view, prepare_view

    views = [prepare_view(ctx.model, cam, ctx.stage, trainer.pipe.backend) for cam in ctx.batch]
    ctx.views = views
    for k, view in enumerate(views):
        composite_view(view, ctx.background, trainer.hooks.merged("extra_features", ctx, k, prefix=False),
                       trainer.pipe.backend)
    return views


if __name__ == "__main__":
    sys.exit(main())
