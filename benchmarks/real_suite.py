"""Baseline vs ReFlow on real captures: held-out PSNR/SSIM, PSNR inside the (estimated) motion masks.

    python benchmarks/real_suite.py [--captures nvidia_balloon1,nvidia_balloon1_colmap,davis_lady_running]
                                    [--methods baseline,reflow] [--data data/real] [--out output/real] [--jobs 1]
                                    [--coarse_iterations 300] [--iterations 2000] [--seed 0]
                                    [--resolution NAME=R,...] [--chunk-seconds S]
                                    [--images docs/images] [-- extra train.py flags]
    python benchmarks/real_suite.py --fetch-instructions      # where each capture comes from
    python benchmarks/real_suite.py --setup NAME --clone DIR  # extract (and prepare) one capture

The captures and their sources (repository + commit) are the registry in
`benchmarks/real_captures.py`; a capture missing under `--data` stops the command before any
training with one error that prints how to fetch it. Each (capture, method) is an ordinary
`train.py` run in `OUT/<capture>/<method>` with the family's default config (no `--configs`:
`arguments/nvidia/*` for NVIDIA, `arguments/hypernerf/*` for prepared clips and panoptic), `--eval`
(the family's hold-out: every 8th frame; panoptic: its test camera every 10th timestamp), the same schedule and `--seed` for both methods; ReFlow runs with its defaults
(`--plugin reflow`); `--methods ...,reflow_flow_provider` adds a diagnosis row, ReFlow with its
canonical space built from triangulated optical flow instead of the dataset's `disp/`. A run is done when `real_done.json` exists (written after train.py
succeeded, with the command and the code's commit); a folder without it is a torn run and is
redone, and a folder trained with another command stops the suite (use a fresh `--out` after
changing the schedule or the code you want to measure).

`--chunk-seconds S` (machines that allow short calls only; `benchmarks/gpu_real_suite.sh`): the
runs go `--jobs` at a time; after about S seconds of the call the run in training is stopped with
SIGTERM (train.py checkpoints the iteration it is at and exits 143), the command exits 3, and the
next call continues that run from its latest `chkpnt_*.pth` (`--start_checkpoint`, same command,
same code version: `real_chunks.json` records them with each call's seconds, whose sum is the
run's train_s). A run is never cut before its training loop starts or after it ends (final
evaluation and renders). train_cpu_s is the CPU seconds of the training steps over the whole run
(each checkpoint carries the training clock, so it counts every chunk; empty for a run resumed
from a checkpoint older than that): the time to compare between runs trained beside different loads.

In-mask metrics: the dataset's masks when every held-out view has one (evaluation-only ground
truth first: NVIDIA and prepared clips' `gt/motion_masks/`, e.g. the DAVIS annotations, panoptic
`seg/` carved into the test cameras as a visual hull; else `motion_masks/`, e.g. prepare's auto
masks), else
masks estimated once per capture over ALL frames from DIS flow and the known cameras
(`baselines.data.motion_masks`, epipolar test, cached in `OUT/<capture>/eval_masks/`); the same
masks score both methods. PSNR-mask / PSNR-outside are computed from the saved 8-bit test
renders and ground truth (`test/ours_<N>/{renders,gt}`); PSNR and SSIM are train.py's
(`results.json`). Side-by-side images (ground truth | baseline | ReFlow, the two held-out views
with the most masked pixels) go to `IMAGES/real_<capture>.jpg`. Prints one Markdown table and
writes it with the raw figures to `OUT/real_suite.md` / `OUT/real_suite.json`.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from baselines.run_folder import read_run_record  # noqa: E402
from benchmarks.cli import split_passthrough  # noqa: E402
from benchmarks.real_captures import (CAPTURES, DEFAULT_DATA, Capture, CaptureError, dataset_dir,  # noqa: E402
                                      fetch_instructions, require_ready, select, setup)

METHODS = {
    "baseline": [],
    "reflow": ["--plugin", "reflow"],
    # diagnosis (not run by default): the canonical space from triangulated optical flow instead of disp/
    "reflow_flow_provider": ["--plugin", "reflow", "--canonical_provider", "flow"],
}
DEFAULT_METHODS = ("baseline", "reflow")
DONE_FILE = "real_done.json"
CHUNKS_FILE = "real_chunks.json"  # a chunked run: its command, code and each call's seconds
INTERRUPTED_RC = 143  # train.py after SIGTERM: checkpointed and stopped (baselines/cli_exit.py)
COLUMNS = ("PSNR", "SSIM", "PSNR-mask", "PSNR-outside", "mask %", "train_s", "train_cpu_s", "code", "MLP")
NEAR_PLANE = 0.01  # the rasterizer's default near plane (baselines/render/api.py)


class SuiteError(RuntimeError):
    """A run folder cannot be reused as it is."""


class ChunkPending(SuiteError):
    """A chunked run (--chunk-seconds) stopped at a checkpoint; the next call continues it."""


class TrainingFailed(SuiteError):
    """train.py exited non-zero for one (capture, method); the suite goes on with the others."""


TRAINING_CODE = (".", ":!benchmarks", ":!tests", ":!docs", ":!README.md")  # what a run's figures depend on


def code_version() -> str:
    """Short hash of the last commit that changed the training code (everything but benchmarks/,
    tests/, docs/ and the README), with '+dirty' when that code differs from it."""
    head = subprocess.run(["git", "-C", str(ROOT), "log", "-1", "--format=%h", "--abbrev=10", "--", *TRAINING_CODE],
                          capture_output=True, text=True)
    if head.returncode != 0 or not head.stdout.strip():
        return "unknown"
    dirty = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", "HEAD", "--", *TRAINING_CODE], capture_output=True)
    return head.stdout.strip() + ("+dirty" if dirty.returncode else "")


def train_command(capture: Capture, method: str, source: Path, run: Path, schedule: dict, extra: list[str]) -> list[str]:
    """The train.py argument list of one (capture, method): same schedule and seed for every method."""
    return ["train.py", "-s", str(source), "-m", str(run), "-r", str(capture.resolution), "--eval",
            "--coarse_iterations", str(schedule["coarse_iterations"]), "--iterations", str(schedule["iterations"]),
            "--seed", str(schedule["seed"]), "--quiet", *METHODS[method], *extra]


def run_one(capture: Capture, method: str, data_root: Path, out: Path, schedule: dict, extra: list[str],
            threads: int, run: Path | None = None, chunk_seconds: float | None = None) -> Path:
    """Train one (capture, method) unless its run folder (default OUT/<capture>/<method>) is done;
    returns the run folder. Its lock and log sit next to it: <run>.lock, <run>_train.log.

    With `chunk_seconds`, the training is stopped (SIGTERM: train.py checkpoints the iteration it
    is at and exits) once it has trained that long, and ChunkPending is raised; the next call
    continues from the latest checkpoint (`--start_checkpoint`) instead of redoing the folder."""
    run = out / capture.name / method if run is None else run
    command = train_command(capture, method, dataset_dir(capture, data_root), run, schedule, extra)
    done = run / DONE_FILE
    if done.is_file():
        stored = json.loads(done.read_text())
        if stored.get("command") != command:
            raise SuiteError(f"{run} was trained with another command ({' '.join(stored.get('command', []))}); "
                             "use a fresh --out or delete that folder")
        return run
    lock = run.parent / f"{run.name}.lock"
    log_file = run.parent / f"{run.name}_train.log"
    owner = _live_owner(lock)
    if owner is not None:
        raise SuiteError(f"{run} is being trained by process {owner} (another real_suite.py); wait for it")
    chunks_file = run / CHUNKS_FILE
    checkpoint = latest_checkpoint(run) if chunk_seconds is not None and chunks_file.is_file() else None
    if checkpoint is not None:  # a chunked run stopped at a checkpoint: continue it with the same command
        chunks = json.loads(chunks_file.read_text())
        if chunks["command"] != command:
            raise SuiteError(f"{run} was started with another command ({' '.join(chunks['command'])}); "
                             "use a fresh --out or delete that folder")
        code = chunks["code"]
        if code_version() != code:
            raise SuiteError(f"{run} was started with code {code}, the checkout is now {code_version()}; "
                             "resume with that code, or delete the folder")
    else:
        if run.exists():  # torn: a killed or failed earlier attempt
            shutil.rmtree(run)
        run.mkdir(parents=True)
        code = code_version()  # the code that trains, before anyone edits the checkout
        chunks = {"command": command, "code": code, "chunks": []}
    lock.write_text(str(os.getpid()))
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    if chunk_seconds is None:
        with open(log_file, "w") as log:
            result = subprocess.run([sys.executable, *command], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
        returncode = result.returncode
    else:
        resume = ["--start_checkpoint", str(checkpoint)] if checkpoint is not None else []
        with open(log_file, "a") as log:
            returncode, seconds = train_chunk([sys.executable, *command, *resume], env, log, run / "train_log.jsonl",
                                              chunk_seconds)
        chunks["chunks"].append({"from": str(checkpoint) if checkpoint else None, "seconds": seconds,
                                 "returncode": returncode})
        (run / CHUNKS_FILE).write_text(json.dumps(chunks, indent=1))
    lock.unlink(missing_ok=True)
    if chunk_seconds is not None and returncode == INTERRUPTED_RC and latest_checkpoint(run) is not None:
        raise ChunkPending(f"{run}: stopped at {latest_checkpoint(run).name} after {chunk_seconds:.0f} s; "
                           "call again to continue")
    if returncode != 0:
        lines = log_file.read_text().strip().splitlines()
        errors = [line for line in lines if line.startswith("error:")]  # train.py's one-line reason
        reason = errors[-1] if errors else " | ".join(lines[-3:])
        raise TrainingFailed(f"train.py exited {returncode}: {reason} (log: {log_file})")
    tmp = run / (DONE_FILE + ".tmp")
    tmp.write_text(json.dumps({"command": command, "code": code}, indent=1))
    tmp.replace(done)
    return run


def latest_checkpoint(run: Path) -> Path | None:
    """The run's chkpnt_<stage>_<N>.pth furthest into training (fine after coarse), None when none."""
    found = []
    for path in run.glob("chkpnt_*_*.pth"):
        _, stage, number = path.stem.split("_", 2)
        if stage in ("coarse", "fine") and number.isdigit():
            found.append(((stage == "fine", int(number)), path))
    return max(found)[1] if found else None


