"""Bad and odd inputs through the public command lines: how many end with one clean line.

    python benchmarks/bad_inputs.py [--root CHECKOUT] [--jobs 2] [--only-table]

Runs tests/test_bad_inputs.py's table plus the extra cases below (inputs refused cleanly before
issue 25, and issue 41's weak items and odd-but-valid inputs; kept here, not in the test suite, to
keep CI short) on a 32x32 simulator scene, each in a subprocess, and prints per case: seconds, exit
code, whether the outcome was clean and the first line that matters (the ``error:`` line, else the
first line of output). Clean means: exit 2, exactly one ``error:`` line, no traceback, and the
output folder untouched to the byte (a folder holding a finished run included) or absent; for the
full-disk cases: no half-written iteration folder and whole log lines. A case marked "ok" is valid
input: clean means exit 0, no traceback and its outputs where the caller asked. ``--root`` runs the
same inputs against another checkout (e.g. ``git -C /work/main archive HEAD | tar -x -C /tmp/main``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def extra_cases(Case, train, short, table):  # noqa: N803  (the table's Case class and helpers)
    """Inputs refused cleanly already before issue 25 (the issue's survey), then issue 41's."""
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
        *issue41_cases(Case, train, short, table),
    ]


def issue41_cases(Case, train, short, table):  # noqa: N803
    """Issue 41's weak items (each one line now) and valid inputs that must work from any folder."""
    root = table.ROOT
    out = lambda w: str(w / "out")  # noqa: E731

    def two_frames(scene: Path) -> None:
        np.save(scene / "poses_bounds.npy", np.load(scene / "poses_bounds.npy")[:2])
        for folder in ("images", "disp", "motion_masks"):
            for extra in sorted((scene / folder).iterdir())[2:]:
                extra.unlink()

    def foreign_deformation(s: Path, w: Path) -> Path:
        run = table._trained(s, w)
        other = w / "other"  # the same scene and flags, another seed: same shapes, other values
        env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(root))
        subprocess.run([sys.executable, str(root / "train.py"), "-s", str(s), "-m", str(other), *short, "--seed", "5"],
                       cwd=root, env=env, check=True, capture_output=True)
        shutil.copy(other / "point_cloud" / "iteration_1" / "deformation.pth", run / "point_cloud" / "iteration_1")
        return run

    def corrupt_run_json(s: Path, w: Path) -> Path:
        run = table._trained(s, w)
        (run / "run.json").write_text("{")
        return run

    def torn_log(s: Path, w: Path) -> Path:
        run = table._trained(s, w, "--eval")
        with open(run / "train_log.jsonl", "a") as handle:
            handle.write('{"kind": "test", "ite')
        return w

    def ablate_elsewhere(s: Path, w: Path) -> list[str]:
        (w / "elsewhere").mkdir()
        return ["-m", "reflow_plugin.ablate", "-s", str(s), "-o", "rel_out", "--rows", "baseline", "--",
                "--configs", str(root / "arguments" / "synthetic" / "default.py"), "--coarse_iterations", "1",
                "--iterations", "1"]

    elsewhere = {"cwd": lambda w: w / "elsewhere", "ok": "elsewhere/rel_out/ablation.md"}
    return [
        Case("--iterations 0", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--iterations", "0"),
             "--iterations"),
        Case("--seed -1", lambda s, w: train("-s", str(s), "-m", out(w), *short, "--seed", "-1"), "--seed"),
        Case("-s names a file", lambda s, w: train("-s", str(s / "poses_bounds.npy"), "-m", out(w), *short),
             "is a file; -s names the dataset folder"),
        Case("2 frames, --eval, --plugin reflow", lambda s, w: (two_frames(s), train(
            "-s", str(s), "-m", out(w), *short[:-1], "--eval", "--plugin", "reflow"))[1], "--no-eval trains on"),
        Case("-m holds a run with a corrupt run.json", lambda s, w: train(
            "-s", str(s), "-m", str(corrupt_run_json(s, w)), *short), "run.json cannot be read", output="first"),
        Case("render: deformation.pth of another run", lambda s, w: [
            str(root / "render.py"), "-m", str(foreign_deformation(s, w))], "is not the file the run saved",
             output="first"),
        Case("export -o an existing file", lambda s, w: ((w / "f.txt").write_text("x"), [
            "-m", "baselines.export", "-m", str(table._trained(s, w)), "--format", "ply", "--times", "0", "-o",
            str(w / "f.txt")])[1],
             "is a file, not a folder", output="first"),
        Case("export -o into a run's iteration folder", lambda s, w: (lambda run: [
            "-m", "baselines.export", "-m", str(run), "--format", "ply", "--times", "0", "-o",
            str(run / "point_cloud" / "iteration_1")])(table._trained(s, w)), "point_cloud/", output="first"),
        Case("evaluate --images -3", lambda s, w: ["-m", "reflow_plugin.evaluate", "-m", str(table._trained(s, w)),
                                                   "--images", "-3"], "--images must be >= 0", output="first"),
        Case("ok: report on a log with a torn last line", lambda s, w: ["-m", "reflow_plugin.report",
                                                                       str(torn_log(s, w))], "", output="first",
             extra={"ok": "cost.md"}),
        Case("ok: ablate -o REL from another folder", lambda s, w: ablate_elsewhere(s, w), "", output="none",
             extra=elsewhere),
    ]


