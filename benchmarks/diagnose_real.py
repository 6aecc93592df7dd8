"""Where ReFlow loses or ties against the baseline on real captures, and why: one table per output folder.

    python benchmarks/diagnose_real.py OUT [--layout suite|convergence] [--captures a,b]
                                       [--data DIR] [--no-train-renders] [--output STEM]

OUT is a finished `benchmarks/real_suite.py` output (`OUT/<capture>/<method>/`) or, with
`--layout convergence`, a `benchmarks/convergence.py` one (`OUT/<capture>/<method>/fine_<B>/`, one
row group per capture and budget). A run counts when it holds `real_done.json`; a group is listed
when either method finished, the other method's row then says why it is missing. Nothing is
trained. Each group's dataset is the one its runs were trained on (`-s` and `-r` of the command in
`real_done.json`; `--data DIR` reads `DIR/<that folder's name>` instead).

Columns, per (capture, method):

- PSNR: train.py's held-out PSNR (`results.json`).
- train PSNR: the same on the training views (mean of the per-view PSNR of the 8-bit renders below).
- held-out in / out: PSNR inside / outside the TRUE masks (the dataset's evaluation-only masks,
  `Camera.extras["eval_mask"]`: DAVIS annotations, panoptic seg/ and its visual hull), mean over the
  held-out views, from the saved 8-bit renders (`real_suite.masked_metrics`). A dataset without true
  masks (NVIDIA Balloon1) leaves the cells empty: real_suite's estimated masks are no truth.
- train in / out: the same on the TRAINING views, rendered from the final model the way render.py
  does (`render.py -m RUN --skip_test --skip_video`, in-process, into `RUN/train/ours_<N>/`; reused
  when already there). Train well above held-out = poor generalisation; both low = under-fitting.
- SE in mask %: the true masks' share of the held-out squared error (sum over views of the squared
  error inside the masks / the total): does the mover or the background carry the loss.
- out-of-span: held-out views whose time lies outside the training views' time span [min, max]
  (recomputed from the cameras, as the trainer's "test view(s) lie outside" warning does): their
  number, and the full-image PSNR over those views vs the other held-out views.
- mask IoU / P / R (ReFlow's row): the masks ReFlow trained with (`results.json` reflow.mask_source:
  "dataset" = the dataset's `motion_masks/`, e.g. prepare's auto masks; "estimated" =
  `RUN/reflow/motion_masks/`) against the true ones: IoU, precision, recall per frame, mean over the
  frames that have both (IoU over frames where either is non-empty, precision where the estimate
  is, recall where the truth is). Without a ReFlow run, the dataset's masks (what it would use).
- prior resid.: ReFlow's depth prior's OUT-OF-SAMPLE residual at the sparse points (`canonical_check`
  fit_residual in ReFlow's results.json: the median over frames of the held-out relative residual
  of the per-frame disparity fit; marked * when only the in-sample figure existed). Only the
  monocular-disparity provider fits a prior; the flow provider has none (footnote).
- cloud depth err: the canonical static cloud's median |depth / sparse-point depth - 1| (ReFlow's
  canonical_check depth_error, in sample).
- static / sparse depth: median depth of ReFlow's initial static cloud (`reflow/static.ply`) in the
  training views over the dataset points' (`real_suite.canonical_check`).
- Gaussians: in the final `point_cloud/iteration_<N>/point_cloud.ply`; static / dynamic: ReFlow's
  labels at the end (`deformation_table.pth` beside it, True = dynamic; saved by every run, only
  meaningful with the `separation` component).
- bg motion px: how far the model moves what lies outside the TRUE masks over time, in pixels of
  the training views: per training view, over the Gaussians whose centre at the view's time
  projects into the image and outside the view's true mask (dilated by 3 px), the median
  distance between that projection and the projection of the Gaussian's mean position over all
  training times; the median over the views (`background_motion`). 0 for a background that
  holds still (ReFlow's static Gaussians); 4DGS's field moves every Gaussian a little, so a
  baseline's figure says how much per-frame freedom its background uses (pose, lens and
  exposure errors a static background must average instead).
- NN dist: median distance from each final (canonical) Gaussian of this method to the other
  method's nearest one, in units of the scene extent (the training cameras' radius, as the
  trainer's `cameras_extent`); ReFlow's row adds its static Gaussians alone (its dynamic ones sit
  at canonical positions of the separated deformation, not at any one frame's).

Missing pieces give an empty cell with a footnote number; a folder that is not a finished output
is one error line. Writes `STEM.md` and `STEM.json` (default `OUT/diagnosis`); the JSON adds, per
run, each held-out view's time and PSNR (all / in / out), the training views' error share, ReFlow's
canonical alignment residual and its whole results.json "reflow" record, the pixel-pooled mask
scores, and the scene extent.
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks import real_suite  # noqa: E402
from benchmarks.prepare_davis import mask_scores  # noqa: E402

METHODS = real_suite.DEFAULT_METHODS  # ("baseline", "reflow")
COLUMNS = ("PSNR", "train PSNR", "held-out in", "held-out out", "train in", "train out", "SE in mask %", "out-of-span",
           "mask IoU / P / R", "prior resid.", "cloud depth err", "static / sparse depth", "Gaussians",
           "static / dynamic", "bg motion px", "NN dist")


class DiagnosisError(RuntimeError):
    """OUT (or a run in it) is not a finished real_suite / convergence output."""


@dataclass
class Group:
    """One capture (and budget, in the convergence layout): its finished runs and why others are missing."""

    label: str
    runs: dict[str, Path] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)


def find_groups(out: Path, layout: str = "suite", captures: list[str] | None = None) -> list[Group]:
    """The row groups of OUT: a group per capture (suite) or per capture and budget (convergence)
    where at least one method has a finished run (`real_done.json`). DiagnosisError when none has."""
    if not out.is_dir():
        raise DiagnosisError(f"{out}: no such folder (want a real_suite.py --out or convergence.py --out folder)")
    if (out / real_suite.DONE_FILE).is_file():
        raise DiagnosisError(f"{out} is one run; give the output folder that holds <capture>/<method>/ (its "
                             f"{'grandparent' if layout == 'suite' else 'third parent'})")
    groups: dict[str, Group] = {}
    for capture in sorted(p for p in out.iterdir() if p.is_dir()):
        if captures and capture.name not in captures:
            continue
        for method in METHODS:
            folder = capture / method
            if layout == "suite":
                candidates = {capture.name: folder}
            else:
                budgets = sorted((int(p.name.split("_", 1)[1]), p) for p in folder.glob("fine_*")
                                 if p.is_dir() and p.name.split("_", 1)[1].isdigit())
                candidates = {f"{capture.name} @{budget}": path for budget, path in budgets}
            for label, run in candidates.items():
                group = groups.setdefault(label, Group(label))
                if (run / real_suite.DONE_FILE).is_file():
                    group.runs[method] = run
                else:
                    where = run.relative_to(out)
                    group.missing[method] = (f"{where} is not finished (no {real_suite.DONE_FILE})" if run.exists()
                                             else f"no {method} run ({where})")
    found = [g for g in groups.values() if g.runs]
    if not found:
        where = "<capture>/<method>" + ("" if layout == "suite" else "/fine_<B>")
        raise DiagnosisError(f"{out} holds no finished run ({where}/{real_suite.DONE_FILE}); is it a "
                             f"{'real_suite.py' if layout == 'suite' else 'convergence.py'} output?"
                             + ("" if layout == "convergence" else " (a convergence study: --layout convergence)"))
    for group in found:
        for method in METHODS:
            if method not in group.runs:
                group.missing.setdefault(method, f"no {method} run")
    return sorted(found, key=lambda g: g.label)


def run_dataset(run: Path, data: Path | None) -> tuple[Path, int]:
    """(dataset folder, train.py -r) of a finished run, from the command in its real_done.json."""
    command = json.loads((run / real_suite.DONE_FILE).read_text()).get("command") or []
    try:
        source = Path(command[command.index("-s") + 1])
        resolution = int(command[command.index("-r") + 1]) if "-r" in command else -1
    except (ValueError, IndexError):
        raise DiagnosisError(f"{run / real_suite.DONE_FILE}: its command names no -s DATASET") from None
    source = data / source.name if data is not None else source
    if not source.is_dir():
        raise DiagnosisError(f"{run} was trained on {source}, which does not exist "
                             "(--data DIR: where the captures are)")
    return source, resolution


def final_iteration(run: Path) -> int:
    """N of the run's last held-out renders `test/ours_<N>` (the iteration its results.json scores)."""
    try:
        return int(real_suite.latest_test_dir(run).name.split("_")[1])
    except real_suite.SuiteError:
        raise DiagnosisError(f"{run} has {real_suite.DONE_FILE} but no test/ours_<N> renders: "
                             "not a finished run") from None