def train_chunk(command: list[str], env: dict, log, train_log: Path, seconds: float,
                poll: float = 0.1) -> tuple[int, float]:
    """Run train.py; once `seconds` have passed AND its training loop is running (a new "iter" line
    in `train_log`: its SIGTERM handler is installed) AND it has not finished training ("train_end"),
    send SIGTERM, which makes it checkpoint the current iteration and exit INTERRUPTED_RC.
    Returns (exit status, wall seconds)."""
    offset = train_log.stat().st_size if train_log.is_file() else 0  # earlier chunks' lines
    start = time.monotonic()
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    signalled = False
    while process.poll() is None:
        time.sleep(poll)
        if signalled or time.monotonic() - start < seconds or not train_log.is_file():
            continue
        with open(train_log, "rb") as handle:
            handle.seek(offset)
            new = handle.read()
        if b'"kind": "train_end"' in new:  # training is over: let the evaluation finish
            process.wait()
            break
        if b'"kind": "iter"' in new:
            process.send_signal(signal.SIGTERM)
            signalled = True
    return process.wait(), time.monotonic() - start


def _live_owner(lock: Path) -> int | None:
    """The pid recorded in `lock` when that process still runs, else None (a stale lock)."""
    try:
        pid = int(lock.read_text().strip())
        os.kill(pid, 0)
    except (OSError, ValueError):
        return None
    return pid


