"""Real captures for `benchmarks/real_suite.py`: where each one comes from, how to set it up locally.

    python benchmarks/real_suite.py --fetch-instructions            # what to clone, and the setup command
    python benchmarks/real_suite.py --setup NAME --clone CLONE      # extract (and prepare) one capture

Every capture is a folder committed to a public GitHub repository, pinned to one commit. The
data is never copied into this repository: `setup` reads it with `git archive COMMIT FOLDER` from
a local clone (a plain or a bare clone) and writes `DATA/<name>` (default `data/real/`, git-ignored):

- family `nvidia`: NVIDIA Dynamic Scenes frames in the DynamicNeRF layout; the entries in `keep`
  (`images/`, `disp/`, `poses_bounds.npy`) are copied as they are, nothing else;
- family `panoptic`: a CMU Panoptic capture in the Dynamic3DGaussians layout; the entries in
  `keep` (`ims/`, `seg/`, `train_meta.json`, `test_meta.json`) are copied, then the static cloud
  `points3D.ply` is triangulated by pycolmap from every train_meta camera at timestamp 0
  (`baselines.data.panoptic.triangulate_first_timestep`; the repository's `init_pt_cld.npz` is
  not used);
- family `clip`: a folder of video frames (DAVIS-style JPGs) with no cameras; the frames go to
  `DATA/src/<name>` and `python -m baselines.prepare` (pycolmap SfM, auto motion masks) writes
  the COLMAP-layout dataset `DATA/<name>` with `prepare_flags`. A clip with `truth` (a folder
  of annotation PNGs, one per source frame, pixel = object id, e.g. DAVIS `Annotations/480p/`)
  also gets evaluation-only ground-truth masks: the annotations go to `DATA/truth/<name>` and,
  binarised (any object id > 0) and resized to the prepared frames, to
  `DATA/<name>/gt/motion_masks/<frame stem>.png` for each registered frame. Training never sees
  them (it uses prepare's own auto masks, `motion_masks/`); real_suite scores "inside the masks"
  with them.

Held-out protocol (`--eval`) is the family's: NVIDIA's monocular protocol holds out every 8th
frame (`llffhold`); prepared clips use the same LLFF rule on the registered frames; panoptic
trains on one camera per timestamp cycling over the 5 training cameras nearest the first test
camera (17, 29, 13, 21, 24 for basketball) and tests on that held-out camera (0) at every 10th
timestamp (`--train_cameras`, `--test_cameras`, `--test_every`).
"""
from __future__ import annotations

import io
import shutil
import subprocess
import sys
import tarfile
from dataclasses import dataclass
from pathlib import Path

import cv2

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = ROOT / "data" / "real"
FAMILIES = ("nvidia", "panoptic", "clip")
POINTS_FILE = "points3D.ply"  # panoptic: the cloud setup triangulates
TRUTH_MASKS = "gt/motion_masks"  # clip with truth: evaluation-only masks inside the dataset

DAVIS_REPO, DAVIS_COMMIT = "MathLee/EOR-VOS", "1bde4d5f936304c5ad69e301956e9d65082dfbc8"
DAVIS_CLIPS = {  # clip: (frames, what the camera and the subject do)
    "blackswan": (50, "a swan swimming, slow pan"), "bmx-trees": (80, "a BMX rider behind trees, fast pan"),
    "breakdance": (84, "a dancer spinning, camera nearly still"), "cows": (104, "a cow walking, slow pan"),
    "dog": (60, "a dog running, camera following"), "drift-chicane": (52, "a drifting car, camera on a tripod"),
    "goat": (90, "a goat walking, camera following"), "kite-surf": (50, "a kite surfer on waves, pan"),
    "libby": (49, "a dog running towards the camera, fast pan"),
    "motocross-jump": (40, "a motocross jump, fast pan and zoom"),
    "paragliding-launch": (80, "a paraglider taking off, slow pan"),
    "scooter-black": (43, "a scooter crossing the view, pan"), "soapbox": (99, "a soapbox cart, camera following"),
}
# prepare's video defaults at 320 px wide (the frames are 854x480): the lady-running capture's size
DAVIS_FLAGS = ("--size", "320")


def _davis(clip: str) -> "Capture":
    frames, what = DAVIS_CLIPS[clip]
    return Capture(name="davis_" + clip.replace("-", "_"), family="clip", repo=DAVIS_REPO, commit=DAVIS_COMMIT,
                   folder=f"DAVIS/JPEGImages/480p/{clip}", truth=f"DAVIS/Annotations/480p/{clip}",
                   what=f"DAVIS {clip}, {frames} JPG frames 854x480, {what}; annotations as true masks",
                   prepare_flags=DAVIS_FLAGS)


class CaptureError(ValueError):
    """A capture is unknown, missing, or cannot be set up; the message says what to do."""


