"""benchmarks/diagnose_real.py on two tiny finished runs (baseline, ReFlow) of a simulated capture.

The capture is the simulator's balloon at 32x32 with its exact masks as evaluation-only truth
(`gt/motion_masks/`, no `motion_masks/`: ReFlow estimates its own, as on NVIDIA Balloon1), frames 0
and 8 held out, so frame 0 lies before the training views' time span. After a first diagnosis
(which renders the training views), the held-out and training renders and ReFlow's masks are
replaced by images with a known error inside and outside the true masks; the second diagnosis must
give the figures worked out here by hand.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from benchmarks import diagnose_real
from benchmarks.real_suite import DONE_FILE
from tests.conftest import _depth_points
from tests.test_trainer import FAST

ITERATIONS = 3
TEST_VIEWS = ("000", "008")  # the NVIDIA hold-out: every 8th of 12 frames


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """OUT/tiny/{baseline,reflow}: finished real_suite-style runs (1 + 3 iterations, 256 points)."""
    from baselines.fourdgs.app import REPO_ROOT, train_from_argv
    from baselines.synthetic import get_scene, simulate

    root = tmp_path_factory.mktemp("diagnose")
    scene = root / "data" / "tiny"
    simulate(get_scene("balloon", frames=12, width=32, height=32, seed=0), scene, progress=False)
    shutil.rmtree(scene / "motion_masks")  # the exact masks stay in gt/motion_masks: evaluation only
    np.save(scene / "points.npy", _depth_points(scene, [1, 6])[::8])  # few points: seconds, not minutes
    for method, extra in (("baseline", []),
                          ("reflow", ["--plugin", "reflow", "--flow_vis_every", "0", "--disable", "comp_init"])):
        run = root / "out" / "tiny" / method
        argv = ["-s", str(scene), "-m", str(run), "-r", "1", "--eval", "--configs",
                str(REPO_ROOT / "arguments/synthetic/default.py"), "--coarse_iterations", "1",
                "--iterations", str(ITERATIONS), *FAST, *extra]
        train_from_argv(argv)
        (run / DONE_FILE).write_text(json.dumps({"command": ["train.py", *argv], "code": "test"}))
    return root / "out"


def _truth(out: Path, name: str) -> np.ndarray:
    scene = Path(json.loads((out / "tiny" / "baseline" / DONE_FILE).read_text())["command"][2])
    return cv2.imread(str(scene / "gt" / "motion_masks" / f"{name}.png"), cv2.IMREAD_GRAYSCALE) > 127


def _with_error(gt: np.ndarray, mask: np.ndarray, inside: int, outside: int) -> np.ndarray:
    """gt moved by exactly `inside` levels on the mask's pixels and `outside` elsewhere (every channel)."""
    step = np.where(mask, inside, outside)[..., None]
    return np.where(gt < 128, gt.astype(int) + step, gt.astype(int) - step).astype(np.uint8)


def _rewrite(folder: Path, masks: list[np.ndarray], inside: int, outside: int) -> None:
    for index, mask in enumerate(masks):
        gt = cv2.imread(str(folder / "gt" / f"{index:05d}.png"))
        cv2.imwrite(str(folder / "renders" / f"{index:05d}.png"), _with_error(gt, mask, inside, outside))


def _psnr(level: float) -> float:
    return 20 * math.log10(255 / level)