def latest_test_dir(run: Path) -> Path:
    dirs = sorted((run / "test").glob("ours_*"), key=lambda p: int(p.name.split("_")[1]))
    if not dirs:
        raise SuiteError(f"no test renders under {run / 'test'}")
    return dirs[-1]


def load_capture(capture: Capture, data_root: Path):
    """The capture's SceneInfo at the benchmark's resolution, with the family's hold-out."""
    from baselines.data.loader import load_scene

    return load_scene(dataset_dir(capture, data_root), resolution=capture.resolution, eval=True)


def eval_masks(capture: Capture, scene, out: Path) -> list[np.ndarray]:
    """[H, W] bool motion mask per held-out view (test order), the dataset's masks or estimated (cached)."""
    from baselines.data.motion_masks import estimate_motion_masks

    folder = out / capture.name / "eval_masks"
    tests = scene.test_cameras
    if all(c.evaluation_mask is not None for c in tests):  # the dataset's (training or evaluation-only) masks
        return [c.evaluation_mask.cpu().numpy() > 0.5 for c in tests]
    paths = [folder / f"{c.image_name}.png" for c in tests]
    cached = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) if p.is_file() else None for p in paths]
    if all(m is not None and m.shape == (c.height, c.width) for m, c in zip(cached, tests)):
        return [m > 127 for m in cached]
    frames = sorted(scene.train_cameras + tests, key=lambda c: (c.time, c.frame_index))
    masks, _ = estimate_motion_masks([c.image.cpu().numpy() for c in frames],
                                     [c.K.double().cpu().numpy() for c in frames],
                                     [c.viewmat.double().cpu().numpy() for c in frames])
    by_name = {c.image_name: m for c, m in zip(frames, masks)}
    folder.mkdir(parents=True, exist_ok=True)
    for name, mask in by_name.items():
        cv2.imwrite(str(folder / f"{name}.png"), mask.astype(np.uint8) * 255)
    return [by_name[c.image_name] for c in tests]