def read_views(folder: Path, count: int) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """[(render, gt)] as [H, W, 3] uint8 for views 00000..count-1 of `folder/{renders,gt}`, None if incomplete."""
    views = []
    for index in range(count):
        name = f"{index:05d}.png"
        if not (folder / "renders" / name).is_file() or not (folder / "gt" / name).is_file():
            return None
        render, gt = cv2.imread(str(folder / "renders" / name)), cv2.imread(str(folder / "gt" / name))
        if render is None or gt is None or render.shape != gt.shape:
            return None
        views.append((render, gt))
    return views


def _mean(values: list) -> float | None:
    kept = [v for v in values if v is not None]
    return float(np.mean(kept)) if kept else None


def region_figures(views: list[tuple[np.ndarray, np.ndarray]], masks: list[np.ndarray] | None) -> dict:
    """PSNR inside / outside the masks (mean over views, `real_suite.region_psnr`) and the masks'
    share of the squared error summed over the views; all None without masks."""
    if masks is None:
        return {"in": None, "out": None, "se_in_share": None, "per_view": []}
    inside, outside, se_in, se_all = [], [], 0.0, 0.0
    for (render, gt), mask in zip(views, masks):
        if mask.shape != gt.shape[:2]:
            raise DiagnosisError(f"a true mask is {mask.shape}, the render {gt.shape[:2]}: "
                                 "the dataset is not the run's")
        inside.append(real_suite.region_psnr(render, gt, mask))
        outside.append(real_suite.region_psnr(render, gt, ~mask))
        error = ((render.astype(np.float64) - gt.astype(np.float64)) ** 2).sum(axis=2)
        se_in, se_all = se_in + float(error[mask].sum()), se_all + float(error.sum())
    return {"in": _mean(inside), "out": _mean(outside), "se_in_share": se_in / se_all if se_all > 0 else None,
            "per_view": [{"in": a, "out": b} for a, b in zip(inside, outside)]}


