"""`labelsynth train`: end to end on tiny sources, augmentation alignment, weighting, resume,
and the one-line errors for bad input."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from labelsynth.classes import IGNORE_ID, ClassMap
from labelsynth.cli import app
from labelsynth.export import LabelsWriter
from labelsynth.train import TrainConfig
from labelsynth.train.checkpoint import load_checkpoint, save_checkpoint
from labelsynth.train.data import TrainError, load_sources, make_target, split_by_capture
from labelsynth.train.loss import segmentation_loss

W, H = 64, 48
TINY = ["--steps", "2", "--batch-size", "2", "--crop", "32", "--device", "cpu", "--eval-every", "1"]


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, Path]:
    """Two tiny synthetic captures and a labels.h5 (predictions as labels, a known confidence)."""
    from labelsynth.capture import load_capture
    from labelsynth.evaluation.synth import SynthConfig, synthesize

    root = tmp_path_factory.mktemp("train_sources")
    caps = {}
    for seed in (0, 1):
        syn = synthesize(root / f"syn{seed}", SynthConfig(frames=4, annotated=2, width=W, height=H, seed=seed),
                         progress=False)
        caps[f"cap{seed}"] = syn.capture_dir
    cap = load_capture(caps["cap1"])
    h5 = root / "expanded" / "labels.h5"
    with LabelsWriter(h5, len(cap), cap.classes, source=caps["cap1"]) as w:
        for i, frame in enumerate(cap.frames):
            conf = np.full((H, W), 0.9, dtype=np.float32)
            conf[:, : W // 2] = 0.3
            w.add(frame.name, cap.load_image(i), cap.load_prediction(i), conf, frame.annotation_path is not None)
    return {**caps, "h5": h5, "root": root}


def _invoke(*args: str):
    return CliRunner().invoke(app, ["train", *map(str, args)])


def _one_line_error(result, *needles: str) -> str:
    assert result.exit_code == 2, result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]
    err = [ln for ln in lines if ln.startswith("labelsynth: error:")]
    assert len(err) == 1, result.output
    for needle in needles:
        assert needle in err[0], err[0]
    return err[0]


# --- end to end -----------------------------------------------------------------------------------
def test_train_two_sources_writes_everything_and_segment_runs_it(sources, tmp_path):
    import onnx

    from labelsynth.train.segment import segment_capture

    before = {p: p.stat().st_mtime_ns for p in sources["cap0"].rglob("*")}
    out = tmp_path / "model"
    result = _invoke(sources["cap0"], sources["h5"], "--out", out, *TINY, "--min-confidence", "0.5",
                     "--class-weights", "0:0.5", "--expert-weight", "4", "--val-split", "auto")
    assert result.exit_code == 0, result.output
    assert "trained 2/2 steps" in result.output
    for name in ("model.onnx", "checkpoint.pt", "train.json", "curves.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not list(out.glob("*.partial"))
    assert {p: p.stat().st_mtime_ns for p in sources["cap0"].rglob("*")} == before  # sources untouched

    report = json.loads((out / "train.json").read_text())
    classes = ClassMap.default()
    assert report["classes"] == classes.to_json()
    assert report["arguments"]["min_confidence"] == 0.5 and report["arguments"]["expert_weight"] == 4
    assert report["arguments"]["class_weights"] == "0:0.5"
    assert report["step"] == 2 and [h["step"] for h in report["history"]] == [1, 2]
    assert set(report["history"][-1]["val_dice"]) == set(classes.names)
    assert "last contiguous block" in report["split"]["description"]
    assert report["times"]["total_s"] > 0

    model = onnx.load(str(out / "model.onnx"))
    assert model.graph.input[0].name == "pixel_values"
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta["labelsynth_classes"]) == classes.to_json()
    assert meta["labelsynth_input_size"] == f"{W}x{H}"

    rep = segment_capture(sources["cap0"], out / "model.onnx", tmp_path / "seg", progress=False)  # no id_map
    masks = sorted((tmp_path / "seg").glob("*.png"))
    assert len(masks) == 4 and rep.input_size == (W, H) and not rep.unknown_ids
    import cv2

    assert cv2.imread(str(masks[0]), cv2.IMREAD_UNCHANGED).shape == (H, W)


def test_segment_reads_a_non_identity_id_map_from_the_metadata(tmp_path):
    """Class ids 0 and 7: the model's index 1 must come out as id 7 without --id-map."""
    from labelsynth.train.segment import OnnxSegmenter
    from labelsynth.train.export_onnx import export_onnx

    classes = ClassMap.from_dict({"classes": [{"id": 0, "name": "background"}, {"id": 7, "name": "wound"}]})

    class Fixed(torch.nn.Module):
        def forward(self, pixel_values):
            return torch.stack([pixel_values[:, 0] * 0, pixel_values[:, 0] * 0 + 1], dim=1)

    export_onnx(Fixed(), tmp_path / "m.onnx", classes, (32, 24))
    seg = OnnxSegmenter(tmp_path / "m.onnx", device="cpu")
    assert seg.input_size == (32, 24)
    assert np.unique(seg.predict(np.zeros((10, 12, 3), np.uint8))).tolist() == [7]