def test_diagnosis_gives_the_figures_of_known_errors_inside_and_outside_the_true_masks(finished, tmp_path):
    from baselines.data.loader import load_scene

    stem = tmp_path / "first"
    assert diagnose_real.main([str(finished), "--output", str(stem)]) == 0
    scene = load_scene(Path(json.loads((finished / "tiny" / "baseline" / DONE_FILE).read_text())["command"][2]),
                       resolution=1, eval=True)
    train_names = [c.image_name for c in scene.train_cameras]
    assert [c.image_name for c in scene.test_cameras] == list(TEST_VIEWS)
    for method in ("baseline", "reflow"):  # the training views, rendered in the trainer's camera order
        folder = finished / "tiny" / method / "train" / f"ours_{ITERATIONS}"
        assert len(list((folder / "renders").glob("*.png"))) == len(train_names)
        for index, camera in enumerate(scene.train_cameras):
            expected = cv2.imread(str(scene.source_path / "images" / f"{camera.image_name}.png"))
            assert np.abs(cv2.imread(str(folder / "gt" / f"{index:05d}.png")).astype(int) - expected).max() <= 1

    held_masks = [_truth(finished, n) for n in TEST_VIEWS]
    train_masks = [_truth(finished, n) for n in train_names]
    assert all(m.any() and not m.all() for m in held_masks)
    runs = {m: finished / "tiny" / m for m in ("baseline", "reflow")}
    _rewrite(runs["baseline"] / "test" / f"ours_{ITERATIONS}", held_masks, 0, 4)   # exact on the mover
    _rewrite(runs["reflow"] / "test" / f"ours_{ITERATIONS}", held_masks, 4, 2)
    _rewrite(runs["baseline"] / "train" / f"ours_{ITERATIONS}", train_masks, 0, 2)
    _rewrite(runs["reflow"] / "train" / f"ours_{ITERATIONS}", train_masks, 8, 1)
    estimated = sorted((runs["reflow"] / "reflow" / "motion_masks").glob("*.png"))
    assert estimated, "ReFlow estimated no masks"
    for path in estimated:  # "everything moves": IoU = precision = the truth's share of the frame
        cv2.imwrite(str(path), np.full((32, 32), 255, np.uint8))

    results = json.loads((runs["reflow"] / "results.json").read_text())
    assert "canonical" not in results["reflow"]  # comp_init off: footnotes; the figures a canonical space records:
    results["reflow"]["canonical"] = {"provider": "depth|stride=2", "alignment": {"residual": 0.07}}
    results["reflow"]["canonical_check"] = {"fit_residual": 0.05, "fit_residual_held_out": False, "depth_error": 0.03}
    (runs["reflow"] / "results.json").write_text(json.dumps(results))
    stem = tmp_path / "second"
    assert diagnose_real.main([str(finished), "--output", str(stem)]) == 0
    rows = json.loads(stem.with_suffix(".json").read_text())["groups"]["tiny"]
    base, reflow = rows["baseline"], rows["reflow"]
    assert base["held-out PSNR-mask"] == math.inf and base["held-out PSNR-outside"] == pytest.approx(_psnr(4))
    assert reflow["held-out PSNR-mask"] == pytest.approx(_psnr(4))
    assert reflow["held-out PSNR-outside"] == pytest.approx(_psnr(2))
    assert base["train in"] == math.inf and base["train out"] == pytest.approx(_psnr(2))
    assert base["train PSNR"] == pytest.approx(np.mean([_psnr(2) + 10 * math.log10(m.size / (~m).sum())
                                                        for m in train_masks]))
    assert reflow["train in"] == pytest.approx(_psnr(8)) and reflow["train out"] == pytest.approx(_psnr(1))
    inside = sum(int(m.sum()) for m in held_masks)
    outside = sum(int((~m).sum()) for m in held_masks)
    assert base["SE in mask share"] == 0.0
    assert reflow["SE in mask share"] == pytest.approx(16 * inside / (16 * inside + 4 * outside))
    # frame 0 is before the training span: scored alone (full-image PSNR of its known error)
    assert reflow["out-of-span views"] == ["000"]
    first = held_masks[0]
    mse = (16 * first.sum() + 4 * (~first).sum()) / first.size
    assert reflow["out-of-span PSNR"] == pytest.approx(10 * math.log10(255 ** 2 / mse))
    assert base["out-of-span PSNR"] == pytest.approx(_psnr(4) + 10 * math.log10(first.size / (~first).sum()))
    agreement = reflow["mask agreement"]
    truths = [_truth(finished, p.stem) for p in estimated]
    assert agreement["frames"] == len(estimated)
    assert agreement["IoU"] == pytest.approx(np.mean([t.mean() for t in truths]))
    assert agreement["precision"] == pytest.approx(np.mean([t.mean() for t in truths]))
    assert agreement["recall"] == 1.0
    from plyfile import PlyData

    for method, row in rows.items():
        ply = runs[method] / "point_cloud" / f"iteration_{ITERATIONS}" / "point_cloud.ply"
        assert row["Gaussians"] == PlyData.read(str(ply))["vertex"].count
        assert row["NN dist"] is not None and row["NN dist"] >= 0
    assert reflow["static"] + reflow["dynamic"] == reflow["Gaussians"] and reflow["dynamic"] > 0
    import torch

    clouds = {m: np.stack([np.asarray(PlyData.read(str(runs[m] / "point_cloud" / f"iteration_{ITERATIONS}" /
                                                       "point_cloud.ply"))["vertex"][k]) for k in "xyz"], 1)
              for m in runs}
    static = ~torch.load(runs["reflow"] / "point_cloud" / f"iteration_{ITERATIONS}" / "deformation_table.pth").numpy()
    assert static.sum() == reflow["static"]

    def brute(a: np.ndarray, b: np.ndarray) -> float:  # every pair's distance, no tree
        return float(np.median(np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1)).min(1)))
    assert reflow["NN dist"] == pytest.approx(brute(clouds["reflow"], clouds["baseline"]) / reflow["extent"], rel=1e-5)
    assert base["NN dist"] == pytest.approx(brute(clouds["baseline"], clouds["reflow"]) / base["extent"], rel=1e-5)
    assert reflow["NN dist static"] == pytest.approx(
        brute(clouds["reflow"][static], clouds["baseline"]) / reflow["extent"], rel=1e-5)
    for row in (base, reflow):  # the models were loaded and deformed at the training times
        assert row["bg motion px"] is not None and math.isfinite(row["bg motion px"]) and row["bg motion px"] >= 0
    assert reflow["prior residual"] == 0.05 and reflow["cloud depth error"] == 0.03
    assert reflow["canonical alignment residual"] == 0.07
    first_reflow = json.loads((tmp_path / "first.json").read_text())["groups"]["tiny"]["reflow"]
    assert "no canonical space" in first_reflow["why"]["prior residual"]
    text = stem.with_suffix(".md").read_text()
    reflow_line = next(line for line in text.splitlines() if line.startswith("| tiny | reflow |"))
    assert f"1: {reflow['out-of-span PSNR']:.2f} vs" in reflow_line
    assert f"{reflow['static']:,} / {reflow['dynamic']:,}" in reflow_line
    assert "| 0.050* | 0.030 |" in reflow_line  # an in-sample prior residual is starred


