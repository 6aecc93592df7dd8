"""Command line: ``python -m baselines.synthetic --scene NAME --out DIR`` or ``--list``.

    python -m baselines.synthetic --scene skating --out data/synthetic_real/skating --priors real --scene_scale 50

writes the scene as a real capture would come (priors.py: monocular disparity, no motion masks,
NVIDIA-like world units); ground truth under gt/ stays exact.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

from .scenes import get_scene, list_scenes
from .priors import MODES, Priors
from .simulate import simulate
from .spec import SceneSpec


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (width, height), both positive integers."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise ValueError(f"--size must be WxH with positive integers (e.g. 128x96), got {text!r}")
    width, height = (int(p) for p in parts)
    if width <= 0 or height <= 0:
        raise ValueError(f"--size must be WxH with positive integers (e.g. 128x96), got {text!r}")
    return width, height


class _Parser(argparse.ArgumentParser):
    """Argument errors become ValueError, so every failure is reported as one line."""

    def error(self, message: str):
        raise ValueError(message)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="python -m baselines.synthetic",
        description="Render a synthetic dynamic scene (NVIDIA/DynamicNeRF layout + ground truth).")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--scene", help="name of a built-in scene (see --list)")
    source.add_argument("--spec", type=Path, help="JSON file with a scene spec")
    source.add_argument("--list", action="store_true", help="describe the built-in scenes")
    parser.add_argument("--out", type=Path, help="output directory")
    parser.add_argument("--frames", type=int, help="number of frames (>= 2)")
    parser.add_argument("--size", help="image size WxH, e.g. 128x96")
    parser.add_argument("--seed", type=int, help="random seed (>= 0)")
    parser.add_argument("--priors", default="exact", choices=MODES,
                        help="exact: disparity = 1 / depth and the true motion masks; real: a monocular "
                             "network's disparity (per-frame scale and shift, low-frequency error, soft edges) "
                             "and no motion_masks/ (ground truth under gt/ either way)")
    parser.add_argument("--prior_edge_blur", type=float, default=None, metavar="PX",
                        help="--priors real only: blur of the disparity's depth edges in pixels (default 1.5; 0 = sharp)")
    parser.add_argument("--prior_bias", type=float, default=None, metavar="F",
                        help="--priors real only: size of the disparity's low-frequency error (default 0.05; 0 = none)")
    parser.add_argument("--prior_masks", action="store_true",
                        help="--priors real only: write the exact motion_masks/ as well (a run then uses them)")
    parser.add_argument("--scene_scale", type=float, default=1.0,
                        help="world units: every length x this (NVIDIA-like captures: 50)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def list_lines() -> list[str]:
    """One line per scene: name, effects, description."""
    scenes = list_scenes()
    width = max(len(name) for name in scenes)
    lines = []
    for name, description in scenes.items():
        effects = ",".join(get_scene(name).effect_names) or "-"
        lines.append(f"{name:<{width}}  [{effects}]  {description}")
    return lines


def _load_spec(path: Path) -> SceneSpec:
    try:
        data = json.loads(path.read_text())
    except OSError as err:
        raise ValueError(f"cannot read --spec {path}: {err.strerror}") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"--spec {path} is not valid JSON: {err}") from None
    if isinstance(data, dict) and "spec" in data and "simulator_version" in data:
        data = data["spec"]  # a scene.json written by the simulator
    return SceneSpec.from_dict(data)


def _priors(args: argparse.Namespace) -> Priors:
    """`--priors` with the real mode's knobs overridden (`--prior_edge_blur`, `--prior_bias`, `--prior_masks`)."""
    priors = Priors.parse(args.priors)
    knobs = {"edge_blur_px": args.prior_edge_blur, "bias": args.prior_bias, "masks": True if args.prior_masks else None}
    given = {name: value for name, value in knobs.items() if value is not None}
    if given and priors.exact:
        raise ValueError("--prior_edge_blur, --prior_bias and --prior_masks change --priors real; "
                         "the exact priors have no such error")
    return dataclasses.replace(priors, **given)


def run(argv: Optional[Sequence[str]] = None) -> Path | None:
    """Parse arguments and do the work; raises ValueError on bad input."""
    args = build_parser().parse_args(argv)
    if args.list:
        print("\n".join(list_lines()))
        return None
    if args.out is None:
        raise ValueError("--out is required with --scene/--spec")
    overrides = {"frames": args.frames, "seed": args.seed}
    if args.size is not None:
        overrides["width"], overrides["height"] = parse_size(args.size)
    spec = get_scene(args.scene) if args.scene else _load_spec(args.spec)
    spec = spec.with_overrides(**overrides)
    start = time.perf_counter()
    out = simulate(spec, args.out, progress=not args.quiet, priors=_priors(args), scene_scale=args.scene_scale)
    if not args.quiet:
        print(f"{spec.name}: {spec.frames} frames {spec.width}x{spec.height} "
              f"[{','.join(spec.effect_names)}] priors {args.priors}, scale {args.scene_scale:g} -> {out} "
              f"({time.perf_counter() - start:.1f} s)", file=sys.stderr)
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    try:
        run(argv)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
