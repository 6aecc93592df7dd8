"""4DGS-layout checkpoints, written atomically.

Layout (4DGS's, so either code base reads the other's output)::

    <model_path>/point_cloud/iteration_N/         fine stage (coarse_iteration_N for coarse)
        point_cloud.ply          3DGS/4DGS Gaussian PLY (pre-activation values)
        deformation.pth          deformation module state_dict (4DGS key names)
        deformation_table.pth    [N] bool
        deformation_accum.pth    [N, 3] float
        extra_buffers.pth        ours: registered per-Gaussian buffers/parameters (optional on load)
        manifest.json            ours: every file the saving run wrote here (plugins' too), size + sha256
    <model_path>/chkpnt_<stage>_<N>.pth            full training state (capture() + iteration)

Every file is written to a temporary file in the same folder, flushed, fsync'ed and renamed
over the target, so a killed run leaves either the old file or the new one, never a torn one.
An iteration folder is written whole under a temporary name (``point_cloud/.iteration_N.tmp-*``)
and renamed into place once complete, so `find_latest_iteration`, render.py and a resume never
see a half-written one. A failed write (full disk, read-only folder) raises ``SaveError`` (an
``OSError``) naming the file and the OS reason, after removing what it had written.
Loading checks everything (shapes, SH degree, state-dict keys) before changing the model and
raises ``ValueError`` naming the file. A folder with a ``manifest.json`` must still hold every
file listed there, byte for byte (`check_iteration_folder`): a missing ``extra_buffers.pth`` or a
``deformation.pth`` copied in from another run is refused rather than rendered as if complete.
Folders without one (4DGS's, older runs) are loaded as before.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch
from plyfile import PlyData, PlyElement
from torch import Tensor

from baselines.fourdgs.deformation import check_deformation_state
from baselines.fourdgs.gaussian_model import GaussianModel
from baselines.fourdgs.numpy_globals import allow_numpy_scalars
from baselines.fourdgs.state import GaussianState

PLY_FILE = "point_cloud.ply"
DEFORMATION_FILE = "deformation.pth"
TABLE_FILE = "deformation_table.pth"
ACCUM_FILE = "deformation_accum.pth"
EXTRA_FILE = "extra_buffers.pth"
EXTRA_FORMAT = "reflow-4dgs/extra-buffers"
MANIFEST_FILE = "manifest.json"
MANIFEST_FORMAT = "reflow-4dgs/iteration-files"
TRAINING_STATE_FORMAT = "reflow-4dgs/training-state"
FORMAT_VERSION = 1


# --------------------------------------------------------------------------------------------
# Atomic writers.
class SaveError(OSError):
    """A file or folder could not be written: the path and the OS reason, in one line."""

    def __init__(self, path: str | os.PathLike, cause: BaseException) -> None:
        if isinstance(cause, SaveError):
            reason, errno = cause.reason, cause.errno
        else:
            os_error = _os_cause(cause)
            errno = os_error.errno if os_error is not None else None
            text = str(cause).strip()
            reason = (f"[Errno {os_error.errno}] {os_error.strerror}" if os_error is not None and os_error.strerror
                      else text.splitlines()[0] if text else type(cause).__name__)
        super().__init__(errno, reason)
        self.path, self.reason = Path(path), reason

    def __str__(self) -> str:
        return f"cannot write {self.path}: {self.reason}"


class FolderContentError(ValueError):
    """A checkpoint file that is missing, unreadable or not the one its run saved (no config can fix
    it, unlike a shape mismatch: callers add no "pass --configs" hint to these)."""


def _os_cause(error: BaseException | None) -> OSError | None:
    """The OSError behind `error` (torch reports a failed write as a RuntimeError whose context it is)."""
    seen = 0
    while error is not None and seen < 8:
        if isinstance(error, OSError):
            return error
        error, seen = error.__cause__ or error.__context__, seen + 1
    return None


def _atomic_write(path: str | os.PathLike, write: Callable[[IO[bytes]], None]) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp", delete=False)
    except OSError as err:
        raise SaveError(path, err) from None
    try:
        with handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(handle.name, path)
    except BaseException as err:
        try:
            os.unlink(handle.name)
        except FileNotFoundError:
            pass
        if isinstance(err, SaveError) or not (isinstance(err, OSError) or _os_cause(err) is not None):
            raise
        raise SaveError(path, err) from None
    _fsync_directory(path.parent)
    return path


def _fsync_directory(directory: Path) -> None:
    # Makes the rename itself durable; not every platform/filesystem allows opening a folder.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save(obj, path)`` through a temporary file + fsync + rename."""
    return _atomic_write(path, lambda f: torch.save(obj, f))