def test_resume_continues_the_step_count(sources, tmp_path):
    out = tmp_path / "model"
    assert _invoke(sources["cap0"], sources["cap1"], "--out", out, *TINY).exit_code == 0
    refused = _invoke(sources["cap0"], sources["cap1"], "--out", out, *TINY)
    _one_line_error(refused, str(out), "not empty")
    result = _invoke(sources["cap0"], sources["cap1"], "--out", out, *TINY[2:], "--steps", "4", "--resume")
    assert result.exit_code == 0, result.output
    assert "resumed at step 2" in result.output
    report = json.loads((out / "train.json").read_text())
    assert report["resumed_from"] == 2 and report["step"] == 4
    assert report["split"]["train_frames"] == 4 and "training on all 4 frames given" in report["split"]["description"]
    assert [h["step"] for h in report["history"]] == [1, 2, 3, 4]
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 4
    for option, value in (("--arch", "unet"), ("--encoder", "b1"), ("--input-size", "32x24")):
        refused = _invoke(sources["cap0"], sources["cap1"], "--out", out, *TINY[2:], "--steps", "5", "--resume",
                          option, value)
        _one_line_error(refused, str(out / "checkpoint.pt"), f"{option} {value}")
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 4  # refused runs changed nothing
    same = _invoke(sources["cap0"], sources["cap1"], "--out", out, *TINY[2:], "--steps", "4", "--resume",
                   "--arch", "segformer", "--encoder", "b0")
    assert same.exit_code == 0, same.output  # naming the checkpoint's own model is fine


def test_init_starts_from_another_runs_weights(sources, tmp_path):
    """--init: the new run's model starts from the given run's weights (a near-zero learning rate
    keeps them), with its own step count; a missing, resumed or differently shaped start is one line."""
    first = tmp_path / "first"
    assert _invoke(sources["cap0"], sources["cap1"], "--out", first, *TINY).exit_code == 0
    start = load_checkpoint(first / "checkpoint.pt")["model"]
    frozen = ["--steps", "1", "--lr", "1e-12", "--batch-size", "2", "--crop", "32", "--device", "cpu", "--seed", "7"]
    warm = _invoke(sources["cap0"], sources["cap1"], "--out", tmp_path / "warm", *frozen, "--init", first)
    assert warm.exit_code == 0, warm.output
    assert f"startingfromtheweightsof{first / 'checkpoint.pt'}" in "".join(warm.output.split())  # the console wraps
    cold = _invoke(sources["cap0"], sources["cap1"], "--out", tmp_path / "cold", *frozen)
    assert cold.exit_code == 0, cold.output
    warm_w = load_checkpoint(tmp_path / "warm" / "checkpoint.pt")["model"]
    cold_w = load_checkpoint(tmp_path / "cold" / "checkpoint.pt")["model"]
    weights = [k for k in start if "running_" not in k and "num_batches" not in k]  # batch norm statistics move anyway
    assert all(torch.allclose(warm_w[k], start[k], atol=1e-6) for k in weights)
    assert not all(torch.allclose(cold_w[k], start[k], atol=1e-6) for k in weights)  # seed 7 from scratch: another model
    report = json.loads((tmp_path / "warm" / "train.json").read_text())
    assert report["step"] == 1 and report["arguments"]["init"] == str(first)
    _one_line_error(_invoke(sources["cap0"], "--out", tmp_path / "x", *TINY, "--init", tmp_path / "nope"),
                    f"--init {tmp_path / 'nope'}", "no checkpoint.pt")
    _one_line_error(_invoke(sources["cap0"], "--out", tmp_path / "y", *TINY, "--init", first, "--arch", "unet"),
                    str(first / "checkpoint.pt"), "--init cannot start from it with --arch unet")
    _one_line_error(_invoke(sources["cap0"], sources["cap1"], "--out", first, *TINY[2:], "--steps", "3", "--resume",
                            "--init", first), "--init", "--resume")
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()
    # weights that went NaN are refused as --resume refuses them, before MODEL_DIR is written
    from labelsynth.train.model import build_model

    saved = load_checkpoint(first / "checkpoint.pt")
    (tmp_path / "nan").mkdir()
    model = build_model("segformer", "b0", saved["classes"].num_classes)
    model.load_state_dict(saved["model"])
    next(model.parameters()).data.fill_(float("nan"))
    save_checkpoint(tmp_path / "nan" / "checkpoint.pt", model, torch.optim.AdamW(model.parameters()), 2,
                    TrainConfig(**saved["config"]), saved["classes"], [])
    _one_line_error(_invoke(sources["cap0"], "--out", tmp_path / "z", *TINY, "--init", tmp_path / "nan"),
                    str(tmp_path / "nan" / "checkpoint.pt"), "NaN or infinite")
    assert not (tmp_path / "z").exists()


