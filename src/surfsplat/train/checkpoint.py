"""Training checkpoints: everything an exact resume needs, written atomically, read without pickle.

One checkpoint is one folder under `<out_dir>/checkpoints/`:

    step-00000200/
        model.safetensors, model.json   the network, in surfsplat.model.checkpoint's format (loads alone)
        train_state.safetensors         optimizer moments and every rank's RNG states
        train_state.json                step, run config, optimizer groups, schedule, data positions, environment
        manifest.json                   size and SHA-256 of the four files above, written last

Atomicity: the folder is assembled under a hidden temporary name, every file and the folder are
fsync'ed, then one rename publishes it. A process killed at any moment leaves either the complete
folder or a temporary one that readers ignore (and the next writer removes); the newest published
checkpoint is found by listing, so there is no pointer file that could disagree with the folders.
Reading verifies the manifest, so a damaged checkpoint fails loudly instead of resuming wrongly.

Bit-identical resume needs more than the state: the same code and libraries, and the same CPU
thread count (float32 reductions split their sums per thread, so 1 and 2 threads give different
gradients). Every checkpoint records that environment per rank (`capture_environment`); a resume
reuses the thread count when the run left it to the defaults, and names whatever else differs.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import os
import random
import re
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from ..model.checkpoint import save_checkpoint as save_model
from ..model.checkpoint import training_metadata
from ..model.surfsplat import SurfSplat
from ..utils.atomic import fsync_dir, output_error
from ..utils.checks import SurfSplatInputError

FORMAT_NAME = "surfsplat-train-state"
FORMAT_VERSION = 1
CHECKPOINT_DIR = "checkpoints"
_STEP_DIR = re.compile(r"^step-(\d{8,})$")
_TEMP_PREFIX = ".tmp-"
MODEL_FILES = ("model.safetensors", "model.json")
STATE_FILES = ("train_state.safetensors", "train_state.json")
MANIFEST = "manifest.json"


class CorruptCheckpoint(SurfSplatInputError):
    """A published checkpoint whose files do not match its manifest (or are unreadable)."""


@dataclass
class TrainingState:
    """What a checkpoint restores besides the model weights."""

    step: int  # optimizer steps completed
    config: dict[str, Any]  # TrainConfig.to_dict() of the run
    optimizer: dict[str, Any]  # torch optimizer state_dict
    rng: list[dict[str, Any]]  # per rank: {"torch": ByteTensor, "cuda": [ByteTensor], "numpy": ..., "python": ...}
    data: list[dict[str, Any]]  # per rank: position of the data stream (JSON-ready)
    grad_scaler: dict[str, Any] | None = None  # torch.amp.GradScaler state (fp16 runs)
    extra: dict[str, Any] | None = None  # JSON-ready bookkeeping (e.g. last validation metrics)
    environment: list[dict[str, Any]] | None = None  # per rank: `capture_environment` (None: older checkpoints)


def checkpoint_name(step: int) -> str:
    return f"step-{step:08d}"


def checkpoint_root(out_dir: str | Path) -> Path:
    return Path(out_dir) / CHECKPOINT_DIR


# ------------------------------------------------------------------------------------------ RNG
def capture_rng() -> dict[str, Any]:
    """This process's random generators: torch (CPU and every CUDA device), NumPy, Python."""
    np_state = np.random.get_state()
    py_state = random.getstate()
    return {
        "torch": torch.get_rng_state(),
        "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        "numpy": [np_state[0], np_state[1].tolist(), int(np_state[2]), int(np_state[3]), float(np_state[4])],
        "python": [py_state[0], list(py_state[1]), py_state[2]],
    }


def restore_rng(state: Mapping[str, Any]) -> None:
    """Undo `capture_rng`: the generators continue exactly where they were captured."""
    torch.set_rng_state(state["torch"])
    if state["cuda"]:
        if len(state["cuda"]) != torch.cuda.device_count():
            raise SurfSplatInputError(
                f"checkpoint RNG: saved for {len(state['cuda'])} CUDA devices, {torch.cuda.device_count()} visible now"
            )
        torch.cuda.set_rng_state_all(state["cuda"])
    name, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((name, np.asarray(keys, dtype=np.uint32), pos, has_gauss, cached))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))