@dataclass(frozen=True)
class Capture:
    name: str
    family: str                    # nvidia | panoptic | clip
    repo: str                      # GitHub owner/name
    commit: str                    # 40-hex commit the data is read from
    folder: str                    # folder inside the repository
    what: str                      # one line for the table in docs/REAL_CAPTURES.md
    resolution: int = 1            # train.py -r (downscale factor of the stored images)
    keep: tuple[str, ...] = ()     # nvidia, panoptic: entries of `folder` copied into the dataset
    prepare_flags: tuple[str, ...] = ()  # clip: options of `python -m baselines.prepare`
    truth: str = ""                # clip: folder of annotation PNGs (object ids), evaluation only

    @property
    def url(self) -> str:
        return f"https://github.com/{self.repo}"


CAPTURES: dict[str, Capture] = {c.name: c for c in (
    Capture(name="nvidia_balloon1", family="nvidia", repo="xyi1023/ShanghaiTech-CS172-Final-Project",
            commit="60c41bd1a306341bddac115cbc31c8243ea92618", folder="Balloon1",
            what="NVIDIA Dynamic Scenes Balloon1, 12 frames 960x540, disp/ from a monocular network, no motion masks",
            resolution=4, keep=("images", "disp", "poses_bounds.npy")),
    Capture(name="davis_lady_running", family="clip", repo="Junyi42/monst3r",
            commit="574cc77ad278bad582f470e5382624e01f8769a7", folder="demo_data/lady-running",
            what="DAVIS lady-running, 65 JPG frames 854x480, hand-held camera following a runner",
            prepare_flags=("--size", "320")),
    Capture(name="nvidia_balloon1_colmap", family="clip", repo="xyi1023/ShanghaiTech-CS172-Final-Project",
            commit="60c41bd1a306341bddac115cbc31c8243ea92618", folder="Balloon1/images",
            what="the same 12 Balloon1 frames without poses or disparity, through prepare (COLMAP cameras, flow path)",
            prepare_flags=("--size", "240")),
    Capture(name="panoptic_basketball", family="panoptic", repo="guanxiangwenyyds/4dreconstruction",
            commit="064f5e5836f85aa1798c86bcff5460b80103ea9a", folder="data/basketball",
            what="CMU Panoptic basketball (Dynamic3DGaussians layout), 150 frames 640x360, 27 training + 4 test "
                 "cameras, seg/ person masks; monocular protocol",
            resolution=2, keep=("ims", "seg", "train_meta.json", "test_meta.json")),
    *(_davis(clip) for clip in DAVIS_CLIPS),
)}


def dataset_dir(capture: Capture, data_root: Path) -> Path:
    return Path(data_root) / capture.name


def frames_dir(capture: Capture, data_root: Path) -> Path:
    return Path(data_root) / "src" / capture.name


def truth_dir(capture: Capture, data_root: Path) -> Path:
    return Path(data_root) / "truth" / capture.name


def is_ready(capture: Capture, data_root: Path) -> bool:
    """True when `DATA/<name>` holds a dataset train.py can read for this family."""
    folder = dataset_dir(capture, data_root)
    if capture.family == "nvidia":
        return (folder / "poses_bounds.npy").is_file() and (folder / "images").is_dir()
    if capture.family == "panoptic":
        return all((folder / name).exists() for name in capture.keep) and (folder / POINTS_FILE).is_file()
    prepared = (folder / "images").is_dir() and (folder / "sparse" / "0").is_dir() and (folder / "prepare_report.json").is_file()
    return prepared and (not capture.truth or (folder / TRUTH_MASKS).is_dir())


def fetch_instructions(capture: Capture, data_root: Path, clone_root: str = "/tmp/clones") -> str:
    """Shell lines that fetch `capture` from its repository and set it up under `data_root`."""
    clone = f"{clone_root}/{capture.repo.replace('/', '+')}"
    return "\n".join([
        f"# {capture.name}: {capture.what}",
        f"#   {capture.url}/tree/{capture.commit}/{capture.folder}",
        f"git clone {capture.url} {clone}",
        f"python benchmarks/real_suite.py --setup {capture.name} --clone {clone} --data {data_root}",
    ])


def require_ready(captures: list[Capture], data_root: Path) -> None:
    """One CaptureError naming every missing capture and how to fetch it (before any training)."""
    missing = [c for c in captures if not is_ready(c, data_root)]
    if not missing:
        return
    names = ", ".join(f"{c.name} ({dataset_dir(c, data_root)})" for c in missing)
    how = "\n".join(fetch_instructions(c, data_root) for c in missing)
    raise CaptureError(f"capture(s) not found: {names}; fetch them with:\n{how}\n"
                       "(or run only the captures you have with --captures NAME,...)")


def select(names: str | None) -> list[Capture]:
    """The registry entries named in a comma list (all when None); CaptureError for an unknown name."""
    if not names:
        return list(CAPTURES.values())
    chosen = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in chosen if n not in CAPTURES]
    if unknown:
        raise CaptureError(f"unknown capture(s) {unknown}; known: {', '.join(CAPTURES)}")
    return [CAPTURES[n] for n in chosen]