def test_missing_pieces_are_footnotes_and_the_convergence_layout_is_read(finished, tmp_path):
    """A capture without the ReFlow run and a dataset without true masks: empty cells, numbered
    footnotes naming why, no crash; the same run in the convergence layout gives a group per budget."""
    data = tmp_path / "data"
    scene = Path(json.loads((finished / "tiny" / "baseline" / DONE_FILE).read_text())["command"][2])
    shutil.copytree(scene, data / scene.name, ignore=shutil.ignore_patterns("motion_masks"))
    suite = tmp_path / "suite" / "tiny"
    suite.mkdir(parents=True)
    (suite / "baseline").symlink_to(finished / "tiny" / "baseline")
    stem = tmp_path / "diagnosis"
    assert diagnose_real.main([str(tmp_path / "suite"), "--data", str(data), "--no-train-renders",
                               "--output", str(stem)]) == 0
    text = stem.with_suffix(".md").read_text()
    lines = text.splitlines()
    reflow_line = next(line for line in lines if line.startswith("| tiny | reflow |"))
    base_line = next(line for line in lines if line.startswith("| tiny | baseline |"))
    note = reflow_line.split("|")[3].strip()
    assert note.startswith("[") and any(line.startswith(f"- {note}") and "no reflow run" in line for line in lines)
    held_in = base_line.split("|")[[c.strip() for c in lines[0].split("|")].index("held-out in")].strip()
    assert any(line.startswith(f"- {held_in}") and "no true masks" in line for line in lines)
    assert len(base_line.split("|")) == len(lines[0].split("|"))  # as many cells as the header

    study = tmp_path / "study" / "tiny"
    for method in ("baseline", "reflow"):
        (study / method).mkdir(parents=True)
        (study / method / f"fine_{ITERATIONS}").symlink_to(finished / "tiny" / method)
    (study / "baseline" / "fine_99").symlink_to(finished / "tiny" / "baseline")
    (study / "reflow" / "fine_99").mkdir()  # torn: no done-marker
    (study / "reflow" / "fine_50").mkdir()  # a budget no method finished: no group
    assert diagnose_real.main([str(tmp_path / "study"), "--layout", "convergence", "--no-train-renders",
                               "--output", str(stem)]) == 0
    groups = json.loads(stem.with_suffix(".json").read_text())["groups"]
    assert set(groups) == {f"tiny @{ITERATIONS}", "tiny @99"}
    assert "missing" not in groups[f"tiny @{ITERATIONS}"]["reflow"]
    assert "not finished" in groups["tiny @99"]["reflow"]["missing"]