def full_psnr(views: list[tuple[np.ndarray, np.ndarray]]) -> float | None:
    """Mean over views of the full-image PSNR (peak 255); None for no view."""
    return _mean([real_suite.region_psnr(r, g, np.ones(g.shape[:2], bool)) for r, g in views])


def true_masks(cameras) -> list[np.ndarray] | None:
    """[H, W] bool evaluation-only mask per camera; None unless every camera has one."""
    masks = [c.extras.get("eval_mask") for c in cameras]
    if not masks or any(m is None for m in masks):
        return None
    return [m.cpu().numpy() > 0.5 for m in masks]


def time_span_split(scene) -> tuple[list[int], list[int]]:
    """(indices of held-out views inside the training views' time span, indices outside it)."""
    times = [c.time for c in scene.train_cameras]
    lo, hi = min(times), max(times)
    inside = [i for i, c in enumerate(scene.test_cameras) if lo <= c.time <= hi]
    return inside, [i for i in range(len(scene.test_cameras)) if i not in inside]


def train_views(run: Path, iteration: int, count: int, source: Path, render: bool) -> tuple[Path | None, str | None]:
    """(RUN/train/ours_<N> holding `count` rendered training views, None) or (None, why not).

    Renders them with render.py's code (`render_from_argv`, the run's saved configuration, test
    views and video skipped) unless they are there already or `render` is False."""
    folder = run / "train" / f"ours_{iteration}"
    if read_views(folder, count) is not None and not (folder / "renders" / f"{count:05d}.png").exists():
        return folder, None
    if not render:
        return None, "training views not rendered (--no-train-renders)"
    from baselines.fourdgs.app import render_from_argv

    try:
        render_from_argv(["-m", str(run), "-s", str(source), "--iteration", str(iteration), "--skip_test",
                          "--skip_video", "--quiet"])
    except Exception as error:  # a run the current code cannot load: that cell stays empty
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        return None, f"rendering the training views of {run} failed: {reason}"
    if read_views(folder, count) is None:
        return None, f"{folder} lacks some of the {count} training views after rendering"
    return folder, None