def _archive(clone: Path, commit: str, paths: list[str]) -> tarfile.TarFile:
    """The tar of `paths` at `commit` in the clone (plain or bare); CaptureError if git cannot give it."""
    if not Path(clone).exists():
        raise CaptureError(f"--clone {clone} does not exist")
    result = subprocess.run(["git", "-C", str(clone), "archive", "--format=tar", commit, "--", *paths],
                            capture_output=True)
    if result.returncode != 0:
        reason = result.stderr.decode(errors="replace").strip().splitlines()
        raise CaptureError(f"git archive {commit} {' '.join(paths)} failed in {clone}: "
                           f"{reason[-1] if reason else 'unknown'} (is it a clone of the capture's repository, with that commit?)")
    return tarfile.open(fileobj=io.BytesIO(result.stdout))


def extract(clone: Path, commit: str, folder: str, target: Path, keep: tuple[str, ...] = ()) -> int:
    """Write the files of `folder` (only the top-level entries in `keep`, when given) into `target`.

    Returns the number of files written; CaptureError when `keep` names something absent."""
    prefix = folder.rstrip("/") + "/"
    written, seen = 0, set()
    paths = [prefix + k for k in keep] if keep else [folder]
    with _archive(clone, commit, paths) as tar:
        for member in tar.getmembers():
            if not member.isfile() or not member.name.startswith(prefix):
                continue
            relative = member.name[len(prefix):]
            top = relative.split("/", 1)[0]
            if keep and top not in keep:
                continue
            seen.add(top)
            destination = Path(target) / relative
            destination.parent.mkdir(parents=True, exist_ok=True)
            with tar.extractfile(member) as source, open(destination, "wb") as out:
                shutil.copyfileobj(source, out)
            written += 1
    absent = [k for k in keep if k not in seen]
    if absent or written == 0:
        raise CaptureError(f"{folder} at {commit[:12]} lacks {absent or 'any file'} "
                           "(a snapshot without its large files? clone the full repository)")
    return written


def setup(capture: Capture, clone: Path, data_root: Path) -> Path:
    """Extract (and for clips, prepare) `capture` under `data_root`; returns the dataset folder."""
    target = dataset_dir(capture, data_root)
    if capture.family == "nvidia":
        count = extract(clone, capture.commit, capture.folder, target, capture.keep)
        print(f"{capture.name}: {count} files -> {target}")
        return target
    if capture.family == "panoptic":
        from baselines.data.panoptic import triangulate_first_timestep

        count = extract(clone, capture.commit, capture.folder, target, capture.keep)
        points = triangulate_first_timestep(target, target / POINTS_FILE)
        print(f"{capture.name}: {count} files -> {target}; {points} static points triangulated -> {POINTS_FILE}")
        return target
    frames = frames_dir(capture, data_root)
    count = extract(clone, capture.commit, capture.folder, frames)
    print(f"{capture.name}: {count} frames -> {frames}; running prepare")
    if capture.truth:  # before prepare's long run: a clone without the annotations stops here
        truth = truth_dir(capture, data_root)
        annotations = extract(clone, capture.commit, capture.truth, truth)
        if annotations != count:
            raise CaptureError(f"{capture.truth} holds {annotations} annotations for {count} frames at {capture.commit[:12]}")
    subprocess.run([sys.executable, "-m", "baselines.prepare", str(frames), "-o", str(target), "--quiet",
                    *capture.prepare_flags], cwd=ROOT, check=True)
    if capture.truth:
        written = write_truth_masks(truth_dir(capture, data_root), target)
        print(f"{capture.name}: {written} ground-truth masks (evaluation only) -> {target / TRUTH_MASKS}")
    return target


def write_truth_masks(annotations: Path, dataset: Path) -> int:
    """`dataset/gt/motion_masks/<stem>.png` (255 = any object id > 0) for every frame in `dataset/images`.

    prepare names a frame by its index in the SOURCE sequence (`00012.png`: the 13th frame), so
    it takes the 13th annotation in name order, resized (nearest) to the prepared frame's size.
    Returns the number written; CaptureError when an annotation is missing or unreadable."""
    files = sorted(p for p in Path(annotations).iterdir() if p.suffix.lower() == ".png")
    out = Path(dataset) / TRUTH_MASKS
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    frames = sorted(p for p in (Path(dataset) / "images").iterdir() if p.is_file())
    for frame in frames:
        index = int(frame.stem)
        if index >= len(files):
            raise CaptureError(f"{annotations} has {len(files)} annotations: none for source frame {index} ({frame.name})")
        labels = cv2.imread(str(files[index]), cv2.IMREAD_UNCHANGED)
        height, width = cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE).shape
        if labels is None:
            raise CaptureError(f"cannot read annotation {files[index]}")
        if labels.ndim == 3:  # a colour palette saved as RGB: any non-black pixel is an object
            labels = labels.max(axis=2)
        moving = cv2.resize((labels > 0).astype("uint8") * 255, (width, height), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(out / f"{frame.stem}.png"), moving)
    return len(frames)
