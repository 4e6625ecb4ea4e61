"""Which ``checkpoint-N`` a training run resumes from: the newest COMPLETE one.

The Trainer writes a checkpoint file by file into ``checkpoint-N`` (weights, optimizer, scheduler,
RNG state, ``trainer_state.json`` last). A run killed while it writes leaves a folder that
``transformers.trainer_utils.get_last_checkpoint`` still picks, and the resume then dies on it
(``SafetensorError`` on a truncated ``model.safetensors``). :func:`last_complete_checkpoint` picks
the newest folder whose files are all whole and skips the others with a warning; they stay on disk
(the Trainer's rotation removes them in time) so nothing is deleted behind the user's back.
:func:`complete_checkpoints` lists every complete one, oldest first: what ``rl_remote.sh pack`` carries
to the next host (a folder the Trainer is still writing is left behind).

The check is the guarantee; checkpoints are not staged in a temporary folder and renamed. The
Trainer itself did that in transformers 4.36 (``tmp-checkpoint-N``): ranks racing on the rename
broke multi-GPU and multi-node saves (transformers issues 27925, 28119) and it was taken out again,
and redirecting ``_save_checkpoint`` from a subclass would mean copying it.

A checkpoint is complete when ``trainer_state.json`` parses and names its step, it holds weights
(``model.safetensors``, a sharded index with every shard, an adapter, or a DeepSpeed
``global_step*`` folder), every ``*.safetensors`` has a readable header whose tensors end exactly
at the end of the file, and every ``torch.save`` file (``optimizer.pt``, ``scheduler.pt``,
``rng_state*.pth``, ``*.bin``) is a readable zip archive (a cut one has no central directory).
"""

from __future__ import annotations

import json
import logging
import re
import struct
import zipfile
from pathlib import Path

from safetensors import safe_open

__all__ = ["checkpoint_problem", "complete_checkpoints", "last_complete_checkpoint", "run_folder",
           "weights_problem"]

logger = logging.getLogger(__name__)

# The Trainer's folder names (transformers.trainer_utils.PREFIX_CHECKPOINT_DIR): spelled here, since
# importing that module loads torch and peft (seconds) and rl_remote.sh lists checkpoints in a shell loop.
_CHECKPOINT = re.compile(r"^checkpoint-(\d+)$")
_WEIGHTS = ("model.safetensors", "model.safetensors.index.json", "adapter_model.safetensors",
            "pytorch_model.bin", "pytorch_model.bin.index.json", "adapter_model.bin")
_TORCH_SAVE_SUFFIXES = (".pt", ".pth", ".bin")


def run_folder(folder: str | Path) -> Path:
    """The run folder of a Trainer checkpoint ``<run>/checkpoint-N``; any other folder as it is."""
    folder = Path(folder)
    return folder.parent if _CHECKPOINT.match(folder.name) else folder


def _safetensors_problem(path: Path) -> str | None:
    """Why ``path`` is not a whole safetensors file, or None."""
    size = path.stat().st_size
    try:
        with path.open("rb") as fh:
            (n,) = struct.unpack("<Q", fh.read(8))
            if n > size - 8:
                return f"{path.name}: header of {n} bytes in a file of {size}"
            header = json.loads(fh.read(n))
        end = max((t["data_offsets"][1] for k, t in header.items() if k != "__metadata__"), default=0)
        if 8 + n + end != size:
            return f"{path.name}: {size} bytes, its header describes {8 + n + end}"
        with safe_open(str(path), framework="numpy"):  # checks the header; numpy: no torch to import
            pass
    except (struct.error, ValueError, KeyError, TypeError, OSError) as exc:  # SafetensorError is an OSError
        return f"{path.name}: {exc}"
    except Exception as exc:  # safetensors' own error type differs between versions
        return f"{path.name}: {type(exc).__name__}: {exc}"
    return None


def checkpoint_problem(folder: str | Path) -> str | None:
    """Why the checkpoint ``folder`` is incomplete (one line), or None when it is complete."""
    folder = Path(folder)
    state = folder / "trainer_state.json"
    if not state.is_file():
        return "no trainer_state.json (the Trainer writes it last)"
    try:
        if not isinstance(json.loads(state.read_text()).get("global_step"), int):
            return "trainer_state.json names no global_step"
    except (ValueError, AttributeError) as exc:
        return f"trainer_state.json: {exc}"
    return weights_problem(folder)


def weights_problem(folder: str | Path) -> str | None:
    """Why the weights saved in ``folder`` are missing or cut short (one line), or None."""
    folder = Path(folder)
    names = {p.name for p in folder.iterdir()}
    if not names.intersection(_WEIGHTS) and not any(n.startswith("global_step") for n in names):
        return "no weights (model.safetensors, an adapter or a DeepSpeed global_step folder)"
    for index_name in ("model.safetensors.index.json", "pytorch_model.bin.index.json"):
        if index_name in names:
            try:
                shards = set(json.loads((folder / index_name).read_text())["weight_map"].values())
            except (ValueError, KeyError, AttributeError) as exc:
                return f"{index_name}: {exc}"
            missing = sorted(shards - names)
            if missing:
                return f"{index_name} lists missing shards {missing}"
    for path in sorted(folder.iterdir()):
        if path.suffix == ".safetensors":
            problem = _safetensors_problem(path)
        elif path.suffix in _TORCH_SAVE_SUFFIXES and path.is_file():
            problem = None if zipfile.is_zipfile(path) else f"{path.name}: not a whole torch.save archive"
        else:
            continue
        if problem:
            return problem
    return None


def _checkpoint_folders(run_dir: str | Path) -> list[Path]:
    """The ``checkpoint-N`` folders under ``run_dir`` in step order (checkpoint-10 after checkpoint-4),
    complete or not; none when ``run_dir`` is not a folder."""
    root = Path(run_dir)
    if not root.is_dir():
        return []
    found = ((int(m.group(1)), p) for p in root.iterdir() if p.is_dir() and (m := _CHECKPOINT.match(p.name)))
    return [p for _, p in sorted(found)]


def complete_checkpoints(run_dir: str | Path) -> list[Path]:
    """The complete ``checkpoint-N`` folders under ``run_dir`` in step order, oldest first; an
    incomplete one (being written, or cut short) is left out."""
    return [p for p in _checkpoint_folders(run_dir) if checkpoint_problem(p) is None]


def last_complete_checkpoint(output_dir: str | Path) -> str | None:
    """The newest complete ``checkpoint-N`` under ``output_dir`` (a path string, as the Trainer's
    ``resume_from_checkpoint`` takes it), or None when there is none; incomplete newer ones are
    skipped with a warning naming what is wrong."""
    for path in reversed(_checkpoint_folders(output_dir)):
        problem = checkpoint_problem(path)
        if problem is None:
            return str(path)
        logger.warning("skipping incomplete checkpoint %s: %s", path, problem)
    return None
