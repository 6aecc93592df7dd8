"""Bad and odd inputs through the public command lines: how many end with one clean line.

    python benchmarks/bad_inputs.py [--root CHECKOUT] [--jobs 2] [--only-table]

Runs tests/test_bad_inputs.py's table plus the extra cases below (inputs that were already refused
cleanly before issue 25; kept here, not in the test suite, to keep CI short) on a 32x32 simulator
scene, each in a subprocess, and prints per case: seconds, exit code, whether the output was clean
(exit 2, exactly one ``error:`` line, no traceback, output folder untouched or absent; for the
full-disk case: no half-written iteration folder) and the error line. ``--root`` runs the same
inputs against another checkout (e.g. ``git -C /work/main archive HEAD | tar -x -C /tmp/main``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def extra_cases(Case, train, short):  # noqa: N803  (the table's Case class and helpers)
    """Inputs refused cleanly already before issue 25 (the issue's survey); same checks."""
    def write(path: Path, text: str) -> Path:
        path.write_text(text)
        return path

    def nan_pose(scene: Path) -> None:
        poses = np.load(scene / "poses_bounds.npy")
        poses[3, 4] = np.nan
        np.save(scene / "poses_bounds.npy", poses)

    def corrupt_image(scene: Path) -> None:
        sorted((scene / "images").iterdir())[2].write_bytes(b"\x89PNG not really")

    def drop_image(scene: Path) -> None:
        sorted((scene / "images").iterdir())[-1].unlink()

    out = lambda w: str(w / "out")  # noqa: E731
    return [
        Case("unknown flag", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--iteratons", "5"), "--iteratons"),
        Case("unknown plugin", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--plugin", "nope"), "nope"),
        Case("unknown component", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--plugin", "reflow",
                                                     "--disable", "fullflow"), "fullflow"),
        Case("unknown config key", lambda s, w: train("-s", str(s), "-m", out(w), *short[2:], "--configs",
                                                      str(write(w / "c.py", "OptimizationParams = dict(iteratons=3)\n"))),
             "iteratons"),
        Case("config file missing", lambda s, w: train("-s", str(s), "-m", out(w), *short[2:], "--configs",
                                                       str(w / "none.py")), "none.py"),
        Case("bad flag value", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--iterations", "many"),
             "--iterations"),
        Case("missing source folder", lambda s, w: train("-s", str(w / "nothing"), "-m", out(w), *short), "nothing"),
        Case("NaN pose", lambda s, w: (nan_pose(s), train("-s", str(s), "-m", out(w), *short))[1], "non-finite"),
        Case("corrupt image", lambda s, w: (corrupt_image(s), train("-s", str(s), "-m", out(w), *short))[1], "002"),
        Case("image/pose count mismatch", lambda s, w: (drop_image(s), train("-s", str(s), "-m", out(w), *short))[1],
             "poses"),
        Case("--device cuda without CUDA", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--device", "cuda"),
             "cuda"),
        Case("render: no model folder", lambda s, w: [str(train()[0]).replace("train.py", "render.py"), "-m", out(w)],
             "out"),
        Case("render: missing -m", lambda s, w: [str(train()[0]).replace("train.py", "render.py")], "-m"),
        Case("prepare: missing video", lambda s, w: ["-m", "baselines.prepare", str(w / "none.mp4"), "-o", out(w)],
             "none.mp4"),
        Case("ablate: unknown row", lambda s, w: ["-m", "reflow_plugin.ablate", "-s", str(s), "-o", out(w), "--rows",
                                                  "nope"], "nope"),
    ]


def clean(result: dict) -> tuple[bool, str]:
    output, case = result["output"], result["case"]
    errors = [line for line in output.splitlines() if "error:" in line]
    ok = result["rc"] == 2 and "Traceback" not in output and len(errors) == 1 and case.expect in errors[0]
    if ok and case.untouched:
        ok = result["after"] == result["before"]
    elif ok:
        folder = result["work"] / case.output / "point_cloud"
        ok = not (folder.is_dir() and any(folder.glob("*iteration_*")))
    return ok, (errors[-1] if errors else (output.strip().splitlines() or ["<no output>"])[-1])[:140]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, help="checkout to run (default: this one)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--only-table", action="store_true", help="the test table only")
    args = parser.parse_args()
    if args.root:
        os.environ["REFLOW_BAD_INPUTS_ROOT"] = str(args.root.resolve())
    from baselines.synthetic import get_scene, simulate
    from tests import test_bad_inputs as table

    cases = list(table.CASES) + ([] if args.only_table else extra_cases(table.Case, table._train, table.SHORT))
    work = Path(tempfile.mkdtemp(prefix="bad_inputs_"))
    scene = work / "tiny"
    simulate(get_scene("balloon", frames=12, width=32, height=32, seed=0), scene, progress=False)
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(lambda ic: table._run_case(ic[1], scene, work / f"case{ic[0]}"), enumerate(cases)))
    wall = time.perf_counter() - start
    print(f"| case | s | exit | clean | last error line |\n|---|---:|---:|---|---|")
    count = 0
    for r in results:
        ok, line = clean(r)
        count += ok
        print(f"| {r['name']} | {r['seconds']:.1f} | {r['rc']} | {'yes' if ok else 'NO'} | {line.replace('|', '/')} |")
    root = os.environ.get("REFLOW_BAD_INPUTS_ROOT", "this checkout")
    print(f"\n{count} of {len(results)} inputs end with one clean error line ({root}); {wall:.0f} s wall, "
          f"{args.jobs} at a time; load {open('/proc/loadavg').read().split()[0]}")
    print(json.dumps({"clean": count, "tried": len(results), "wall_s": round(wall, 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