def _ply_points(path: Path) -> np.ndarray:
    from plyfile import PlyData

    vertex = PlyData.read(str(path))["vertex"]
    return np.stack([vertex["x"], vertex["y"], vertex["z"]], 1).astype(np.float64)


def camera_depths(points: np.ndarray, camera) -> tuple[np.ndarray, np.ndarray]:
    """(depth z [P], inside [P] bool: in front of the camera and projecting inside the image)."""
    viewmat, K = camera.viewmat.double().cpu().numpy(), camera.K.double().cpu().numpy()
    cam = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    safe = np.where(np.abs(z) > 1e-12, z, 1e-12)
    u, v = K[0, 0] * cam[:, 0] / safe + K[0, 2], K[1, 1] * cam[:, 1] / safe + K[1, 2]
    return z, (z > 0) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)


def canonical_check(run: Path, scene) -> dict | None:
    """Where ReFlow's initial clouds (`reflow/static.ply`, `dynamic.ply`) lie, against the scene.

    static depth / scene depth: median depth of the static points that project into the training
    views over the scene's reference depth (the dataset's points, else sqrt(near * far) of its
    bounds); static in view: mean over training cameras of the fraction of static points inside
    the image and beyond the rasterizer's near plane (what can render at all); dynamic spread: std of the dynamic points over the scene depth
    (about 0 = collapsed to one position). None for a run without those files."""
    static_file, dynamic_file = run / "reflow" / "static.ply", run / "reflow" / "dynamic.ply"
    if not static_file.is_file():
        return None
    static = _ply_points(static_file)
    cams = scene.train_cameras
    if scene.point_cloud is not None and len(scene.point_cloud.points):
        reference = float(np.median(np.concatenate(
            [z[inside] for z, inside in (camera_depths(scene.point_cloud.points.astype(np.float64), c) for c in cams)])))
        source = "dataset points"
    elif scene.near_far is not None:
        reference, source = float(np.sqrt(scene.near_far[0] * scene.near_far[1])), "bounds"
    else:
        return None
    seen = [camera_depths(static, c) for c in cams]
    inside_depths = np.concatenate([z[inside] for z, inside in seen]) if seen else np.zeros(0)
    check = {"reference_depth": reference, "reference": source,
             "static depth / scene depth": float(np.median(inside_depths)) / reference if len(inside_depths) else None,
             "static in view %": 100.0 * float(np.mean([(inside & (z > NEAR_PLANE)).mean() for z, inside in seen]))}
    if dynamic_file.is_file():
        dynamic = _ply_points(dynamic_file)
        check["dynamic spread"] = float(np.linalg.norm(dynamic.std(0))) / reference if len(dynamic) else None
    return check