def clean(result: dict) -> tuple[bool, str]:
    output, case = result["output"], result["case"]
    errors = [line for line in output.splitlines() if "error:" in line]
    first = (errors[0] if errors else (output.strip().splitlines() or ["<no output>"])[0])[:140]
    if "ok" in case.extra:  # valid input: exit 0, its outputs where the caller asked
        return (result["rc"] == 0 and "Traceback" not in output
                and (result["work"] / case.extra["ok"]).is_file()), first
    ok = result["rc"] == 2 and "Traceback" not in output and len(errors) == 1 and case.expect in errors[0]
    if ok and case.untouched:
        ok = result["after"] == result["before"]
    elif ok and case.extra.get("render"):  # render.py on a full disk: the run's log lines stay whole
        lines = (result["work"] / case.output / "train_log.jsonl").read_text().splitlines()
        ok = all(_parses(line) for line in lines)
    elif ok:
        folder = result["work"] / case.output / "point_cloud"
        ok = not (folder.is_dir() and any(folder.glob("*iteration_*")))
    return ok, first


def _parses(line: str) -> bool:
    try:
        json.loads(line)
        return True
    except ValueError:
        return False


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

    cases = list(table.CASES) + ([] if args.only_table else extra_cases(table.Case, table._train, table.SHORT, table))
    work = Path(tempfile.mkdtemp(prefix="bad_inputs_"))
    scene = work / "tiny"
    simulate(get_scene("balloon", frames=12, width=32, height=32, seed=0), scene, progress=False)
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(lambda ic: table._run_case(ic[1], scene, work / f"case{ic[0]}"), enumerate(cases)))
    wall = time.perf_counter() - start
    print(f"| input | s | exit | clean | first line (the error line, if any) |\n|---|---:|---:|---|---|")
    count = 0
    for r in results:
        ok, line = clean(r)
        count += ok
        print(f"| {r['name']} | {r['seconds']:.1f} | {r['rc']} | {'yes' if ok else 'NO'} | {line.replace('|', '/')} |")
    root = os.environ.get("REFLOW_BAD_INPUTS_ROOT", "this checkout")
    print(f"\n{count} of {len(results)} inputs end cleanly (one error line; \"ok\" cases: exit 0) ({root}); {wall:.0f} s wall, "
          f"{args.jobs} at a time; load {open('/proc/loadavg').read().split()[0]}")
    print(json.dumps({"clean": count, "tried": len(results), "wall_s": round(wall, 1)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