def estimated_masks(run: Path | None, scene, reflow: dict | None) -> tuple[list, list, str] | None:
    """(estimated masks, true masks, where the estimate comes from) over the frames that have both.

    The masks the ReFlow run trained with (reflow.mask_source); without a ReFlow run, the dataset's
    training masks. None when no frame has both."""
    cameras = list(scene.train_cameras) + list(scene.test_cameras)
    source = (reflow or {}).get("mask_source", "dataset")
    pairs, origin = [], "the dataset's motion_masks/"
    for camera in cameras:
        truth = camera.extras.get("eval_mask")
        if truth is None:
            continue
        truth = truth.cpu().numpy() > 0.5
        if source == "estimated" and run is not None:
            origin = f"{run.name}/reflow/motion_masks/ (estimated by ReFlow)"
            path = run / "reflow" / "motion_masks" / f"{camera.image_name}.png"
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
            if image is None:  # ReFlow estimates the training frames' masks only
                continue
            if image.shape != truth.shape:
                image = cv2.resize(image, truth.shape[::-1], interpolation=cv2.INTER_NEAREST)
            estimate = image > 127
        elif camera.mask is not None:
            estimate = camera.mask.cpu().numpy() > 0.5
        else:
            continue
        pairs.append((estimate, truth))
    if not pairs:
        return None
    return [p[0] for p in pairs], [p[1] for p in pairs], origin


def mask_agreement(estimates: list[np.ndarray], truths: list[np.ndarray]) -> dict[str, float | None]:
    """Per-frame IoU, precision and recall, each the mean over the frames where it is defined
    (IoU: either mask non-empty; precision: the estimate non-empty; recall: the truth non-empty);
    plus the pixel-pooled figures (`prepare_davis.mask_scores`) and the frame count."""
    iou, precision, recall = [], [], []
    for estimate, truth in zip(estimates, truths):
        hit, predicted, actual = int((estimate & truth).sum()), int(estimate.sum()), int(truth.sum())
        if predicted + actual - hit:
            iou.append(hit / (predicted + actual - hit))
        if predicted:
            precision.append(hit / predicted)
        if actual:
            recall.append(hit / actual)
    pooled = mask_scores(estimates, truths)
    return {"IoU": _mean(iou), "precision": _mean(precision), "recall": _mean(recall), "frames": len(estimates),
            "pooled": pooled}


def final_cloud(run: Path, iteration: int) -> tuple[np.ndarray, np.ndarray | None]:
    """(canonical means [N, 3], deformation table [N] bool or None) of point_cloud/iteration_<N>."""
    folder = run / "point_cloud" / f"iteration_{iteration}"
    if not (folder / "point_cloud.ply").is_file():
        raise DiagnosisError(f"{folder / 'point_cloud.ply'} is missing: not a finished run")
    points = real_suite._ply_points(folder / "point_cloud.ply")
    table = None
    if (folder / "deformation_table.pth").is_file():
        import torch

        table = torch.load(folder / "deformation_table.pth", map_location="cpu", weights_only=True).numpy().astype(bool)
        if table.shape != (len(points),):
            table = None
    return points, table


