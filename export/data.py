"""Training and evaluation data for the apple detector: ADD256 patches and crops of simulated flights.

Boxes are ``x1, y1, x2, y2`` in OpenCV's pixel convention (the top-left pixel's centre is (0, 0)),
as everywhere in the project. ADD256 gives circles ``(cx, cy, r)``: the box is ``cx ± r, cy ± r``.
ADD256 is CC BY-NC 4.0: it is read from where it lies (``--add256`` or ``$POMAR_ADD256``), never copied.

No torch here: samples are ``(image RGB uint8 HxWx3, boxes float32 Nx4)``; ``export.train`` turns them
into tensors. That keeps this module usable by ``export.evaluate`` through onnxruntime alone.
"""

from __future__ import annotations

import csv
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pomar.cli import InputError
from pomar.countable import IGNORE_ABOVE, MIN_VISIBLE

log = logging.getLogger(__name__)

ADD256_ENV = "POMAR_ADD256"
#: Where the shared ADD256 copy lies in this workplace (tried last, after the option and $POMAR_ADD256).
ADD256_FALLBACK = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "add256"
APPLEBBCH76_ENV = "POMAR_APPLEBBCH76"
APPLEBBCH76_FALLBACK = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "applebbch76"

#: The held-out photos, fixed before any training: models and thresholds are chosen on them, never trained on.
#: ADD256: the official training split's photos whose number is divisible by 10 ("held-back", 15 of 150 photos; the
#: official test split is scored once, at the end). AppleBBCH76: photos whose number is divisible by 5 ("held-out",
#: 51 of 247 photos). Tiles of one photo overlap, so a photo's tiles all go one way.
ADD256_HELD_BACK_EVERY = 10
APPLEBBCH76_HELD_OUT_EVERY = 5


class DataError(InputError, ValueError):
    """A dataset that is missing or malformed; the message names the file."""


def find_dataset(name: str, path, env: str, fallback: Path, needs: tuple[str, ...], option: str) -> Path:
    """A dataset's folder: ``path``, else ``$env``, else the workplace's shared copy ``fallback``; it must hold
    ``needs`` (files, or folders ending in /). One asked for that is not one, or none found: DataError naming it."""
    def holds(root: Path) -> bool:
        return all((root / n.rstrip("/")).is_dir() if n.endswith("/") else (root / n).is_file() for n in needs)

    for cand in (path, os.environ.get(env), fallback):
        if cand is None:
            continue
        root = Path(cand)
        if holds(root):
            return root
        if cand is not fallback:
            raise DataError(f"{root}: not an {name} folder (needs {', '.join(needs[:-1])} and {needs[-1]})")
    raise DataError(f"{name} not found: pass {option} DIR or set ${env}")


def find_add256(path: str | os.PathLike | None = None) -> Path:
    """The ADD256 folder: ``path``, else ``$POMAR_ADD256``, else the workplace's shared copy."""
    return find_dataset("ADD256", path, ADD256_ENV, ADD256_FALLBACK, ("training.json", "images/"),
                        "--add256")


@dataclass
class Sample:
    name: str
    image: np.ndarray  # RGB uint8
    boxes: np.ndarray  # float32 (N, 4), x1 y1 x2 y2, OpenCV pixels
    ignore: np.ndarray | None = None  # float32 (M, 4): boxes neither counted as apples nor as false positives