def test_interrupt_saves_a_checkpoint_that_resumes(sources, tmp_path, monkeypatch):
    from labelsynth.train import loop

    calls = {"n": 0}
    real = loop.segmentation_loss

    def interrupting(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # the third training step (validation does not call this: eval_every is large)
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(loop, "segmentation_loss", interrupting)
    out = tmp_path / "model"
    cfg = loop.TrainConfig(steps=5, batch_size=2, crop=32, device="cpu", eval_every=100)
    with pytest.raises(KeyboardInterrupt):
        loop.train([sources["cap0"], sources["cap1"]], out, cfg, progress=False, log=lambda m: None)
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 2
    assert json.loads((out / "train.json").read_text())["interrupted"] is True
    monkeypatch.setattr(loop, "segmentation_loss", real)
    res = loop.train([sources["cap0"], sources["cap1"]], out, loop.TrainConfig(steps=3, batch_size=2, crop=32,
                     device="cpu"), resume=True, progress=False, log=lambda m: None)
    assert res.resumed_from == 2 and res.step == 3 and (out / "model.onnx").is_file()


# --- augmentation ---------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(6))
def test_augmentation_keeps_image_mask_and_weight_aligned(seed):
    from labelsynth.train.augment import build_augment

    image = np.zeros((H, W, 3), np.uint8)
    mask = np.zeros((H, W), np.uint8)
    image[12:36, 20:44] = 255
    mask[12:36, 20:44] = 1
    weight = mask.astype(np.float32) * 2 + 1
    t = build_augment(40, seed=seed, photometric=False)
    out = t(image=image, mask=mask, weight=weight)
    img, msk, wgt = out["image"], out["mask"], out["weight"]
    assert img.shape == (40, 40, 3) and msk.shape == (40, 40) and wgt.shape == (40, 40)
    assert set(np.unique(msk).tolist()) <= {0, 1, IGNORE_ID}  # nearest: no blended ids
    bright = img[..., 0] > 127
    labelled = msk != IGNORE_ID
    # The square stays on the same pixels (edges may differ by the image's interpolation).
    disagree = (bright != (msk == 1)) & labelled
    m1 = (msk == 1).astype(np.uint8)
    import cv2

    edge = cv2.dilate(m1, np.ones((3, 3), np.uint8)) != cv2.erode(m1, np.ones((3, 3), np.uint8))
    assert not (disagree & ~edge).any()
    np.testing.assert_array_equal(wgt[labelled], (msk[labelled] * 2 + 1).astype(np.float32))


def test_augmentation_pads_small_frames_with_ignore():
    from labelsynth.train.augment import build_augment

    out = build_augment(96, seed=0, geometric=False, photometric=False)(
        image=np.full((H, W, 3), 200, np.uint8), mask=np.zeros((H, W), np.uint8), weight=np.ones((H, W), np.float32))
    assert out["mask"].shape == (96, 96)
    assert (out["mask"] == IGNORE_ID).sum() == 96 * 96 - H * W
    assert (out["image"][out["mask"] == IGNORE_ID] == 0).all()


def test_importing_the_package_does_not_import_albumentations():
    import subprocess
    import sys

    code = "import sys, labelsynth, labelsynth.train, labelsynth.cli; print('albumentations' in sys.modules)"
    env = {k: v for k, v in os.environ.items() if k != "NO_ALBUMENTATIONS_UPDATE"}
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env).stdout.strip() == "False"