# ------------------------------------------------------------------------------------------ environment
def source_digest(root: str | Path) -> str:
    """SHA-256 (16 hex digits) of the Python sources under `root`: relative names and contents, sorted."""
    root = Path(root)
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py"), key=lambda p: p.relative_to(root).as_posix()):
        h.update(path.relative_to(root).as_posix().encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


@functools.cache
def software_identity() -> dict[str, str | None]:
    """The code that computes a training step: this package's sources (a digest, so an edited
    working tree counts as other code) and the versions of the numeric libraries. Once per process."""
    return {
        "surfsplat": source_digest(Path(__file__).resolve().parents[1]),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "numba": _version("numba"),
    }


def capture_environment(precision: str) -> dict[str, Any]:
    """What, besides the state, decides this process's steps bit for bit: torch's CPU thread count
    (it splits float32 reductions), the precision the forward passes run in, and the software."""
    return {"cpu_threads": torch.get_num_threads(), "precision": precision, "software": software_identity()}


def changed_entries(saved: Mapping[str, Any], current: Mapping[str, Any], prefix: str = "") -> list[str]:
    """'key: saved -> current' for every entry that differs (nested keys dotted): a checkpoint's
    settings or environment against the resuming run's."""
    out = []
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += changed_entries(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key}: {a!r} -> {b!r}")
    return out


def read_environment(path: str | Path) -> list[dict[str, Any]]:
    """The per-rank environments a checkpoint folder records, read before it is loaded (to start
    the resumed process with the same thread count); [] where there are none or the file is
    unreadable (`load_training_checkpoint` reports damage)."""
    try:
        document = json.loads((Path(path) / STATE_FILES[1]).read_text())
    except (OSError, ValueError):
        return []
    found = document.get("environment") if isinstance(document, dict) else None
    if not isinstance(found, list) or not all(isinstance(e, dict) for e in found):
        return []
    return found


# ------------------------------------------------------------------------------------------ writing
def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _flatten_state(state: TrainingState) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Split the state into tensors (safetensors) and JSON; tensors are referenced by key."""
    tensors: dict[str, Tensor] = {}

    def put(key: str, value: Tensor) -> dict[str, str]:
        tensors[key] = value.detach().contiguous().cpu()
        return {"tensor": key}

    optimizer_state: dict[str, dict[str, Any]] = {}
    for param_id, entries in state.optimizer["state"].items():
        slot: dict[str, Any] = {}
        for name, value in entries.items():
            if isinstance(value, Tensor):
                slot[name] = put(f"optimizer.{param_id}.{name}", value)
            elif isinstance(value, (int, float, bool)) or value is None:
                slot[name] = {"value": value}
            else:
                raise TypeError(f"optimizer state {param_id}.{name}: cannot store a {type(value).__name__}")
        optimizer_state[str(param_id)] = slot
    rng = []
    for rank, states in enumerate(state.rng):
        rng.append(
            {
                "torch": put(f"rng.{rank}.torch", states["torch"]),
                "cuda": [put(f"rng.{rank}.cuda.{i}", s) for i, s in enumerate(states["cuda"])],
                "numpy": states["numpy"],
                "python": states["python"],
            }
        )
    document = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "step": state.step,
        "config": state.config,
        "optimizer": {"state": optimizer_state, "param_groups": state.optimizer["param_groups"]},
        "rng": rng,
        "data": state.data,
        "grad_scaler": state.grad_scaler,
        "extra": state.extra,
        "environment": state.environment,
    }
    return tensors, document


def _clean_temporaries(root: Path) -> None:
    """Remove folders left by writers that were killed (never a published checkpoint)."""
    for path in root.glob(_TEMP_PREFIX + "*"):
        shutil.rmtree(path, ignore_errors=False)


def save_training_checkpoint(out_dir: str | Path, model: SurfSplat, state: TrainingState, keep: int = 0) -> Path:
    """Publish checkpoint `step-<state.step>` atomically; keep the newest `keep` (0 = all).

    Call on one process only (rank 0). Returns the published folder.
    """
    root = checkpoint_root(out_dir)
    root.mkdir(parents=True, exist_ok=True)
    _clean_temporaries(root)
    final = root / checkpoint_name(state.step)
    temp = root / f"{_TEMP_PREFIX}{checkpoint_name(state.step)}-{os.getpid()}"
    temp.mkdir()
    try:
        save_model(model, temp / "model", metadata=weights_metadata(state))
        tensors, document = _flatten_state(state)
        save_file(tensors, str(temp / STATE_FILES[0]), metadata={"format": FORMAT_NAME})
        (temp / STATE_FILES[1]).write_text(json.dumps(document, indent=1))
        files = {}
        for name in MODEL_FILES + STATE_FILES:
            path = temp / name
            _fsync_file(path)
            files[name] = {"bytes": path.stat().st_size, "sha256": _sha256(path)}
        manifest = temp / MANIFEST
        manifest.write_text(json.dumps({"format": FORMAT_NAME, "step": state.step, "files": files}, indent=1))
        _fsync_file(manifest)
        fsync_dir(temp, strict=True)
    except BaseException as err:
        # Interrupted (Ctrl-C, SIGTERM) or failed (full disk, NaN weights): the unpublished folder goes.
        shutil.rmtree(temp, ignore_errors=True)
        if isinstance(err, OSError):
            raise output_error(final, err) from None
        raise
    if final.exists():
        # A folder for this step survives from a run that was killed after publishing it and
        # resumed from an earlier step: move it aside first, a rename cannot replace a full folder.
        stale = root / f"{_TEMP_PREFIX}stale-{final.name}-{os.getpid()}"
        final.rename(stale)
        temp.rename(final)
        shutil.rmtree(stale)
    else:
        temp.rename(final)
    fsync_dir(root, strict=True)
    if keep > 0:
        for old in list_checkpoints(out_dir)[:-keep]:
            # Unpublish with one rename before deleting: a kill during rmtree must not leave a
            # half-deleted folder under a published name.
            doomed = root / f"{_TEMP_PREFIX}old-{old.name}-{os.getpid()}"
            old.rename(doomed)
            shutil.rmtree(doomed)
    return final


def weights_metadata(state: TrainingState) -> dict[str, Any]:
    """What `surfsplat weights info` shows about a trained model: preset, resolution, steps, source."""
    return training_metadata(state.step, state.config)


# ------------------------------------------------------------------------------------------ reading
def list_checkpoints(out_dir: str | Path) -> list[Path]:
    """Published checkpoint folders, oldest first."""
    root = checkpoint_root(out_dir)
    if not root.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in root.iterdir() if p.is_dir() and (m := _STEP_DIR.match(p.name))]
    return [p for _, p in sorted(found)]


def latest_checkpoint(out_dir: str | Path) -> Path | None:
    """The newest published checkpoint folder, or None."""
    found = list_checkpoints(out_dir)
    return found[-1] if found else None


def verify_checkpoint(path: str | Path) -> dict[str, Any]:
    """Check every file against the manifest; returns the manifest or raises CorruptCheckpoint."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: checkpoint folder not found")
    manifest_path = path / MANIFEST
    try:
        manifest = json.loads(manifest_path.read_text())
    except FileNotFoundError:
        raise CorruptCheckpoint(f"{manifest_path}: missing; the checkpoint was not written completely") from None
    except ValueError as err:
        raise CorruptCheckpoint(f"{manifest_path}: not valid JSON ({err})") from None
    if (
        not isinstance(manifest, dict)
        or manifest.get("format") != FORMAT_NAME
        or not isinstance(manifest.get("files"), dict)
    ):
        raise CorruptCheckpoint(f"{manifest_path}: not a SurfSplat training manifest")
    for name in MODEL_FILES + STATE_FILES:
        entry = manifest["files"].get(name)
        file = path / name
        if not isinstance(entry, dict):
            raise CorruptCheckpoint(f"{manifest_path}: no entry for {name}")
        if not file.is_file():
            raise CorruptCheckpoint(f"{file}: missing")
        if file.stat().st_size != entry.get("bytes") or _sha256(file) != entry.get("sha256"):
            raise CorruptCheckpoint(f"{file}: contents do not match the manifest (damaged or modified)")
    return manifest