def atomic_write_ply(ply: PlyData, path: str | os.PathLike) -> Path:
    """Write a ``PlyData`` through a temporary file + fsync + rename."""
    return _atomic_write(path, ply.write)


def _torch_load(path: Path, map_location: Any, trusted: bool = False) -> Any:
    if not path.is_file():
        raise FolderContentError(f"{path}: file not found")
    try:
        with allow_numpy_scalars():  # 4DGS checkpoints hold numpy.float64 learning rates
            return torch.load(path, map_location=map_location, weights_only=not trusted)
    except Exception as err:  # torch raises many types for corrupt/foreign files
        raise FolderContentError(f"{path}: cannot be read as a torch file of this project or 4DGS "
                                 f"({_load_reason(err)})") from None


def _load_reason(err: Exception) -> str:
    """One line for torch.load's failure (its weights-only message is a page of advice)."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    if lines and lines[0].startswith("Weights only load failed"):
        detail = next((line for line in lines[1:] if not line.startswith(("Please file", "Check the"))), "")
        return ("it holds objects other than tensors and numbers, or is not a torch file"
                + (f": {detail}" if detail else ""))
    return f"{type(err).__name__}: {lines[0] if lines else ''}".rstrip(": ")


# --------------------------------------------------------------------------------------------
# Paths.
def point_cloud_dir(model_path: str | os.PathLike, iteration: int, stage: str = "fine") -> Path:
    """``<model_path>/point_cloud/iteration_N`` (fine) or ``coarse_iteration_N`` (coarse)."""
    if stage not in ("coarse", "fine"):
        raise ValueError(f"stage must be 'coarse' or 'fine', got {stage!r}")
    prefix = "coarse_iteration" if stage == "coarse" else "iteration"
    return Path(model_path) / "point_cloud" / f"{prefix}_{int(iteration)}"


def training_state_path(model_path: str | os.PathLike, stage: str, iteration: int) -> Path:
    """``<model_path>/chkpnt_<stage>_<N>.pth`` (4DGS's name)."""
    return Path(model_path) / f"chkpnt_{stage}_{int(iteration)}.pth"


def find_latest_iteration(model_path: str | os.PathLike, stage: str = "fine") -> int | None:
    """Largest N with a ``point_cloud/(coarse_)iteration_N`` folder, or None."""
    root = Path(model_path) / "point_cloud"
    pattern = re.compile(r"coarse_iteration_(\d+)" if stage == "coarse" else r"iteration_(\d+)")
    if not root.is_dir():
        return None
    found = [int(m.group(1)) for p in root.iterdir() if p.is_dir() and (m := pattern.fullmatch(p.name))]
    return max(found) if found else None


# --------------------------------------------------------------------------------------------
# Gaussian PLY (3DGS/4DGS format).
def ply_attribute_names(num_rest_coefficients: int) -> list[str]:
    """x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3 (4DGS's order)."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * num_rest_coefficients)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_ply(model: GaussianModel) -> PlyData:
    """The model's stored (canonical) Gaussians as a binary little-endian 3DGS PLY."""
    return state_to_ply(model.canonical_state())


def state_to_ply(state: GaussianState) -> PlyData:
    """N Gaussians (pre-activation, e.g. ``model.deform(t, "fine")``) as a binary little-endian 3DGS PLY.

    The layout Inria's 3DGS and its viewers read: x y z, nx ny nz (zeros), f_dc_0..2, f_rest_*,
    opacity (logit), scale_0..2 (log), rot_0..3 (w first, unnormalised). SH features are written
    channel-major (all R coefficients, then G, then B), i.e. the transposed [N, 3, K] layout
    flattened, as 3DGS/4DGS do.
    """
    count = state.num_gaussians

    def flat(t: Tensor) -> np.ndarray:
        return t.detach().float().cpu().reshape(count, -1).numpy()

    columns = [
        flat(state.means),
        np.zeros((count, 3), dtype=np.float32),
        flat(state.shs[:, :1].transpose(1, 2)),
        flat(state.shs[:, 1:].transpose(1, 2)),
        flat(state.opacity_logits),
        flat(state.log_scales),
        flat(state.rotations),
    ]
    values = np.ascontiguousarray(np.concatenate(columns, axis=1), dtype="<f4")
    names = ply_attribute_names(state.shs.shape[1] - 1)
    records = values.view(np.dtype([(n, "<f4") for n in names])).reshape(count)
    return PlyData([PlyElement.describe(records, "vertex")], byte_order="<")


def read_gaussian_ply(path: str | os.PathLike, sh_degree: int) -> dict[str, Tensor]:
    """Per-Gaussian float32 tensors (keys xyz, f_dc, f_rest, opacity, scaling, rotation) of a PLY.

    Raises ``ValueError`` naming the file if it is unreadable, lacks properties, holds another
    SH degree than ``sh_degree`` or contains NaN/inf (unreadable or NaN/inf: `FolderContentError`).
    """
    path = Path(path)
    if not path.is_file():
        raise FolderContentError(f"{path}: file not found")
    try:
        ply = PlyData.read(str(path))
        vertex = ply["vertex"]
        names = [p.name for p in vertex.properties]
    except Exception as err:
        raise FolderContentError(f"{path}: not a readable Gaussian PLY ({type(err).__name__}: {err})") from None
    count = vertex.count

    def columns(prefix: str, expected: int | None = None) -> np.ndarray:
        found = sorted((n for n in names if re.fullmatch(rf"{prefix}_\d+", n)), key=lambda n: int(n.rsplit("_", 1)[1]))
        wanted = [f"{prefix}_{i}" for i in range(len(found))]
        if found != wanted or (expected is not None and len(found) != expected):
            raise ValueError(f"{path}: expected properties {prefix}_0..{prefix}_{(expected or 1) - 1}, found {found}")
        if not found:
            return np.zeros((count, 0), np.float32)
        return np.stack([np.asarray(vertex[n], dtype=np.float32) for n in found], axis=1)

    for required in ("x", "y", "z", "opacity"):
        if required not in names:
            raise ValueError(f"{path}: missing property {required!r}")
    rest = (sh_degree + 1) ** 2 - 1
    num_rest = sum(1 for n in names if re.fullmatch(r"f_rest_\d+", n))
    if num_rest != 3 * rest:
        degree = (num_rest // 3 + 1) ** 0.5 - 1
        valid = degree == int(degree) and num_rest % 3 == 0
        degree_text = f"SH degree {int(degree)}" if valid else "no valid SH degree"
        raise ValueError(
            f"{path}: {num_rest} f_rest properties ({degree_text}), the model has SH degree {sh_degree} "
            f"({3 * rest} f_rest properties)"
        )
    xyz = np.stack([np.asarray(vertex[a], dtype=np.float32) for a in "xyz"], axis=1)
    f_dc = columns("f_dc", 3)
    f_rest = columns("f_rest", 3 * rest).reshape(count, 3, rest).transpose(0, 2, 1)
    arrays = {
        "xyz": xyz,
        "f_dc": f_dc.reshape(count, 1, 3),
        "f_rest": np.ascontiguousarray(f_rest),
        "opacity": np.asarray(vertex["opacity"], dtype=np.float32)[:, None],
        "scaling": columns("scale", 3),
        "rotation": columns("rot", 4),
    }
    for name, array in arrays.items():
        if not np.isfinite(array).all():  # a damaged file: no --configs fixes it
            raise FolderContentError(f"{path}: {name} values contain NaN or inf")
    return {name: torch.from_numpy(np.ascontiguousarray(array)) for name, array in arrays.items()}


# --------------------------------------------------------------------------------------------
# point_cloud/iteration_N folders.
def save_point_cloud_dir(model: GaussianModel, directory: str | os.PathLike,
                         before_publish: Callable[[Path], None] | None = None) -> Path:
    """Write the 4DGS files plus ``extra_buffers.pth`` as the folder ``directory``, atomically.

    The files go into a temporary sibling folder; ``before_publish(temporary folder)`` may add
    files (the plugins' ``on_save``); then the folder is renamed to ``directory`` (an existing
    one is replaced). On failure nothing is left but what was there before (``SaveError``).
    """
    directory = Path(directory)
    try:
        directory.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(dir=directory.parent, prefix=f".{directory.name}.tmp-"))
    except OSError as err:
        raise SaveError(directory, err) from None
    try:
        _write_point_cloud_files(model, staging)
        if before_publish is not None:
            before_publish(staging)
        _write_manifest(staging)
        _publish_folder(staging, directory)
    except SaveError as err:  # name the folder being saved, not its temporary name
        shutil.rmtree(staging, ignore_errors=True)
        file = err.path.relative_to(staging) if err.path.is_relative_to(staging) else None
        raise SaveError(directory / file if file else directory, err) from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return directory


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _write_manifest(directory: Path) -> None:
    """Record every file of the (staged) iteration folder: relative path -> size and sha256."""
    files = {str(p.relative_to(directory)): {"bytes": p.stat().st_size, "sha256": _file_digest(p)}
             for p in sorted(directory.rglob("*")) if p.is_file() and p.name != MANIFEST_FILE}
    text = json.dumps({"format": MANIFEST_FORMAT, "version": FORMAT_VERSION, "files": files}, indent=1) + "\n"
    _atomic_write(directory / MANIFEST_FILE, lambda f: f.write(text.encode()))


def check_iteration_folder(directory: str | os.PathLike) -> None:
    """Refuse (ValueError, one line) an iteration folder that lacks or altered a file its saving run
    recorded in ``manifest.json``; a folder without a manifest (4DGS's, older runs) passes."""
    directory = Path(directory)
    manifest_path = directory / MANIFEST_FILE
    if not manifest_path.is_file():
        return
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
        files = manifest["files"] if manifest.get("format") == MANIFEST_FORMAT else None
        if not isinstance(files, dict):
            raise FolderContentError("not this project's manifest")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise FolderContentError(f"{manifest_path}: cannot be read ({err}); the folder's files cannot be checked") from None
    missing = [name for name in files if not (directory / name).is_file()]
    if missing:
        raise FolderContentError(f"{directory} is incomplete: {', '.join(missing)} missing (the run that saved it wrote "
                         f"{len(files)} files); copy the folder whole, or use another iteration")
    for name, facts in files.items():
        path = directory / name
        if path.stat().st_size != facts.get("bytes") or _file_digest(path) != facts.get("sha256"):
            raise FolderContentError(f"{path} is not the file the run saved there (its size or content hash differs from "
                             f"{MANIFEST_FILE}): another run's copy? Put back the original, or use another iteration")


def _publish_folder(staging: Path, directory: Path) -> None:
    """Rename the complete `staging` folder to `directory` (replacing an old one)."""
    old = None
    try:
        if directory.exists():
            old = directory.with_name(f".{directory.name}.old-{os.getpid()}")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(directory, old)
        os.replace(staging, directory)
    except OSError as err:
        if old is not None and not directory.exists():
            os.replace(old, directory)
        raise SaveError(directory, err) from None
    _fsync_directory(directory.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _write_point_cloud_files(model: GaussianModel, directory: Path) -> None:
    state = model._deformation.state_dict()
    for key in state:
        state[key] = state[key].detach().cpu()
    atomic_write_ply(gaussians_to_ply(model), directory / PLY_FILE)
    atomic_save(state, directory / DEFORMATION_FILE)
    atomic_save(model._deformation_table.detach().cpu(), directory / TABLE_FILE)
    atomic_save(model._deformation_accum.detach().cpu(), directory / ACCUM_FILE)
    extras = {
        "format": EXTRA_FORMAT,
        "version": FORMAT_VERSION,
        "buffers": {n: v.detach().cpu() for n, v in model.registered_buffers.items()},
        "parameters": {n: v.detach().cpu() for n, v in model.registered_parameters.items()},
        "parameter_lrs": dict(model.registered_parameter_lrs),
    }
    atomic_save(extras, directory / EXTRA_FILE)


def _module_device(module: torch.nn.Module) -> torch.device:
    for tensor in module.parameters():
        return tensor.device
    return torch.device("cpu")


def load_point_cloud_dir(
    directory: str | os.PathLike, model: GaussianModel, device: torch.device | str | None = None
) -> None:
    """Load a 4DGS ``point_cloud/iteration_N`` folder (ours or 4DGS's) into ``model``.

    As 4DGS's ``load_ply`` + ``load_model``: the active SH degree becomes the maximum, a missing
    deformation table means "all deformed", a missing accumulator zeros, statistics restart at
    zero. Registered per-Gaussian buffers/parameters become those of ``extra_buffers.pth`` (none
    if the file is absent). The optimizer is dropped: call ``training_setup`` afterwards, and set
    ``spatial_lr_scale`` first if the model was not created from a point cloud.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise ValueError(f"{directory}: checkpoint folder not found")
    check_iteration_folder(directory)  # every file its run saved, unchanged
    device = torch.device(device) if device is not None else _module_device(model._deformation)
    rows = read_gaussian_ply(directory / PLY_FILE, model.max_sh_degree)
    count = rows["xyz"].shape[0]
    deformation_state = _torch_load(directory / DEFORMATION_FILE, "cpu")
    complete = getattr(model._deformation, "complete_foreign_state", None)
    if complete is not None and isinstance(deformation_state, Mapping):  # e.g. a plugin's extra branch
        deformation_state = complete(deformation_state)
    check_deformation_state(model._deformation, deformation_state, str(directory / DEFORMATION_FILE))

    table = None
    if (directory / TABLE_FILE).exists():
        table = _load_rows(directory / TABLE_FILE, count, (count,))
    accum = None
    if (directory / ACCUM_FILE).exists():
        accum = _load_rows(directory / ACCUM_FILE, count, (count, 3))
    extras: Mapping[str, Any] = {"buffers": {}, "parameters": {}, "parameter_lrs": {}}
    if (directory / EXTRA_FILE).exists():
        extras = _load_extras(directory / EXTRA_FILE, count)

    model.unfreeze(model.frozen_groups)
    model._deformation = model._deformation.to(device)
    model._deformation.load_state_dict(deformation_state, strict=True)
    model.set_gaussians(rows, table, accum, device, str(directory / PLY_FILE))
    model.active_sh_degree = model.max_sh_degree
    model.set_extras(extras["buffers"], extras["parameters"], extras["parameter_lrs"], str(directory / EXTRA_FILE))


def _load_rows(path: Path, count: int, shape: tuple[int, ...]) -> Tensor:
    value = _torch_load(path, "cpu")
    if not isinstance(value, Tensor) or tuple(value.shape) != shape:
        got = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(f"{path}: expected a tensor of shape {list(shape)} ({count} Gaussians in the PLY), got {got}")
    return value


def _load_extras(path: Path, count: int) -> Mapping[str, Any]:
    extras = _torch_load(path, "cpu")
    if not isinstance(extras, Mapping) or extras.get("format") != EXTRA_FORMAT:
        raise ValueError(f"{path}: not an extra-buffers file of this project")
    for kind in ("buffers", "parameters"):
        for name, value in extras.get(kind, {}).items():
            if not isinstance(value, Tensor) or value.dim() == 0 or value.shape[0] != count:
                got = list(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(f"{path}: {kind[:-1]} {name!r} has shape {got}, expected {count} rows")
    return {"buffers": extras.get("buffers", {}), "parameters": extras.get("parameters", {}),
            "parameter_lrs": extras.get("parameter_lrs", {})}


# --------------------------------------------------------------------------------------------
# Full training state (chkpnt_<stage>_<N>.pth).
@dataclass
class TrainingState:
    """A loaded ``chkpnt`` file: pass ``capture`` to ``GaussianModel.restore``."""

    capture: tuple
    iteration: int
    stage: str | None
    extra: dict[str, Any] = field(default_factory=dict)
    is_4dgs_format: bool = False


def save_training_state(
    path: str | os.PathLike, model: GaussianModel, iteration: int, stage: str, extra: Mapping[str, Any] | None = None
) -> Path:
    """Atomically write ``capture()`` (optimizer included), iteration, stage and ``extra``.

    ``extra`` (e.g. trainer or plugin state) may hold tensors and plain Python values.
    """
    payload = {
        "format": TRAINING_STATE_FORMAT,
        "version": FORMAT_VERSION,
        "capture": model.capture(),
        "iteration": int(iteration),
        "stage": stage,
        "extra": dict(extra or {}),
    }
    return atomic_save(payload, path)


def load_training_state(
    path: str | os.PathLike, map_location: Any = "cpu", trusted: bool = False
) -> TrainingState:
    """Read a training state written by ``save_training_state`` or by 4DGS's train.py.

    4DGS stores ``(capture_tuple, iteration)``; its stage is taken from the file name
    (``chkpnt_<stage>_<N>.pth``) when it follows 4DGS's pattern. ``trusted=True`` allows
    arbitrary pickled objects (only for files you wrote yourself).
    """
    path = Path(path)
    payload = _torch_load(path, map_location, trusted)
    if isinstance(payload, Mapping) and payload.get("format") == TRAINING_STATE_FORMAT:
        capture = payload.get("capture")
        if not isinstance(capture, (tuple, list)):
            raise ValueError(f"{path}: training state without a capture tuple")
        return TrainingState(tuple(capture), int(payload["iteration"]), payload.get("stage"),
                             dict(payload.get("extra", {})))
    if isinstance(payload, (tuple, list)) and len(payload) == 2 and isinstance(payload[0], (tuple, list)):
        match = re.fullmatch(r"chkpnt_(coarse|fine)_(\d+)\.pth", path.name)
        return TrainingState(tuple(payload[0]), int(payload[1]), match.group(1) if match else None, {}, True)
    raise ValueError(f"{path}: neither this project's training state nor 4DGS's (capture, iteration) tuple")