def region_psnr(render: np.ndarray, gt: np.ndarray, region: np.ndarray) -> float | None:
    """PSNR (peak 255) over the pixels of `region` ([H, W] bool) of two [H, W, 3] uint8 images;
    None for an empty region, +inf for identical pixels."""
    if not region.any():
        return None
    diff = render[region].astype(np.float64) - gt[region].astype(np.float64)
    mse = float(np.mean(diff ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


def check_rendered_views(test_dir: Path, count: int, names: list[str] | None) -> None:
    """The numbered PNGs of `test_dir` are the `count` held-out views named `names` (test order).

    Masks pair with renders by position, so a render folder of another split (a capture prepared
    again, a changed hold-out) would be scored against the wrong masks without a word. Runs older
    than `views.json` are checked by count only. SuiteError otherwise."""
    from baselines.fourdgs.evaluate import VIEWS_FILE

    rendered = len(list((test_dir / "renders").glob("*.png")))
    if rendered != count:
        raise SuiteError(f"{test_dir}: {rendered} rendered views for {count} held-out views (masks)")
    views_file = test_dir / VIEWS_FILE
    if names is None or not views_file.is_file():
        return
    recorded = json.loads(views_file.read_text())
    for index, name in enumerate(names):
        png = f"{index:05d}.png"
        if recorded.get(png) != name:
            raise SuiteError(f"{views_file}: {png} renders {recorded.get(png)!r}, the held-out view with this "
                             f"mask is {name!r}: the run was evaluated on another split")


def masked_metrics(run: Path, masks: list[np.ndarray], names: list[str] | None = None) -> dict[str, float | None]:
    """Mean over held-out views of PSNR inside / outside the masks, from the saved renders.

    `names`: the held-out views' image names in test order, checked against the run's record of
    what each PNG shows (check_rendered_views)."""
    if not masks:  # nothing to score inside or outside
        return {"PSNR-mask": None, "PSNR-outside": None}
    test_dir = latest_test_dir(run)
    check_rendered_views(test_dir, len(masks), names)
    inside, outside = [], []
    for index, mask in enumerate(masks):
        name = f"{index:05d}.png"
        render, gt = cv2.imread(str(test_dir / "renders" / name)), cv2.imread(str(test_dir / "gt" / name))
        if render is None or gt is None:
            raise SuiteError(f"missing {test_dir}/renders or gt/{name}")
        if mask.shape != gt.shape[:2]:
            raise SuiteError(f"mask {mask.shape} vs render {gt.shape[:2]} for {test_dir / 'gt' / name}")
        for values, region in ((inside, mask), (outside, ~mask)):
            value = region_psnr(render, gt, region)
            if value is not None:
                values.append(value)
    return {"PSNR-mask": float(np.mean(inside)) if inside else None,
            "PSNR-outside": float(np.mean(outside)) if outside else None}


def mlp_arithmetic_of(run: Path) -> str | None:
    """The deformation MLP's arithmetic the run trained with (run.json's machine record; None for
    runs older than that record). `--mlp_precision auto` picks it per CPU, so it belongs beside
    the figures: two machines can train the same command differently."""
    record = read_run_record(run) or {}
    return (record.get("machine") or {}).get("mlp_arithmetic")


def train_cpu_seconds(log: list[dict]) -> float | None:
    """CPU seconds of the training steps over the whole run (evaluation, saving and start-up
    excluded; less sensitive than wall seconds to what else the machine runs), from its
    train_log.jsonl records; None when a chunk resumed from a checkpoint without the training
    clock (written before it was saved) or the run has not ended."""
    ends = [r for r in log if r.get("kind") == "train_end"]
    if not ends or any(r.get("kind") == "resumed" and not r.get("clock_restored") for r in log):
        return None
    return ends[-1].get("train_cpu_seconds")


def _test_names(scene) -> list[str] | None:
    return None if scene is None else [c.image_name for c in scene.test_cameras]


def summarise(run: Path, masks: list[np.ndarray], scene) -> dict:
    """The figures of one finished run."""
    results = json.loads((run / "results.json").read_text())
    key = max((k for k in results if k.startswith("ours_")), key=lambda k: int(k.split("_")[1]))
    log = [json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines() if line.strip()]
    end = [r for r in log if r.get("kind") == "train_end"]
    chunks = run / CHUNKS_FILE
    if chunks.is_file():  # a chunked run: every call's wall seconds (start-up included)
        end = [{"wall_seconds": sum(c["seconds"] for c in json.loads(chunks.read_text())["chunks"])}]
    row = {"PSNR": results[key]["PSNR"], "SSIM": results[key]["SSIM"], **masked_metrics(run, masks, _test_names(scene)),
           "mask %": 100.0 * float(np.mean([m.mean() for m in masks])) if masks else None,
           "train_s": end[-1].get("wall_seconds") if end else None, "train_cpu_s": train_cpu_seconds(log),
           "code": json.loads((run / DONE_FILE).read_text()).get("code"), "MLP": mlp_arithmetic_of(run)}
    if "reflow" in results:
        row["reflow"] = results["reflow"]
        row["canonical_check"] = canonical_check(run, scene)
    return row


def side_by_side(capture: Capture, runs: dict[str, Path], masks: list[np.ndarray], images: Path) -> Path | None:
    """GT | one column per method for the two held-out views with the most masked pixels."""
    if len(runs) < 2 or not masks:
        return None
    sys.path.insert(0, str(ROOT / "scripts"))
    import side_by_side as tool

    views = sorted(np.argsort([-m.sum() for m in masks], kind="stable")[:2].tolist())
    width = masks[0].shape[1]
    output = images / f"real_{capture.name}.jpg"
    tool.main([*(str(r) for r in runs.values()), "--views", *map(str, views), "--labels", *runs,
               "--scale", str(max(1, math.ceil(320 / width))), "-o", str(output)])
    return output


def table(rows: dict[str, dict[str, dict]]) -> str:
    """Markdown: one line per (capture, method)."""
    fmt = {"SSIM": "{:.3f}", "train_s": "{:.0f}", "train_cpu_s": "{:.0f}", "mask %": "{:.1f}", "code": "{}", "MLP": "{}"}
    lines = ["| capture | method | " + " | ".join(COLUMNS) + " |", "|---|---|" + "---:|" * (len(COLUMNS) - 1) + "---|"]
    for name, methods in rows.items():
        for method, values in methods.items():
            if "failed" in values:  # one cell saying why, the rest left empty
                lines.append(f"| {name} | {method} | FAILED: {values['failed'].replace('|', '/')} |" + " |" * (len(COLUMNS) - 1))
                continue
            cells = " | ".join("-" if values.get(c) is None else fmt.get(c, "{:.2f}").format(values[c]) for c in COLUMNS)
            lines.append(f"| {name} | {method} | {cells} |")
    return "\n".join(lines)


CHECK_COLUMNS = ("static depth / scene depth", "static in view %", "dynamic spread")


def canonical_table(rows: dict[str, dict[str, dict]]) -> str:
    """Markdown: where each ReFlow run's initial clouds lie (canonical_check), '' when none has them."""
    lines = []
    for name, methods in rows.items():
        for method, values in methods.items():
            check = values.get("canonical_check")
            if check:
                cells = " | ".join("-" if check.get(c) is None else f"{check[c]:.3g}" for c in CHECK_COLUMNS)
                lines.append(f"| {name} | {method} | {cells} | {check['reference']} ({check['reference_depth']:.3g}) |")
    if not lines:
        return ""
    head = ["| capture | method | " + " | ".join(CHECK_COLUMNS) + " | scene depth from |", "|---|---|" + "---:|" * 3 + "---|"]
    return "\n".join(head + lines)


def run_chunked(jobs: list, seconds: float, train: Callable[[object, float], Path],
                min_start: float = 60.0, workers: int = 1) -> list[Path | str]:
    """Advance `jobs` in order within one call of about `seconds`, `workers` runs at a time: done
    runs are skipped, unfinished ones continue; raises ChunkPending when the time is spent before
    all are done. `train(job, seconds_left)` is run_one with chunk_seconds (it raises ChunkPending
    itself). No run is started or continued with less than `min_start` seconds left (a start-up,
    e.g. ReFlow's canonical space, runs before the first iteration and cannot be cut); a done run
    costs nothing. A worker whose run was stopped takes no further job (its time is spent). Any
    other error (a SuiteError: a folder trained with another command) stops the worker and is
    raised once every worker has returned, so a caller repeating the call while it is pending
    does not loop on it."""
    deadline = time.monotonic() + seconds
    results: dict[int, Path | str] = {}
    pending: list[str] = []
    errors: list[Exception] = []
    queue = list(enumerate(jobs))[::-1]  # popped from the end: in order
    guard = threading.Lock()

    def worker() -> None:
        while True:
            with guard:
                left = deadline - time.monotonic()
                if not queue or left < min(min_start, seconds) or left <= 0:
                    return
                index, job = queue.pop()
            try:
                results[index] = train(job, left)
            except TrainingFailed as failure:
                print(f"error: {failure}", file=sys.stderr)
                results[index] = str(failure)
            except ChunkPending as stopped:
                with guard:
                    pending.append(str(stopped))
                return
            except Exception as error:  # noqa: BLE001 -- re-raised in the caller's thread below
                with guard:
                    errors.append(error)
                return

    threads = [threading.Thread(target=worker) for _ in range(max(1, workers))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    if len(results) < len(jobs):
        left_over = len(jobs) - len(results)
        raise ChunkPending(pending[0] if pending else
                           f"{left_over} run(s) left after {seconds:.0f} s; call again to continue")
    return [results[i] for i in range(len(jobs))]


def parse_resolutions(text: str | None, captures: list[Capture]) -> dict[str, int]:
    """`--resolution name=r,...` -> {capture: r} for `captures`; unnamed ones keep the registry's resolution,
    registry names not among `captures` are accepted and unused."""
    chosen = {c.name: c.resolution for c in captures}
    for item in filter(None, (text or "").split(",")):
        name, _, value = item.partition("=")
        if name not in CAPTURES or not value.isdigit() or int(value) < 1:
            raise CaptureError(f"--resolution {item!r}: want NAME=R with NAME a registry capture "
                               f"({', '.join(CAPTURES)}) and R >= 1")
        if name in chosen:
            chosen[name] = int(value)
    return chosen


def parse_methods(text: str) -> list[str]:
    """`--methods` as a list: known names, at least one (an empty list would print an empty table
    and exit 0). CaptureError otherwise."""
    methods = [m for m in text.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise CaptureError(f"--methods: unknown method(s) {unknown}; known: {', '.join(METHODS)}")
    if not methods:
        raise CaptureError(f"--methods {text!r}: name at least one of {', '.join(METHODS)}")
    return methods


def check_chunk_seconds(seconds: float | None) -> None:
    """`--chunk-seconds` must leave time to train: 0 or less would end every call at once with exit 3
    ("call again"), so a calling loop would never finish. CaptureError otherwise."""
    if seconds is not None and not seconds > 0:
        raise CaptureError(f"--chunk-seconds {seconds:g}: want a positive number of seconds")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--captures", help="comma list of registry names (default: all)")
    parser.add_argument("--methods", default=",".join(DEFAULT_METHODS), help=f"comma list of {', '.join(METHODS)}")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder holding the captures")
    parser.add_argument("--out", type=Path, default=ROOT / "output" / "real")
    parser.add_argument("--images", type=Path, default=ROOT / "docs" / "images", help="where real_<capture>.jpg go")
    parser.add_argument("--no-images", action="store_true", help="write no side-by-side images")
    parser.add_argument("--jobs", type=int, default=1, help="trainings at once (one thread each when > 1)")
    parser.add_argument("--coarse_iterations", type=int, default=300)
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resolution", help="NAME=R,...: train.py -r per capture (default: the registry's)")
    parser.add_argument("--chunk-seconds", type=float, metavar="S",
                        help="train at most about S seconds in this call, then checkpoint and exit 3; the next "
                             "call continues (for machines that allow short calls only; --jobs runs at once)")
    parser.add_argument("--fetch-instructions", action="store_true", help="print how to fetch each capture, then exit")
    parser.add_argument("--setup", metavar="NAME", help="extract (and prepare) capture NAME from --clone, then exit")
    parser.add_argument("--clone", type=Path, help="a clone (plain or bare) of the capture's repository")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    argv, extra = split_passthrough(argv)
    args = build_parser().parse_args(argv)
    try:
        if args.jobs < 1:
            raise CaptureError(f"--jobs {args.jobs}: want 1 or more trainings at once")
        check_chunk_seconds(args.chunk_seconds)
        if args.setup:
            if args.clone is None:
                raise CaptureError("--setup needs --clone DIR (see --fetch-instructions)")
            setup(select(args.setup)[0], args.clone, args.data)
            return 0
        captures = select(args.captures)
        if args.fetch_instructions:
            print("\n\n".join(fetch_instructions(c, args.data) for c in captures))
            return 0
        methods = parse_methods(args.methods)
        resolutions = parse_resolutions(args.resolution, captures)
        captures = [dataclasses.replace(c, resolution=resolutions[c.name]) for c in captures]
        require_ready(captures, args.data)
    except CaptureError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    schedule = {"coarse_iterations": args.coarse_iterations, "iterations": args.iterations, "seed": args.seed}
    threads = 1 if args.jobs > 1 else int(os.environ.get("OMP_NUM_THREADS", "0")) or max(1, os.cpu_count() or 1)
    jobs = [(c, m) for c in captures for m in methods]
    def attempt(job: tuple[Capture, str]) -> Path | str:
        """The run folder, or the failure's one-line reason (the other runs go on)."""
        try:
            return run_one(job[0], job[1], args.data, args.out, schedule, extra, threads)
        except TrainingFailed as failure:
            print(f"error: {job[0].name}/{job[1]}: {failure}", file=sys.stderr)
            return str(failure)

    try:
        if args.chunk_seconds is not None:
            runs = run_chunked(jobs, args.chunk_seconds, lambda job, seconds: run_one(
                job[0], job[1], args.data, args.out, schedule, extra, threads, chunk_seconds=seconds),
                workers=args.jobs)
        else:
            with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
                runs = list(pool.map(attempt, jobs))
    except ChunkPending as pending:
        print(f"pending: {pending}", file=sys.stderr)
        return 3
    except SuiteError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    rows: dict[str, dict[str, dict]] = {}
    for capture in captures:
        scene = load_capture(capture, args.data)
        masks = eval_masks(capture, scene, args.out)
        mine = {m: r for (c, m), r in zip(jobs, runs) if c is capture}
        rows[capture.name] = {m: summarise(r, masks, scene) if isinstance(r, Path) else {"failed": r}
                              for m, r in mine.items()}
        finished = {m: r for m, r in mine.items() if isinstance(r, Path)}
        if not args.no_images:
            side_by_side(capture, finished, masks, args.images)
    text = table(rows)
    checks = canonical_table(rows)
    if checks:
        text += "\n\nReFlow's initial clouds (reflow/static.ply, dynamic.ply) against the scene:\n\n" + checks
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "real_suite.md").write_text(text + "\n")
    (args.out / "real_suite.json").write_text(json.dumps({"schedule": schedule, "rows": rows}, indent=1, default=str))
    return 1 if any(isinstance(r, str) for r in runs) else 0


if __name__ == "__main__":
    sys.exit(main())