def projected_motion(centres: np.ndarray, cameras, masks: list[np.ndarray], dilate_px: int = 3) -> float | None:
    """Median over views of the median background displacement in pixels (the `bg motion px` column).

    centres: [V, N, 3] world positions of the N Gaussians at each of the V views' times; cameras:
    V cameras (K [3, 3], viewmat [4, 4] world->camera, width, height); masks: V [H, W] bool true
    masks. A Gaussian counts in view v when its centre at that time lies in front of the camera,
    inside the image and outside the mask dilated by `dilate_px`; its displacement is the pixel
    distance between that projection and the projection of its mean over the V times. None when
    no view has such a Gaussian."""
    mean = centres.mean(axis=0)
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    medians = []
    for points, camera, mask in zip(centres, cameras, masks):
        K, viewmat = camera.K.double().cpu().numpy(), camera.viewmat.double().cpu().numpy()

        def pixels(world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            local = world @ viewmat[:3, :3].T + viewmat[:3, 3]
            depth = local[:, 2]
            safe = np.where(depth > 1e-9, depth, 1.0)  # behind the camera: excluded below, no division by 0
            return (local[:, :2] / safe[:, None]) @ K[:2, :2].T + K[:2, 2], depth

        now, depth = pixels(points.astype(np.float64))
        then, _ = pixels(mean.astype(np.float64))
        column, row = np.floor(now[:, 0]), np.floor(now[:, 1])
        seen = (depth > 1e-9) & (column >= 0) & (row >= 0) & (column < camera.width) & (row < camera.height)
        grown = cv2.dilate(mask.astype(np.uint8), kernel) > 0
        background = seen.copy()
        background[seen] = ~grown[row[seen].astype(int), column[seen].astype(int)]
        if background.any():
            medians.append(float(np.median(np.linalg.norm(now[background] - then[background], axis=1))))
    return float(np.median(medians)) if medians else None


def background_motion(run: Path, iteration: int, source: Path, cameras, masks: list[np.ndarray]) -> tuple[float | None, str | None]:
    """(`projected_motion` of the run's model at `iteration` over the training `cameras`, None) or
    (None, why not). The model is loaded the way render.py loads it (the run's saved configuration)."""
    import torch

    from baselines.fourdgs.app import load_run

    try:
        loaded = load_run(["-m", str(run), "-s", str(source), "--iteration", str(iteration)])
    except Exception as error:  # a run the current code cannot load: that cell stays empty
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        return None, f"loading {run} failed: {reason}"
    model = loaded.trainer.ctx.model
    try:
        with torch.no_grad():
            centres = np.stack([model.deform(camera.time, "fine").means.cpu().numpy() for camera in cameras])
    finally:
        loaded.trainer.run_log.close()
    value = projected_motion(centres, cameras, masks)
    return value, None if value is not None else "no Gaussian projects outside the true masks"


def nearest_median(points: np.ndarray, others: np.ndarray, extent: float) -> float | None:
    """Median over `points` [N, 3] of the distance to the nearest of `others` [M, 3], over `extent`."""
    if not len(points) or not len(others) or extent <= 0:
        return None
    try:
        from scipy.spatial import cKDTree

        distances, _ = cKDTree(others).query(points, k=1)
    except ImportError:  # scipy is optional: torch in chunks
        import torch

        target = torch.from_numpy(others)
        distances = torch.cat([torch.cdist(torch.from_numpy(chunk), target).min(dim=1).values
                               for chunk in np.array_split(points, max(1, len(points) // 4096))]).numpy()
    return float(np.median(distances)) / extent


class Notes:
    """Footnotes: one number per distinct reason."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def mark(self, text: str) -> str:
        if text not in self.texts:
            self.texts.append(text)
        return f"[{self.texts.index(text) + 1}]"


def diagnose_run(run: Path, scene, source: Path, render_train: bool) -> dict:
    """The figures of one finished run that need nothing of the other method; `why` maps a figure
    to the reason it is None."""
    iteration = final_iteration(run)
    if not (run / "results.json").is_file():
        raise DiagnosisError(f"{run} has {real_suite.DONE_FILE} but no results.json: not a finished run")
    results = json.loads((run / "results.json").read_text())
    reflow = results.get("reflow")
    row: dict = {"run": str(run), "iteration": iteration, "PSNR": results.get(f"ours_{iteration}", {}).get("PSNR"),
                 "code": json.loads((run / real_suite.DONE_FILE).read_text()).get("code"), "why": {}}
    why = row["why"]
    test_masks = true_masks(scene.test_cameras)
    held = read_views(real_suite.latest_test_dir(run), len(scene.test_cameras))
    if held is None:
        raise DiagnosisError(f"{real_suite.latest_test_dir(run)} lacks renders or gt of the {len(scene.test_cameras)} "
                             "held-out views: not a finished run of this dataset")
    if test_masks is not None:
        row.update({f"held-out {k}": v for k, v in real_suite.masked_metrics(run, test_masks, [c.image_name for c in scene.test_cameras]).items()})
    figures = region_figures(held, test_masks)
    row["SE in mask share"] = figures["se_in_share"]
    if test_masks is None:
        why["held-out in"] = why["held-out out"] = why["SE in mask share"] = \
            "no true masks for the held-out views (the dataset has no evaluation-only masks)"
    row["held-out views"] = [{"name": c.image_name, "time": c.time,
                              "PSNR": real_suite.region_psnr(*view, np.ones(view[1].shape[:2], bool)),
                              **({f"PSNR {k}": v for k, v in figures["per_view"][i].items()} if test_masks else {})}
                             for i, (c, view) in enumerate(zip(scene.test_cameras, held))]
    inside, outside = time_span_split(scene)
    row["out-of-span views"] = [scene.test_cameras[i].image_name for i in outside]
    row["out-of-span PSNR"] = full_psnr([held[i] for i in outside])
    row["in-span PSNR"] = full_psnr([held[i] for i in inside])
    folder, reason = train_views(run, iteration, len(scene.train_cameras), source, render_train)
    train_masks = true_masks(scene.train_cameras)
    if folder is None:
        why["train PSNR"] = why["train in"] = why["train out"] = reason
    else:
        if train_masks is None:
            why["train in"] = why["train out"] = "no true masks for the training views"
        train_images = read_views(folder, len(scene.train_cameras))
        row["train PSNR"] = full_psnr(train_images)
        if train_masks is not None:
            train = region_figures(train_images, train_masks)
            row["train in"], row["train out"] = train["in"], train["out"]
            row["train SE in mask share"] = train["se_in_share"]
    if train_masks is None:
        why["bg motion px"] = "no true masks for the training views"
    elif not render_train:
        why["bg motion px"] = "the model was not loaded (--no-train-renders)"
    else:
        row["bg motion px"], reason = background_motion(run, iteration, source, scene.train_cameras, train_masks)
        if reason:
            why["bg motion px"] = reason
    points, table = final_cloud(run, iteration)
    row["Gaussians"] = len(points)
    row["_points"] = points
    row["_static"] = None
    if reflow is not None:
        row["reflow"] = reflow
        if table is not None and "separation" in reflow.get("components", []):
            row["dynamic"], row["static"] = int(table.sum()), int((~table).sum())
            row["_static"] = points[~table]
        else:
            why["static / dynamic"] = ("no labels at the end: " + ("no deformation_table.pth in the final point cloud"
                                       if table is None else "the separation component was off"))
        check = reflow.get("canonical_check") or {}
        canonical = reflow.get("canonical")
        if check.get("fit_residual") is not None:
            row["prior residual"] = check["fit_residual"]
            row["prior residual held out"] = bool(check.get("fit_residual_held_out"))
        elif canonical is None:
            why["prior residual"] = "ReFlow built no canonical space (its comp_init component was off or unavailable)"
        else:
            provider = str(canonical.get("provider", "unknown")).split("|")[0]
            why["prior residual"] = (f"no fitted depth prior: the canonical space came from the {provider} provider "
                                     "(the disparity fit's residual exists only on the monocular-disparity path)")
        if check.get("depth_error") is not None:
            row["cloud depth error"] = check["depth_error"]
        else:
            why["cloud depth error"] = (why["prior residual"] if canonical is None else
                                        "ReFlow recorded no canonical depth error (no sparse points to compare with)")
        row["canonical alignment residual"] = ((reflow.get("canonical") or {}).get("alignment") or {}).get("residual")
        row["canonical_check"] = real_suite.canonical_check(run, scene)
        if row["canonical_check"] is None or row["canonical_check"].get("static depth / scene depth") is None:
            why["static / sparse depth"] = ("no reflow/static.ply (no canonical space)" if canonical is None else
                                            "no dataset points or bounds to compare reflow/static.ply with")
    return row


def diagnose_group(group: Group, data: Path | None, render_train: bool) -> dict[str, dict]:
    """Rows of one group: {method: row} with every method of METHODS (a missing run: {"missing": why})."""
    datasets = {m: run_dataset(r, data) for m, r in group.runs.items()}
    if len(set(datasets.values())) > 1:
        raise DiagnosisError(f"{group.label}: the runs were trained on different datasets or resolutions: "
                             + ", ".join(f"{m} {s} -r {r}" for m, (s, r) in datasets.items()))
    from baselines.data.loader import load_scene

    source, resolution = next(iter(datasets.values()))
    scene = load_scene(source, resolution=resolution, eval=True)
    extent = float(scene.nerf_normalization["radius"])
    rows: dict[str, dict] = {}
    for method in METHODS:
        if method in group.runs:
            rows[method] = diagnose_run(group.runs[method], scene, source, render_train)
        else:
            rows[method] = {"missing": group.missing[method], "why": {}}
    reflow_row = rows.get("reflow", {})
    agreement = estimated_masks(group.runs.get("reflow"), scene, reflow_row.get("reflow"))
    if agreement is None:
        cameras = list(scene.train_cameras) + list(scene.test_cameras)
        reflow_row["why"]["mask IoU"] = ("no true masks in the dataset" if all(c.extras.get("eval_mask") is None
                                                                               for c in cameras)
                                         else "no frame has both an estimated and a true mask")
    else:
        reflow_row["mask agreement"] = {**mask_agreement(agreement[0], agreement[1]), "masks": agreement[2]}
    pair = [rows[m].get("_points") for m in METHODS]
    for (method, points), other in zip(zip(METHODS, pair), pair[::-1]):
        if points is not None and other is not None:
            rows[method]["NN dist"] = nearest_median(points, other, extent)
            if rows[method].get("_static") is not None:  # the static ones alone: the background's placement
                rows[method]["NN dist static"] = nearest_median(rows[method]["_static"], other, extent)
        elif "missing" not in rows[method]:
            rows[method]["why"]["NN dist"] = "the other method has no finished run"
    for row in rows.values():
        row.pop("_points", None)
        row.pop("_static", None)
        row["extent"] = extent
    return rows


def cells(row: dict, notes: Notes) -> list[str]:
    """The COLUMNS cells of one row; a missing figure gives its footnote mark, one that does not apply ''."""
    why = row.get("why", {})

    def cell(key: str, fmt: str = "{:.2f}", note_key: str | None = None) -> str:
        if row.get(key) is not None:
            return fmt.format(row[key])
        reason = why.get(note_key or key)
        return notes.mark(reason) if reason else ""

    span = row.get("out-of-span views")
    if span is None:
        span_cell = ""
    elif not span:
        span_cell = "0"
    else:
        inside = "-" if row.get("in-span PSNR") is None else f"{row['in-span PSNR']:.2f}"
        span_cell = f"{len(span)}: {row['out-of-span PSNR']:.2f} vs {inside}"
    agreement = row.get("mask agreement")
    if agreement:
        parts = [agreement.get(k) for k in ("IoU", "precision", "recall")]
        mask_cell = " / ".join("-" if v is None else f"{v:.2f}" for v in parts)
    else:
        mask_cell = notes.mark(why["mask IoU"]) if "mask IoU" in why else ""
    prior = cell("prior residual", "{:.3f}")
    if row.get("prior residual") is not None and not row.get("prior residual held out"):
        prior += "*"
    check = row.get("canonical_check") or {}
    ratio = check.get("static depth / scene depth")
    ratio_cell = f"{ratio:.2f}" if ratio is not None else (notes.mark(why["static / sparse depth"])
                                                           if "static / sparse depth" in why else "")
    if row.get("static") is not None:
        labels = f"{row['static']:,} / {row['dynamic']:,}"
    else:
        labels = notes.mark(why["static / dynamic"]) if "static / dynamic" in why else ""
    nn_cell = cell("NN dist", "{:.3f}")
    if row.get("NN dist static") is not None:
        nn_cell += f" (static {row['NN dist static']:.3f})"
    share = row.get("SE in mask share")
    share_cell = f"{100 * share:.0f}" if share is not None else (notes.mark(why["SE in mask share"])
                                                                 if "SE in mask share" in why else "")
    return [cell("PSNR"), cell("train PSNR"), cell("held-out PSNR-mask", note_key="held-out in"),
            cell("held-out PSNR-outside", note_key="held-out out"), cell("train in"), cell("train out"), share_cell,
            span_cell, mask_cell, prior, cell("cloud depth error", "{:.3f}"), ratio_cell,
            cell("Gaussians", "{:,}"), labels, cell("bg motion px"), nn_cell]


def table(groups: dict[str, dict[str, dict]]) -> str:
    """Markdown: a line per (group, method), then the numbered footnotes."""
    notes = Notes()
    lines = ["| capture | method | " + " | ".join(COLUMNS) + " |", "|---|---|" + "---:|" * len(COLUMNS)]
    for label, rows in groups.items():
        for method, row in rows.items():
            if "missing" in row:
                mask = row.get("mask agreement")
                filler = [""] * len(COLUMNS)
                if mask:  # the dataset's masks still score without the run
                    filler[COLUMNS.index("mask IoU / P / R")] = " / ".join(
                        "-" if mask.get(k) is None else f"{mask[k]:.2f}" for k in ("IoU", "precision", "recall"))
                filler[0] = notes.mark(row["missing"])
                lines.append(f"| {label} | {method} | " + " | ".join(filler) + " |")
                continue
            lines.append(f"| {label} | {method} | " + " | ".join(cells(row, notes)) + " |")
    text = "\n".join(lines)
    if notes.texts:
        text += "\n\n" + "\n".join(f"- [{i}] {t}" for i, t in enumerate(notes.texts, 1))
    return text


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="a real_suite.py (or convergence.py) --out folder")
    parser.add_argument("--layout", choices=("suite", "convergence"), default="suite",
                        help="suite: OUT/<capture>/<method>; convergence: OUT/<capture>/<method>/fine_<B>")
    parser.add_argument("--captures", help="comma list of capture folders (default: all)")
    parser.add_argument("--data", type=Path, help="read each dataset from DATA/<name> instead of the runs' -s")
    parser.add_argument("--no-train-renders", action="store_true",
                        help="render no training view and load no model (the training-view cells stay empty unless "
                             "RUN/train/ours_<N> exists; bg motion px stays empty)")
    parser.add_argument("--output", type=Path, help="write STEM.md and STEM.json (default: OUT/diagnosis)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    captures = [c.strip() for c in (args.captures or "").split(",") if c.strip()] or None
    try:
        groups = find_groups(args.out, args.layout, captures)
        for group in groups:  # every dataset is there before any rendering starts
            for run in group.runs.values():
                run_dataset(run, args.data)
                final_iteration(run)
        rows = {g.label: diagnose_group(g, args.data, not args.no_train_renders) for g in groups}
    except DiagnosisError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    text = table(rows)
    print(text)
    stem = args.output if args.output is not None else args.out / "diagnosis"
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".md").write_text(text + "\n")
    stem.with_suffix(".json").write_text(json.dumps(
        {"out": str(args.out), "layout": args.layout, "code": real_suite.code_version(), "groups": rows},
        indent=1, default=str))
    return 0


if __name__ == "__main__":
    from baselines.thread_policy import apply_thread_policy

    apply_thread_policy()  # before torch starts (rendering): passive OpenMP waits, threads from the CPUs available
    sys.exit(main())