def _restore_tensors(node: Any, tensors: Mapping[str, Tensor], where: str) -> Any:
    if isinstance(node, dict) and set(node) == {"tensor"}:
        key = node["tensor"]
        if key not in tensors:
            raise CorruptCheckpoint(f"{where}: tensor {key} missing from {STATE_FILES[0]}")
        return tensors[key].clone()  # owned memory: nothing refers to the checkpoint file after loading
    return node


def load_training_checkpoint(
    path: str | Path, model: nn.Module, map_location: str | torch.device = "cpu"
) -> TrainingState:
    """Verify `path`, load its weights into `model` (same configuration required), return the rest."""
    path = Path(path)
    verify_checkpoint(path)
    model_meta = json.loads((path / "model.json").read_text())
    if isinstance(model, SurfSplat) and model_meta.get("config") != json.loads(json.dumps(model.cfg.to_dict())):
        raise SurfSplatInputError(
            f"{path / 'model.json'}: the checkpoint's model configuration differs from the model being trained"
        )
    try:
        weights = load_file(str(path / MODEL_FILES[0]), device=str(map_location))
        tensors = load_file(str(path / STATE_FILES[0]))
    except SafetensorError as err:
        raise CorruptCheckpoint(f"{path}: unreadable safetensors file ({err})") from None
    missing, unexpected = model.load_state_dict(weights, strict=False)
    if missing or unexpected:
        raise SurfSplatInputError(
            f"{path / MODEL_FILES[0]}: missing keys {missing[:10]}, unexpected keys {unexpected[:10]}"
        )
    document = json.loads((path / STATE_FILES[1]).read_text())
    if document.get("format") != FORMAT_NAME or document.get("version") != FORMAT_VERSION:
        raise SurfSplatInputError(
            f"{path / STATE_FILES[1]}: expected format {FORMAT_NAME} version {FORMAT_VERSION}, "
            f"got {document.get('format')} version {document.get('version')}"
        )
    where = str(path / STATE_FILES[1])
    optimizer_state = {
        int(param_id): {
            name: (_restore_tensors(v, tensors, where) if "tensor" in v else v["value"]) for name, v in slot.items()
        }
        for param_id, slot in document["optimizer"]["state"].items()
    }
    rng = [
        {
            "torch": _restore_tensors(r["torch"], tensors, where),
            "cuda": [_restore_tensors(c, tensors, where) for c in r["cuda"]],
            "numpy": r["numpy"],
            "python": r["python"],
        }
        for r in document["rng"]
    ]
    return TrainingState(
        step=int(document["step"]),
        config=document["config"],
        optimizer={"state": optimizer_state, "param_groups": document["optimizer"]["param_groups"]},
        rng=rng,
        data=document["data"],
        grad_scaler=document.get("grad_scaler"),
        extra=document.get("extra"),
        environment=document.get("environment"),
    )