# --- confidence and expert weighting ---------------------------------------------------------------
def test_min_confidence_ignores_and_expert_weight_applies():
    lut = ClassMap.default().id_to_index_lut()
    mask = np.array([[0, 1, 2, IGNORE_ID]], np.uint8)
    conf = np.array([[0.9, 0.4, 0.6, 1.0]], np.float16)
    target, weight = make_target(mask, conf, True, lut, min_confidence=0.5, expert_weight=4.0)
    assert target.tolist() == [[0, IGNORE_ID, 2, IGNORE_ID]]
    np.testing.assert_allclose(weight, [[3.6, 0.0, 2.4, 0.0]], rtol=1e-3)
    _, plain = make_target(mask, conf, False, lut, min_confidence=0.5, expert_weight=4.0)
    np.testing.assert_allclose(plain, [[0.9, 0.0, 0.6, 0.0]], rtol=1e-3)
    _, flat = make_target(mask, conf, True, lut, expert_weight=4.0, confidence_weight=False)
    np.testing.assert_allclose(flat, [[4.0, 4.0, 4.0, 0.0]])


def test_loss_ignores_255_and_follows_the_weights():
    torch.manual_seed(0)
    logits = torch.randn(1, 3, 4, 4)
    target = torch.randint(0, 3, (1, 4, 4))
    target[0, 0] = IGNORE_ID
    weight = torch.ones(1, 4, 4)
    base, _ = segmentation_loss(logits, target, weight)
    changed = logits.clone()
    changed[0, :, 0] = torch.randn(3, 4) * 10  # ignored pixels: any logits, same loss
    assert torch.allclose(segmentation_loss(changed, target, weight)[0], base)
    zero_w = weight.clone()
    zero_w[0, 1] = 0  # a weight of 0 is the same as ignore
    ignored = target.clone()
    ignored[0, 1] = IGNORE_ID
    assert torch.allclose(segmentation_loss(logits, target, zero_w)[0], segmentation_loss(logits, ignored, weight)[0])