def read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise DataError(f"{path}: cannot read the image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def circles_to_boxes(circles) -> np.ndarray:
    if not circles:
        return np.zeros((0, 4), np.float32)
    c = np.array([[a["cx"], a["cy"], a["r"]] for a in circles], np.float32)
    return np.stack([c[:, 0] - c[:, 2], c[:, 1] - c[:, 2], c[:, 0] + c[:, 2], c[:, 1] + c[:, 2]], 1)


def add256_photo(name: str) -> int:
    """The number of the photo an ADD256 patch was cut from (``gebler-topview-039-04.jpg`` -> 39)."""
    return int(Path(name).stem.rsplit("-", 2)[-2])


def add256_split(root: str | os.PathLike | None, split: str) -> list[tuple[Path, np.ndarray]]:
    """(image path, boxes) for the official ``test`` split, or the official training split: all of it
    (``training-all``), without the held-back photos (``training``), or those alone (``held-back``)."""
    if split in ("training", "held-back"):
        items = add256_split(root, "training-all")
        keep = split == "held-back"
        return [(p, b) for p, b in items if (add256_photo(p.name) % ADD256_HELD_BACK_EVERY == 0) == keep]
    root = find_add256(root)
    path = root / f"{'training' if split == 'training-all' else split}.json"
    try:
        ann = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: {e}") from e
    out = []
    for name, circles in sorted(ann.items()):
        try:
            out.append((root / "images" / name, circles_to_boxes(circles)))
        except (KeyError, TypeError) as e:
            raise DataError(f"{path}: bad annotation for {name}: {e}") from e
    return out


def load_add256(root, split: str) -> list[Sample]:
    return [Sample(p.name, read_rgb(p), b) for p, b in add256_split(root, split)]


def find_applebbch76(path: str | os.PathLike | None = None) -> Path:
    """The AppleBBCH76 folder (``images/``, ``labels/``): ``path``, else ``$POMAR_APPLEBBCH76``, else the shared copy."""
    return find_dataset("AppleBBCH76", path, APPLEBBCH76_ENV, APPLEBBCH76_FALLBACK, ("images/", "labels/"),
                        "--applebbch76")


def applebbch76_photo(name: str) -> int:
    """The number of the photo a tile was cut from (``DSC_1046_17kv10r3k_3.jpg`` -> 1046)."""
    parts = Path(name).stem.split("_")
    if len(parts) != 4 or parts[0] != "DSC" or not parts[1].isdigit():
        raise DataError(f"{name}: not an AppleBBCH76 tile name (DSC_<photo>_<plot>_<k>.jpg)")
    return int(parts[1])


#: Label boxes narrower or shorter than this (px) are dropped: slivers of apples cut by a tile's edge (AppleBBCH76's
#: tiles hold 0.2 % of them), which no detector can be asked to box.
MIN_BOX_PX = 2.0


def yolo_boxes(path: Path, w: int, h: int) -> np.ndarray:
    """A YOLO label file (``class cx cy w h``, normalised) as boxes in OpenCV pixels, slivers left out."""
    rows = []
    try:
        lines = path.read_text().split("\n")
    except OSError as e:
        raise DataError(f"{path}: {e.strerror or e}") from e
    for k, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            _, cx, cy, bw, bh = (float(v) for v in line.split())
        except ValueError:
            raise DataError(f"{path}: line {k} is not 'class cx cy w h': {line.strip()[:60]!r}") from None
        if bw * w >= MIN_BOX_PX and bh * h >= MIN_BOX_PX:
            rows.append([(cx - bw / 2) * w - 0.5, (cy - bh / 2) * h - 0.5, (cx + bw / 2) * w - 0.5,
                         (cy + bh / 2) * h - 0.5])
    return np.array(rows, np.float32).reshape(-1, 4)


def applebbch76_split(root, split: str) -> list[Path]:
    """The tiles of the ``training`` or ``held-out`` photos (``APPLEBBCH76_HELD_OUT_EVERY``)."""
    if split not in ("training", "held-out"):
        raise ValueError(f"AppleBBCH76 split {split!r}: training or held-out")
    root = find_applebbch76(root)
    keep = split == "held-out"
    tiles = sorted(p for p in (root / "images").glob("*.jpg"))
    return [p for p in tiles if (applebbch76_photo(p.name) % APPLEBBCH76_HELD_OUT_EVERY == 0) == keep]


def load_applebbch76(root, split: str) -> list[Sample]:
    out = []
    for p in applebbch76_split(root, split):
        img = read_rgb(p)
        label = p.parent.parent / "labels" / f"{p.stem}.txt"
        if not label.is_file():
            raise DataError(f"{label}: missing (every tile of images/ has a label file)")
        out.append(Sample(p.name, img, yolo_boxes(label, img.shape[1], img.shape[0])))
    return out


def sim_frame_boxes(flight_dir: Path, min_visible: float = MIN_VISIBLE, min_ignore: float = IGNORE_ABOVE):
    """Per frame: (boxes of apples at least ``min_visible`` visible, boxes of the barely visible ones)."""
    path = Path(flight_dir) / "truth" / "detections.csv"
    if not path.is_file():
        raise DataError(f"{path}: missing (a simulated flight has truth/detections.csv)")
    pos: dict[int, list] = {}
    ign: dict[int, list] = {}
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            u, v, r, vis = (float(row[k]) for k in ("u", "v", "r_px", "visible_fraction"))
            box = [u - r, v - r, u + r, v + r]
            if vis >= min_visible:
                pos.setdefault(int(row["frame"]), []).append(box)
            elif vis >= min_ignore:
                ign.setdefault(int(row["frame"]), []).append(box)
    def arr(d, k):
        return np.array(d.get(k, []), np.float32).reshape(-1, 4)
    return {k: (arr(pos, k), arr(ign, k)) for k in set(pos) | set(ign)}


def save_pack(samples: list[Sample], path, quality: int = 95) -> Path:
    """Samples in one ``.npz`` (JPEG frames, boxes, ignore boxes): training data that travels without the video."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {}
    for i, s in enumerate(samples):
        ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(s.image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
        arrays[f"jpg{i}"] = jpg.reshape(-1)
        arrays[f"boxes{i}"] = np.asarray(s.boxes, np.float32).reshape(-1, 4)
        arrays[f"ignore{i}"] = np.asarray(s.ignore if s.ignore is not None else np.zeros((0, 4)), np.float32).reshape(-1, 4)
    arrays["names"] = np.array([s.name for s in samples])
    np.savez(path, **arrays)
    return path


def load_pack(path) -> list[Sample]:
    try:
        z = np.load(path)
        names = [str(n) for n in z["names"]]
        return [Sample(n, cv2.cvtColor(cv2.imdecode(z[f"jpg{i}"], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB), z[f"boxes{i}"],
                       z[f"ignore{i}"]) for i, n in enumerate(names)]
    except (OSError, KeyError, ValueError, cv2.error) as e:
        raise DataError(f"{path}: not a pack of export pack ({e})") from e


def load_sim_frames(flight_dir, min_visible: float = MIN_VISIBLE, every: int = 1, limit: int | None = None,
                    min_ignore: float = IGNORE_ABOVE) -> list[Sample]:
    """Whole frames of a simulated flight (or of a pack of ``save_pack``) with their truth boxes and the ignore boxes of
    the apples from ``min_ignore`` up to ``min_visible`` visible."""
    if str(flight_dir).endswith(".npz"):
        if (min_visible, min_ignore) != (MIN_VISIBLE, IGNORE_ABOVE):
            raise DataError(f"{flight_dir}: a pack keeps the labels it was packed with (apples from {MIN_VISIBLE} "
                            f"visible, ignored from {IGNORE_ABOVE}); give the flight folder to label from "
                            f"{min_visible}, ignored from {min_ignore}")
        return load_pack(flight_dir)[::every][:limit]
    from pomar.video import iter_frames
    from pomar.flight import FlightDir

    flight = FlightDir(flight_dir)
    boxes = sim_frame_boxes(flight.path, min_visible, min_ignore)
    out = []
    for idx, bgr in iter_frames(flight.video):
        if idx % every:
            continue
        b, ig = boxes.get(idx, (np.zeros((0, 4), np.float32),) * 2)
        out.append(Sample(f"{flight.path.name}:{idx}", cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), b, ig))
        if limit and len(out) >= limit:
            break
    return out


def clip_boxes(boxes: np.ndarray, w: int, h: int, min_keep: float = 0.4) -> np.ndarray:
    """Clip to the image; drop boxes that keep less than ``min_keep`` of their area."""
    if not len(boxes):
        return boxes
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    c = boxes.copy()
    c[:, [0, 2]] = c[:, [0, 2]].clip(-0.5, w - 0.5)
    c[:, [1, 3]] = c[:, [1, 3]].clip(-0.5, h - 0.5)
    carea = (c[:, 2] - c[:, 0]).clip(0) * (c[:, 3] - c[:, 1]).clip(0)
    return c[carea >= min_keep * np.maximum(area, 1e-6)]


def crop(sample_img: np.ndarray, boxes: np.ndarray, x0: int, y0: int, size: int):
    h, w = sample_img.shape[:2]
    img = sample_img[y0:y0 + size, x0:x0 + size]
    b = boxes - np.array([x0, y0, x0, y0], np.float32)
    return img, clip_boxes(b, img.shape[1], img.shape[0])


class Augment:
    """Random scale, crop, flips, 90° rotations and colour jitter on (RGB uint8, boxes)."""

    def __init__(self, crop_size: int = 256, scale=(0.45, 1.3), rng: np.random.Generator | None = None):
        self.size = crop_size
        self.scale = scale
        self.rng = rng or np.random.default_rng()

    def __call__(self, img: np.ndarray, boxes: np.ndarray, scale=None, ignore: np.ndarray | None = None):
        """(image, boxes), or (image, boxes, ignore boxes) where ``ignore`` is given: those go through the same
        geometry (and draw nothing from the generator, so that a run without them augments as before)."""
        r = self.rng
        ig = np.zeros((0, 4), np.float32) if ignore is None else np.asarray(ignore, np.float32).reshape(-1, 4)
        lo, hi = scale or self.scale
        s = float(np.exp(r.uniform(np.log(lo), np.log(hi))))
        if abs(s - 1) > 0.02:
            h, w = img.shape[:2]
            nw, nh = max(16, round(w * s)), max(16, round(h * s))
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
            # OpenCV convention: pixel centres scale about (-0.5, -0.5).
            k = np.array([nw / w, nh / h] * 2, np.float32)
            boxes, ig = (boxes + 0.5) * k - 0.5, (ig + 0.5) * k - 0.5
        h, w = img.shape[:2]
        if h > self.size or w > self.size:
            # Prefer crops with apples in them: centre on a random apple half of the time.
            if len(boxes) and r.random() < 0.5:
                b = boxes[r.integers(len(boxes))]
                cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
                x0 = int(np.clip(cx - r.uniform(0.1, 0.9) * self.size, 0, max(0, w - self.size)))
                y0 = int(np.clip(cy - r.uniform(0.1, 0.9) * self.size, 0, max(0, h - self.size)))
            else:
                x0 = int(r.integers(0, max(0, w - self.size) + 1))
                y0 = int(r.integers(0, max(0, h - self.size) + 1))
            img, boxes = crop(img, boxes, x0, y0, self.size)
            ig = clip_boxes(ig - np.array([x0, y0, x0, y0], np.float32), img.shape[1], img.shape[0], min_keep=0.0)
        h, w = img.shape[:2]
        if r.random() < 0.5:  # horizontal flip
            img = img[:, ::-1]
            boxes, ig = (np.stack([w - 1 - b[:, 2], b[:, 1], w - 1 - b[:, 0], b[:, 3]], 1) for b in (boxes, ig))
        if r.random() < 0.5:  # vertical flip
            img = img[::-1]
            boxes, ig = (np.stack([b[:, 0], h - 1 - b[:, 3], b[:, 2], h - 1 - b[:, 1]], 1) for b in (boxes, ig))
        if r.random() < 0.5:  # transpose: with the flips, all eight 90° rotations/reflections
            img = img.transpose(1, 0, 2)
            boxes, ig = boxes[:, [1, 0, 3, 2]], ig[:, [1, 0, 3, 2]]
        img = np.ascontiguousarray(img)
        img = self.colour(img)
        boxes = boxes.astype(np.float32).reshape(-1, 4)
        keep = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)  # the model refuses empty boxes
        if ignore is None:
            return img, boxes[keep]
        ig = ig.astype(np.float32).reshape(-1, 4)
        return img, boxes[keep], ig[(ig[:, 2] > ig[:, 0]) & (ig[:, 3] > ig[:, 1])]

    def colour(self, img: np.ndarray) -> np.ndarray:
        """Other cameras and light: hue, saturation and value, white balance, exposure (gamma), contrast, then the
        sensor and the codec: blur, noise, JPEG."""
        r = self.rng
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV).astype(np.float32)
        hsv[..., 0] = (hsv[..., 0] + r.uniform(-6, 6)) % 180
        hsv[..., 1] *= r.uniform(0.7, 1.3)
        hsv[..., 2] *= r.uniform(0.7, 1.3)
        out = cv2.cvtColor(hsv.clip(0, 255).astype(np.uint8), cv2.COLOR_HSV2RGB).astype(np.float32)
        if r.random() < 0.5:  # white balance: a gain per channel
            out *= r.uniform(0.85, 1.15, 3).astype(np.float32)
        if r.random() < 0.5:  # exposure: a gamma on the whole image
            out = 255.0 * (out.clip(0, 255) / 255.0) ** r.uniform(0.7, 1.4)
        c = r.uniform(0.8, 1.2)
        out = (out - out.mean()) * c + out.mean()
        if r.random() < 0.2:  # focus or motion blur
            out = cv2.GaussianBlur(out, (0, 0), r.uniform(0.4, 1.0))
        if r.random() < 0.3:
            out += r.normal(0, r.uniform(1, 5), out.shape)
        out = out.clip(0, 255).astype(np.uint8)
        if r.random() < 0.3:  # another camera's compression
            ok, jpg = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(r.integers(35, 90))])
            out = cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED)
        return out


def validation_sets(add256, applebbch76, val_flights, use_bbch: bool) -> dict[str, list]:
    """The sets models are chosen on, by name: ADD256's held-back photos, AppleBBCH76's held-out photos, and every 5th
    frame of each held-out simulated flight (every frame of a pack), at its own size. Never ADD256's test split."""
    sets = {"add256_held_back": load_add256(add256, "held-back")}
    if use_bbch:
        sets["applebbch76_held_out"] = load_applebbch76(applebbch76, "held-out")
    for f in val_flights:  # a pack was thinned when packed: all of it
        sets[f"sim:{Path(f).stem}"] = load_sim_frames(f, every=1 if str(f).endswith(".npz") else 5)
    return {k: v for k, v in sets.items() if v}


def run_pack(args) -> int:
    samples = load_sim_frames(args.flight, every=args.every, limit=args.limit)
    path = save_pack(samples, args.out, args.quality)
    print(f"{path}: {len(samples)} frames, {sum(len(s.boxes) for s in samples)} apples, "
          f"{path.stat().st_size / 1e6:.1f} MB")
    return 0
