"""A checkpoint kept in the repository: fp16 weights in parts of at most 16 MB, so that training resumes.

    FOLDER/checkpoint.json   config, iteration, training history, the run's settings, each part's sha256
    FOLDER/part-000.bin ...  the bytes of one ``torch.save`` of the fp16 state dict, cut in order

``python -m export train --init FOLDER`` starts a new cycle from it (the optimiser's state is not kept:
it would double the size), and ``python -m export onnx FOLDER`` exports it.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import torch

#: Largest part written (bytes): under the 16 MB a file in the repository or a device run's $OUT may have.
PART_BYTES = 15_000_000
MANIFEST = "checkpoint.json"


def is_parts(path) -> bool:
    return (Path(path) / MANIFEST).is_file()


def save_parts(ckpt: dict, folder, part_bytes: int = PART_BYTES) -> list[Path]:
    """Write ``ckpt``'s model as fp16 parts (floating tensors halved, counters kept) with its manifest."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    state = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu()) for k, v in ckpt["model"].items()}
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getvalue()
    for old in folder.glob("part-*.bin"):
        old.unlink()
    parts = []
    for i in range(0, len(data), part_bytes):
        p = folder / f"part-{i // part_bytes:03d}.bin"
        p.write_bytes(data[i:i + part_bytes])
        parts.append(p)
    manifest = {k: ckpt.get(k) for k in ("config", "iteration", "history", "best_ap50", "run")}
    manifest["weights"] = "float16"
    manifest["parts"] = [{"file": p.name, "sha256": hashlib.sha256(p.read_bytes()).hexdigest()} for p in parts]
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1))
    return parts


def load_parts(folder) -> dict:
    """The checkpoint of ``save_parts`` with float32 weights (``model``), as ``torch.load`` of a ``.pt`` gives."""
    folder = Path(folder)
    manifest = json.loads((folder / MANIFEST).read_text())
    chunks = []
    for part in manifest["parts"]:
        b = (folder / part["file"]).read_bytes()
        if hashlib.sha256(b).hexdigest() != part["sha256"]:
            raise ValueError(f"{folder / part['file']}: checksum differs from {MANIFEST} (a part is damaged or missing)")
        chunks.append(b)
    state = torch.load(io.BytesIO(b"".join(chunks)), map_location="cpu", weights_only=True)
    manifest["model"] = {k: (v.float() if v.is_floating_point() else v) for k, v in state.items()}
    return manifest
