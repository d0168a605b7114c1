"""Checkpoints kept in the repository, in parts of at most 15 MB, each part checked by its sha256.

Two kinds, each a folder:
- the shipped model's weights (``save_parts``): fp16, ``checkpoint.json`` + ``part-000.bin`` ...; ``python -m export
  train --init FOLDER`` starts a new cycle from it (no optimiser: it would double the size), and ``python -m export
  onnx FOLDER`` exports it;
- a run's exact training state (``save_state``): float32 weights, the optimiser's momenta and the RNG, byte-shuffled
  and deflated (float32 weights alone hardly compress; their bytes sorted by rank do, by about a sixth), ``state.json``
  + ``state-<hash>-000.bin`` ...; ``python -m export train --keep FOLDER --resume`` goes on from it bit for bit. The
  manifest is replaced last and atomically, so a run killed while writing leaves the state before it whole.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zlib
from pathlib import Path

import numpy as np
import torch

from pomar.cli import InputError

#: Largest part written (bytes): under the 16 MB a file in the repository or a device run's $OUT may have.
PART_BYTES = 15_000_000
MANIFEST = "checkpoint.json"
STATE_MANIFEST = "state.json"


class CheckpointError(InputError, ValueError):
    """A checkpoint that is torn, damaged or not of the kind asked for; the message names the file."""


def is_parts(path) -> bool:
    return (Path(path) / MANIFEST).is_file()


def is_state(path) -> bool:
    return (Path(path) / STATE_MANIFEST).is_file()


def _write_chunks(data: bytes, folder: Path, prefix: str, part_bytes: int) -> list[dict]:
    parts = []
    for i in range(0, max(len(data), 1), part_bytes):
        p = folder / f"{prefix}{i // part_bytes:03d}.bin"
        tmp = p.with_suffix(".tmp")
        tmp.write_bytes(data[i:i + part_bytes])
        os.replace(tmp, p)
        parts.append({"file": p.name, "sha256": hashlib.sha256(data[i:i + part_bytes]).hexdigest()})
    return parts


def _read_chunks(folder: Path, manifest_name: str) -> tuple[dict, bytes]:
    path = folder / manifest_name
    try:
        manifest = json.loads(path.read_text())
        listed = manifest["parts"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise CheckpointError(f"{path}: not a checkpoint manifest ({e})") from None
    chunks = []
    for part in listed:
        p = folder / part["file"]
        try:
            b = p.read_bytes()
        except OSError:
            raise CheckpointError(f"{p}: missing (listed in {path.name})") from None
        if hashlib.sha256(b).hexdigest() != part["sha256"]:
            raise CheckpointError(f"{p}: checksum differs from {path.name} (a part is damaged or torn)")
        chunks.append(b)
    return manifest, b"".join(chunks)


def save_parts(ckpt: dict, folder, part_bytes: int = PART_BYTES) -> list[Path]:
    """Write ``ckpt``'s model as fp16 parts (floating tensors halved, counters kept) with its manifest."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu()) for k, v in ckpt["model"].items()}
    buf = io.BytesIO()
    torch.save(state, buf)
    for old in folder.glob("part-*.bin"):
        old.unlink()
    manifest = {k: ckpt.get(k) for k in ("config", "iteration", "history", "best_ap50", "run")}
    manifest["weights"] = "float16"
    manifest["parts"] = _write_chunks(buf.getvalue(), folder, "part-", part_bytes)
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return [folder / p["file"] for p in manifest["parts"]]


def load_parts(folder) -> dict:
    """The checkpoint of ``save_parts`` with float32 weights (``model``), as ``torch.load`` of a ``.pt`` gives."""
    folder = Path(folder)
    manifest, data = _read_chunks(folder, MANIFEST)
    state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    manifest["model"] = {k: (v.float() if v.is_floating_point() else v) for k, v in state.items()}
    return manifest


#: The parts of a training state hold these keys of the checkpoint (tensors); the rest goes in the manifest (JSON).
STATE_TENSORS = ("model", "optimizer", "torch_rng")


def _shuffle(data: bytes) -> bytes:
    """Bytes regrouped by their rank within each 4-byte word (float32 exponents together), length first."""
    pad = -len(data) % 4
    a = np.frombuffer(data + b"\0" * pad, np.uint8).reshape(-1, 4)
    return len(data).to_bytes(8, "little") + a.T.tobytes()


def _unshuffle(data: bytes) -> bytes:
    n = int.from_bytes(data[:8], "little")
    a = np.frombuffer(data[8:], np.uint8).reshape(4, -1)
    return a.T.tobytes()[:n]


def save_state(ckpt: dict, folder, part_bytes: int = PART_BYTES) -> int:
    """Write a training checkpoint exactly (float32 weights, optimiser, RNG) as parts; returns the bytes written.
    New parts are named by their content, the manifest replaces the old one atomically, then stale parts go."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({k: ckpt[k] for k in STATE_TENSORS}, buf)
    data = zlib.compress(_shuffle(buf.getvalue()), 6)
    prefix = f"state-{hashlib.sha256(data).hexdigest()[:10]}-"
    manifest = {k: v for k, v in ckpt.items() if k not in STATE_TENSORS}
    manifest["weights"] = "float32, exact (with the optimiser and RNG state)"
    manifest["parts"] = _write_chunks(data, folder, prefix, part_bytes)
    tmp = folder / (STATE_MANIFEST + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, folder / STATE_MANIFEST)
    keep = {p["file"] for p in manifest["parts"]}
    for old in folder.glob("state-*.bin"):
        if old.name not in keep:
            old.unlink()
    return len(data)


def state_manifest(folder) -> dict:
    """A training state's manifest alone (iteration, history, settings), without reading its parts."""
    path = Path(folder) / STATE_MANIFEST
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path}: not a training state's manifest ({e})") from None


def load_state(folder) -> dict:
    """The checkpoint of ``save_state``, as ``torch.load`` of a run's ``last.pt`` gives it."""
    folder = Path(folder)
    manifest, data = _read_chunks(folder, STATE_MANIFEST)
    try:
        tensors = torch.load(io.BytesIO(_unshuffle(zlib.decompress(data))), map_location="cpu", weights_only=True)
    except (zlib.error, RuntimeError, ValueError, EOFError) as e:
        raise CheckpointError(f"{folder / STATE_MANIFEST}: its parts do not hold a training state ({e})") from None
    manifest.update(tensors)
    return manifest