def test_a_folder_that_is_not_a_finished_output_is_one_error_line(tmp_path, capsys):
    (tmp_path / "cap" / "baseline").mkdir(parents=True)  # a torn run: no real_done.json
    assert diagnose_real.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and str(tmp_path) in err[0]
    assert diagnose_real.main([str(tmp_path / "nowhere")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere" in err[0]
    (tmp_path / "cap" / "baseline" / "real_done.json").write_text('{"command": ["train.py", "-s", "x"]}')
    assert diagnose_real.main([str(tmp_path / "cap" / "baseline")]) == 2  # one run, not an output folder
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is one run" in err[0]
    assert diagnose_real.main([str(tmp_path)]) == 2  # its dataset is not there
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "which does not exist" in err[0]
    (tmp_path / "cap" / "baseline" / "real_done.json").write_text(json.dumps({"command": ["train.py", "-s", str(tmp_path)]}))
    assert diagnose_real.main([str(tmp_path)]) == 2  # done-marked, but no held-out renders
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no test/ours_<N> renders" in err[0] and str(tmp_path / "cap" / "baseline") in err[0]


def test_background_motion_counts_what_moves_outside_the_dilated_masks_in_pixels():
    """Two views from one camera (focal 10 px, centre 16, 32x32; the mask: columns 24 and up). Per
    view, from each Gaussian's mean over the two times: a still one 0 px, a moving one 1 px, one
    inside the mask 3 px, one 1-3 columns left of the mask (inside the 3 px dilation) 1.25 px, one
    behind the camera (3 px if it were projected): each view's median is over {0, 1} = 0.5 px."""
    from types import SimpleNamespace

    import torch

    camera = SimpleNamespace(K=torch.tensor([[10.0, 0, 16], [0, 10.0, 16], [0, 0, 1]]), viewmat=torch.eye(4),
                             width=32, height=32)
    mask = np.zeros((32, 32), bool)
    mask[:, 24:] = True
    #                      still         moving         inside the mask  beside it       behind the camera
    first = np.array([[0.0, 0, 1], [0.1, 0, 1], [0.9, 0, 1], [0.5, 0, 1], [0.3, 0, -1]])
    second = np.array([[0.0, 0, 1], [-0.1, 0, 1], [1.5, 0, 1], [0.75, 0, 1], [-0.3, 0, -1]])
    centres = np.stack([first, second])
    masks = [mask, mask]
    assert diagnose_real.projected_motion(centres, [camera, camera], masks) == pytest.approx(0.5)
    # undilated, the one beside the mask counts: median of {0, 1, 1.25}
    assert diagnose_real.projected_motion(centres, [camera, camera], masks, dilate_px=0) == pytest.approx(1.0)
    everything = [np.ones((32, 32), bool)] * 2
    assert diagnose_real.projected_motion(centres, [camera, camera], everything) is None


def test_nearest_distances_and_mask_agreement_on_known_geometry():
    points = np.array([[0.0, 0, 0], [3.0, 0, 0], [10.0, 0, 0]])
    others = np.array([[0.0, 1, 0], [3.0, 0, 2]])
    assert diagnose_real.nearest_median(points, others, extent=2.0) == pytest.approx(2.0 / 2.0)  # 1, 2, 7.3 -> 2
    assert diagnose_real.nearest_median(others, points, extent=1.0) == pytest.approx(1.5)  # 1, 2 -> 1.5
    truth = [np.zeros((4, 4), bool) for _ in range(4)]
    estimate = [np.zeros((4, 4), bool) for _ in range(4)]
    truth[0][:2] = True                     # 8 pixels
    estimate[0][:1] = True                  # 4 pixels, all inside: IoU 0.5, precision 1, recall 0.5
    estimate[1][3, 3] = True                # a frame without truth: IoU 0, precision 0, no recall
    truth[2][0, 0] = True                   # a frame the estimate misses: IoU 0, no precision, recall 0
    # frame 3: both empty, no figure
    scores = diagnose_real.mask_agreement(estimate, truth)
    assert scores["IoU"] == pytest.approx(0.5 / 3) and scores["precision"] == pytest.approx(0.5)
    assert scores["recall"] == pytest.approx(0.25) and scores["frames"] == 4