def test_labels_h5_min_confidence_reaches_the_training_targets(sources):
    from labelsynth.train.data import FrameDataset

    loaded, classes = load_sources([sources["h5"]])
    ds = FrameDataset(split_by_capture(loaded).train, classes, min_confidence=0.5, expert_weight=3.0)
    item = ds[0]
    assert (item["target"][:, : W // 2] == IGNORE_ID).all()
    right = item["weight"][:, W // 2 :][item["target"][:, W // 2 :] != IGNORE_ID]
    expected = 0.9 * (3.0 if loaded[0].annotated[0] else 1.0)
    assert torch.allclose(right, torch.full_like(right, expected), rtol=1e-2)


def test_labels_h5_is_streamed_frame_by_frame_and_survives_pickling(sources):
    """The source keeps no pixels; each item is read from the file (also in a worker's copy)."""
    import pickle

    import h5py

    from labelsynth.train.data import FrameDataset

    loaded, classes = load_sources([sources["h5"]])
    src = loaded[0]
    assert not any(isinstance(v, np.ndarray) and v.ndim >= 2 for v in vars(src).values())
    with h5py.File(sources["h5"], "r") as f:
        expected = f["images"][2], f["masks"][2]
    image, mask, _ = src.read(2)
    assert np.array_equal(image, expected[0]) and np.array_equal(mask, expected[1])
    frames = split_by_capture(loaded).train
    ds = FrameDataset(frames, classes)
    copy = pickle.loads(pickle.dumps(ds))  # what a DataLoader worker gets
    for a, b in zip(ds[1].values(), copy[1].values()):
        assert torch.equal(a, b)


def test_input_size_resizes_frames_masks_by_nearest(sources):
    from labelsynth.train.data import FrameDataset
    from labelsynth.train.loop import TrainConfig, _frame_size

    loaded, classes = load_sources([sources["h5"]])
    split = split_by_capture(loaded)
    ds = FrameDataset(split.train, classes, size=(32, 24))
    item = ds[0]
    assert item["image"].shape == (3, 24, 32) and item["target"].shape == (24, 32)
    _, mask, _ = split.train[0].load()
    lut = classes.id_to_index_lut()
    assert set(item["target"].unique().tolist()) <= set(lut[np.unique(mask)].tolist()) | {IGNORE_ID}
    assert _frame_size(split, TrainConfig(input_size="32x24")) == (32, 24)
    assert _frame_size(split, TrainConfig()) == (W, H)
    with pytest.raises(TrainError, match="--input-size"):
        TrainConfig(input_size="32by24").check()


# --- the split ------------------------------------------------------------------------------------
def test_split_is_by_capture(sources):
    loaded, _ = load_sources([sources["cap0"], sources["cap1"], sources["h5"]])
    split = split_by_capture(loaded)
    assert {fr.source for fr in split.val} == {"expanded"} and len(split.val) == 4
    assert "expanded" not in {fr.source for fr in split.train}
    split = split_by_capture(loaded, [str(sources["cap0"])])
    assert len(split.val) == 2 and split.val_sources == [str(sources["cap0"])]
    with pytest.raises(TrainError, match="not one of the sources"):
        split_by_capture(loaded, ["nope"])


def test_val_split_modes_say_what_they_hold_out(sources):
    from labelsynth.train.loop import TrainConfig

    loaded, _ = load_sources([sources["cap0"], sources["cap1"], sources["h5"]])  # 2 + 2 + 4 frames
    none = split_by_capture(loaded, mode="none")
    assert len(none.train) == 8 and not none.val and "all 8 frames" in none.description
    cap = split_by_capture(loaded, mode="capture")
    assert len(cap.train) == 4 and {fr.source for fr in cap.val} == {"expanded"}
    assert "training on the other 4 of the 8 frames given" in cap.description
    frames = split_by_capture(loaded, mode="frames")
    assert [fr.name for fr in frames.val][-1] == loaded[-1].names[-1] and len(frames.train) == 5
    assert "training on the other 5 of the 8 frames given" in frames.description
    auto = split_by_capture(loaded, mode="auto")  # 3 sources: a capture held out
    assert [fr.name for fr in auto.val] == [fr.name for fr in cap.val]
    named = split_by_capture(loaded, [str(sources["cap0"])], mode="none")  # named captures win over the mode
    assert named.val_sources == [str(sources["cap0"])]
    with pytest.raises(TrainError, match="--val-split"):
        split_by_capture(loaded, mode="half")
    with pytest.raises(TrainError, match="two or more sources"):
        split_by_capture(loaded[:1], mode="capture")
    with pytest.raises(TrainError, match="--val-split"):
        TrainConfig(val_split="x").check()


# --- bad input: one line naming the file -----------------------------------------------------------
def test_mixed_class_tables_name_the_file(sources, tmp_path):
    other = ClassMap.from_dict({"classes": [{"id": 0, "name": "background"}, {"id": 1, "name": "wound"}]})
    h5 = tmp_path / "other" / "labels.h5"
    with LabelsWriter(h5, 1, other) as w:
        w.add("a", np.zeros((H, W, 3), np.uint8), np.zeros((H, W), np.uint8))
    _one_line_error(_invoke(sources["cap0"], h5, "--out", tmp_path / "m", *TINY), str(h5), "class table")


def test_corrupt_checkpoint_names_the_file(sources, tmp_path):
    out = tmp_path / "m"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(b"not a checkpoint at all")
    _one_line_error(_invoke(sources["cap0"], "--out", out, *TINY, "--resume"), str(out / "checkpoint.pt"),
                    "checkpoint")


def test_labels_h5_missing_datasets_or_other_version(tmp_path):
    import h5py

    from labelsynth.export import FORMAT

    bad = tmp_path / "missing.h5"
    with h5py.File(bad, "w") as f:
        f.attrs["format"], f.attrs["format_version"] = FORMAT, 1
        f.create_dataset("images", data=np.zeros((1, 4, 4, 3), np.uint8))
    _one_line_error(_invoke(bad, "--out", tmp_path / "m", *TINY), str(bad), "masks")
    old = tmp_path / "old.h5"
    with h5py.File(old, "w") as f:
        f.attrs["format"], f.attrs["format_version"] = FORMAT, 99
    _one_line_error(_invoke(old, "--out", tmp_path / "m", *TINY), str(old), "version")
    (tmp_path / "junk.h5").write_bytes(b"junk")
    _one_line_error(_invoke(tmp_path / "junk.h5", "--out", tmp_path / "m", *TINY), "junk.h5")


def test_capture_without_annotations(sources, tmp_path):
    import shutil

    cap = tmp_path / "bare"
    shutil.copytree(sources["cap0"], cap)
    shutil.rmtree(cap / "annotations")
    _one_line_error(_invoke(cap, "--out", tmp_path / "m", *TINY), str(cap), "no annotations")


def test_smp_arch_without_a_working_install_is_one_line(sources, tmp_path, monkeypatch):
    try:
        import segmentation_models_pytorch  # noqa: F401

        pytest.skip("segmentation-models-pytorch works here")
    except Exception:
        pass
    _one_line_error(_invoke(sources["cap0"], "--out", tmp_path / "m", *TINY, "--arch", "unet"), "--arch unet")


def test_a_source_given_twice_and_an_out_that_is_a_source(sources, tmp_path):
    _one_line_error(_invoke(sources["cap0"], sources["cap0"], "--out", tmp_path / "m", *TINY), "given twice")
    _one_line_error(_invoke(sources["h5"], "--out", sources["h5"].parent, *TINY), "train never writes into its sources")


def test_class_weights_multiply_the_pixel_weights():
    from labelsynth.train.data import parse_class_weights

    classes = ClassMap.default()
    cw = parse_class_weights("0:0.1,5:2", classes)
    assert cw.tolist() == pytest.approx([0.1, 1, 1, 1, 1, 2])
    mask = np.array([[0, 1, 5, IGNORE_ID]], np.uint8)
    _, weight = make_target(mask, np.ones_like(mask, np.float16), True, classes.id_to_index_lut(), expert_weight=3.0,
                            class_weight=cw)
    np.testing.assert_allclose(weight, [[0.3, 3.0, 6.0, 0.0]], rtol=1e-5)
    with pytest.raises(TrainError, match="class id 9"):
        parse_class_weights("9:1", classes)
    with pytest.raises(TrainError, match="id:weight"):
        parse_class_weights("0=1", classes)


# --- a batch's merged dataset.h5 -------------------------------------------------------------------
def _merged(tmp_path: Path) -> tuple[Path, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """OUT/dataset.h5 over two captures of different sizes; their pixels hold no fill value
    (images 1..255, masks of known classes, confidence > 0)."""
    from labelsynth.batch import merge_labels
    from labelsynth.export import write_labels_h5

    out = tmp_path / "out"
    classes = ClassMap.default()
    frames, parts = {}, []
    for seed, (name, h, w) in enumerate((("small", 32, 40), ("large", H, W))):
        rng = np.random.default_rng(seed)
        images = rng.integers(1, 256, (3, h, w, 3), dtype=np.uint8)
        masks = rng.integers(0, 6, (3, h, w), dtype=np.uint8)
        path = out / "captures" / name / "labels.h5"
        write_labels_h5(path, images=images, masks=masks, confidence=np.full((3, h, w), 0.8, np.float32),
                        frame_names=[f"{name}_{i}.png" for i in range(3)], classes=classes, annotated=[True] * 3)
        parts.append((name, path))
        for i in range(3):
            frames[f"{name}_{i}.png"] = (images[i], masks[i])
    return merge_labels(out, parts), frames


def test_train_on_a_merged_dataset_never_sees_a_padded_pixel(tmp_path, monkeypatch):
    from labelsynth.train import data

    dataset, frames = _merged(tmp_path)
    seen = []
    real_load = data.Frame.load

    def recording_load(self, size=None):
        loaded = real_load(self, size)
        seen.append((self.name, loaded))
        return loaded

    monkeypatch.setattr(data.Frame, "load", recording_load)
    one_step_of_every_frame = ["--steps", "1", "--batch-size", "5", "--crop", "32", "--device", "cpu", "--val-split", "auto"]
    result = _invoke(dataset, "--out", tmp_path / "model", *one_step_of_every_frame)
    assert result.exit_code == 0, result.output
    assert {name for name, _ in seen} == set(frames)  # 5 frames trained on in one step, 1 validated
    for name, (image, mask, confidence) in seen:
        assert np.array_equal(image, frames[name][0]) and np.array_equal(mask, frames[name][1])  # cropped back
        assert (confidence > 0).all()
    loaded, classes = load_sources([dataset])
    assert sorted(set(loaded[0].sizes)) == [(40, 32), (W, H)]
    items = data.FrameDataset(split_by_capture(loaded).train, classes)
    for k, fr in enumerate(items.frames):
        item = items[k]
        assert tuple(item["target"].shape) == fr.size[::-1]
        assert (item["target"] != IGNORE_ID).all() and (item["weight"] > 0).all()


def test_train_on_a_merged_dataset_with_a_capture_file_gone(tmp_path):
    dataset, _ = _merged(tmp_path)
    gone = dataset.parent / "captures" / "small" / "labels.h5"
    gone.unlink()
    model = tmp_path / "model"
    _one_line_error(_invoke(dataset, "--out", model, *TINY), str(dataset), str(gone), "missing")
    assert not model.exists()
