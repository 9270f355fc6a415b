"""`segment` (the 2D baseline): a real ONNX model (exported from a tiny torch net) run over a tiny capture."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")  # the TorchScript exporter needs the onnx package
ort = pytest.importorskip("onnxruntime")

from typer.testing import CliRunner  # noqa: E402

from labelsynth.cli import app  # noqa: E402
from labelsynth.errors import LabelsynthError  # noqa: E402
from labelsynth.train.segment import (  # noqa: E402
    OnnxSegmenter,
    SegmentError,
    parse_id_map,
    resolve_out_dir,
    segment_capture,
)

W, H = 40, 30
COLOURS = {0: (0, 0, 0), 1: (255, 0, 0), 2: (0, 255, 0), 3: (0, 0, 255)}  # class -> RGB


class ColourNet(torch.nn.Module):
    """Class k (1..3) where RGB channel k-1 is bright, class 0 where all are dark; logits at half size.

    On ImageNet-normalised input a saturated channel is about +2.2 and a dark one about -2,
    so with logit_0 = 0 and logit_k = channel k-1 the arg-max is the dominant colour.
    """

    def __init__(self, extra_classes: int = 0) -> None:
        super().__init__()
        self.pool = torch.nn.AvgPool2d(2)
        self.conv = torch.nn.Conv2d(3, 4 + extra_classes, 1)
        with torch.no_grad():
            self.conv.weight.zero_()
            self.conv.bias.zero_()
            for k in range(3):
                self.conv.weight[k + 1, k, 0, 0] = 1.0
            self.conv.bias[4:] = -100.0  # extra classes never win

    def forward(self, x):
        return self.conv(self.pool(x))


class FlatNet(torch.nn.Module):
    """A classifier-like model: logits (N, C), not a segmentation map."""

    def forward(self, x):
        return x.mean(dim=(2, 3))


def _export(model: torch.nn.Module, path: Path, shape=(1, 3, 32, 32), dynamic: bool = True) -> Path:
    # torch>=2.9 defaults to the dynamo exporter, which needs onnxscript; the TorchScript
    # exporter (dynamo=False) only needs onnx and works offline.
    axes = {"pixel_values": {0: "batch", 2: "height", 3: "width"}} if dynamic else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model.eval(),
            (torch.zeros(*shape),),
            str(path),
            input_names=["pixel_values"],
            output_names=["logits"],
            dynamic_axes=axes,
            dynamo=False,
        )
    return path


def _frame(i: int) -> np.ndarray:
    """Known truth: black background, red / green / blue rectangles that move with i."""
    truth = np.zeros((H, W), dtype=np.uint8)
    truth[2:14, 2 + 2 * i : 18 + 2 * i] = 1
    truth[16:28, 4:20] = 2
    truth[6:26, 24 - 2 * i : 38 - i] = 3
    return truth


def _interior(truth: np.ndarray, margin: int = 2) -> np.ndarray:
    """Pixels at least ``margin`` px from any class boundary: bilinear upsampling may blur the rest."""
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    inner = np.zeros(truth.shape, bool)
    for k in np.unique(truth):
        inner |= cv2.erode((truth == k).astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).astype(bool)
    return inner


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("models")
    return {
        "dynamic": _export(ColourNet(), d / "dynamic.onnx"),
        "static": _export(ColourNet(), d / "static.onnx", shape=(1, 3, 32, 32), dynamic=False),
        "flat": _export(FlatNet(), d / "flat.onnx"),
        "wide": _export(ColourNet(extra_classes=300), d / "wide.onnx"),
    }


@pytest.fixture()
def capture(tmp_path) -> Path:
    root = tmp_path / "capture"
    (root / "images").mkdir(parents=True)
    palette = np.array([COLOURS[k] for k in range(4)], dtype=np.uint8)
    for i in range(3):
        rgb = palette[_frame(i)]
        cv2.imwrite(str(root / "images" / f"frame_{i:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (root / "images" / "notes.txt").write_text("not an image")
    return root


def _read_masks(out: Path) -> dict[str, np.ndarray]:
    return {p.stem: cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted(out.glob("*.png"))}


def test_segment_capture_matches_known_regions(capture, models, tmp_path):
    out = tmp_path / "pred"
    report = segment_capture(capture, models["dynamic"], out, input_size=(W, H), device="cpu", progress=False)
    masks = _read_masks(out)
    assert sorted(masks) == ["frame_000", "frame_001", "frame_002"]
    for i in range(3):
        mask, truth = masks[f"frame_{i:03d}"], _frame(i)
        assert mask.shape == (H, W) and mask.dtype == np.uint8
        inner = _interior(truth)
        assert inner.mean() > 0.3
        np.testing.assert_array_equal(mask[inner], truth[inner])
        assert (mask == truth).mean() > 0.9
    assert report.frames == 3 and report.provider == "CPUExecutionProvider"
    assert report.input_size == (W, H)
    assert set(report.class_pixels) == {0, 1, 2, 3}
    assert abs(sum(report.class_fractions.values()) - 1.0) < 1e-9
    line = report.summary()
    assert "3 frames" in line and "granulation" in line and "\n" not in line


def test_masks_read_back_with_pil_as_ids(capture, models, tmp_path):
    Image = pytest.importorskip("PIL.Image")
    out = tmp_path / "pred"
    segment_capture(capture, models["dynamic"], out, input_size=(W, H), device="cpu", progress=False)
    for stem, mask in _read_masks(out).items():
        with Image.open(out / f"{stem}.png") as im:
            assert im.mode == "L"
            np.testing.assert_array_equal(np.asarray(im), mask)


def test_rgba_frames_are_seen_as_the_field_sees_them(models, tmp_path):
    """Alpha is composited over the capture's background (capture.images.read_image), not
    dropped: a fully transparent red frame is black to the segmenter, as to the field."""
    root = tmp_path / "rgba"
    (root / "images").mkdir(parents=True)
    bgra = np.zeros((H, W, 4), np.uint8)
    bgra[..., 2] = 255  # red under...
    bgra[:, : W // 2, 3] = 0  # ...a transparent left half
    bgra[:, W // 2 :, 3] = 255
    cv2.imwrite(str(root / "images" / "f.png"), bgra)
    out = tmp_path / "pred"
    segment_capture(root, models["dynamic"], out, input_size=(W, H), device="cpu", progress=False)
    mask = _read_masks(out)["f"]
    assert (mask[:, : W // 2 - 2] == 0).all()  # black: background
    assert (mask[:, W // 2 + 2 :] == 1).all()  # red: class 1


def test_masks_land_all_at_once_and_keep_other_files(capture, models, tmp_path):
    """OUT is assembled in OUT.partial: a failed run leaves OUT as it was; a finished one
    replaces the masks and keeps other files there."""
    out = tmp_path / "pred"
    out.mkdir()
    (out / "README.txt").write_text("mine")
    (out / "frame_000.png").write_bytes(b"old")
    with pytest.raises(LabelsynthError, match="wide.onnx"):  # fails at the first batch
        segment_capture(capture, models["wide"], out, input_size=(W, H), device="cpu", progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["README.txt", "frame_000.png"]
    assert not (tmp_path / "pred.partial").exists()
    report = segment_capture(capture, models["dynamic"], out, input_size=(W, H), device="cpu", progress=False)
    assert report.replaced == 1 and (out / "README.txt").read_text() == "mine"
    assert sorted(_read_masks(out)) == ["frame_000", "frame_001", "frame_002"]
    assert not (tmp_path / "pred.partial").exists()


def test_static_input_size_and_batches(capture, models, tmp_path):
    """A fixed 32x32 model: frames are resized to it, logits (16x16) upsampled back to 40x30."""
    seg = OnnxSegmenter(models["static"], device="cpu")
    assert seg.input_size == (32, 32) and seg.input_name == "pixel_values"
    with pytest.raises(SegmentError, match="fixed 32x32"):
        OnnxSegmenter(models["static"], device="cpu", input_size=(64, 64))
    out = tmp_path / "pred"
    segment_capture(capture, models["static"], out, device="cpu", batch_size=2, progress=False)
    for i, (stem, mask) in enumerate(_read_masks(out).items()):
        truth = _frame(i)
        inner = _interior(truth, margin=3)
        assert mask.shape == (H, W)
        assert (mask[inner] == truth[inner]).mean() > 0.98


def test_predict_and_batch_agree(models):
    seg = OnnxSegmenter(models["dynamic"], device="cpu", input_size="40x30")
    palette = np.array([COLOURS[k] for k in range(4)], dtype=np.uint8)
    frames = [palette[_frame(i)] for i in range(3)] + [palette[_frame(0)][:20, :24]]  # mixed sizes
    batched = seg.predict_batch(frames)
    for frame, mask in zip(frames, batched):
        single = seg.predict(frame)
        assert single.shape == frame.shape[:2]
        np.testing.assert_array_equal(single, mask)


def test_id_map(capture, models, tmp_path):
    out = tmp_path / "pred"
    report = segment_capture(
        capture, models["dynamic"], out, input_size=(W, H), id_map="1:4, 3:255", device="cpu", progress=False
    )
    truth = _frame(0)
    mask = _read_masks(out)["frame_000"]
    inner = _interior(truth)
    expected = np.array([0, 4, 2, 255], dtype=np.uint8)[truth]  # 0 and 2 unmapped: keep their index
    np.testing.assert_array_equal(mask[inner], expected[inner])
    assert 1 not in report.class_pixels and 4 in report.class_pixels and 255 in report.class_pixels


def test_option_parsing(models):
    assert parse_id_map("0:0,1:1,2:3") == {0: 0, 1: 1, 2: 3}
    for bad in ("axb", "0x10", "1x2x3"):
        with pytest.raises(SegmentError, match="--input-size"):
            OnnxSegmenter(models["dynamic"], device="cpu", input_size=bad)
    assert OnnxSegmenter(models["dynamic"], device="cpu", input_size="24").input_size == (24, 24)
    for bad in ("0-1", "1:300", "1:-1", "x:1", "1:2,1:3"):
        with pytest.raises(SegmentError):
            parse_id_map(bad)
    cap = Path("cap")
    assert resolve_out_dir(cap, None, True) == cap / "predictions"
    assert resolve_out_dir(cap, Path("o"), False) == Path("o")
    with pytest.raises(SegmentError, match="--out"):
        resolve_out_dir(cap, None, False)
    with pytest.raises(SegmentError, match="not both"):
        resolve_out_dir(cap, Path("o"), True)


def test_errors_name_the_file(capture, models, tmp_path):
    out = tmp_path / "pred"
    with pytest.raises(LabelsynthError, match="missing.onnx: model file not found"):
        segment_capture(capture, tmp_path / "missing.onnx", out, device="cpu", progress=False)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"this is not a protobuf")
    with pytest.raises(LabelsynthError, match="garbage.onnx: not a usable ONNX model"):
        segment_capture(capture, garbage, out, device="cpu", progress=False)
    with pytest.raises(LabelsynthError, match=r"flat.onnx: output 'logits' has shape"):
        segment_capture(capture, models["flat"], out, input_size=(W, H), device="cpu", progress=False)
    with pytest.raises(LabelsynthError, match=r"wide.onnx: the model has 304 classes; indices 255\.\.303"):
        segment_capture(capture, models["wide"], out, input_size=(W, H), device="cpu", progress=False)
    empty = tmp_path / "empty"
    (empty / "images").mkdir(parents=True)
    with pytest.raises(LabelsynthError, match="images: no PNG or JPEG images"):
        segment_capture(empty, models["dynamic"], out, device="cpu", progress=False)
    with pytest.raises(LabelsynthError, match="images folder not found"):
        segment_capture(tmp_path / "nowhere", models["dynamic"], out, device="cpu", progress=False)
    with pytest.raises(LabelsynthError, match="--device"):
        segment_capture(capture, models["dynamic"], out, device="tpu", progress=False)
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        with pytest.raises(LabelsynthError, match="CUDAExecutionProvider"):
            segment_capture(capture, models["dynamic"], out, device="cuda", progress=False)
    # the wide model maps cleanly once its extra classes have ids
    wide_map = ",".join(f"{i}:5" for i in range(4, 304))
    segment_capture(capture, models["wide"], out, input_size=(W, H), id_map=wide_map, device="cpu", progress=False)
    assert len(list(out.glob("*.png"))) == 3


def test_cli_end_to_end(capture, models, tmp_path):
    runner = CliRunner()
    out = tmp_path / "cli_out"
    result = runner.invoke(
        app,
        ["segment", str(capture), "--model", str(models["dynamic"]), "--out", str(out),
         "--input-size", "40x30", "--device", "cpu", "--batch-size", "3"],
    )
    assert result.exit_code == 0, result.output
    assert "segmented 3 frames" in result.output
    masks = _read_masks(out)
    inner = _interior(_frame(1))
    np.testing.assert_array_equal(masks["frame_001"][inner], _frame(1)[inner])

    # --into-capture writes CAPTURE/predictions/, and refuses to replace them without --force
    args = ["segment", str(capture), "--model", str(models["dynamic"]), "--into-capture", "--input-size", "40x30",
            "--id-map", "0:0,1:1,2:2,3:3"]
    assert runner.invoke(app, args).exit_code == 0
    assert sorted(p.name for p in (capture / "predictions").iterdir()) == [
        "frame_000.png", "frame_001.png", "frame_002.png"]
    again = runner.invoke(app, args)
    assert again.exit_code != 0 and "--force" in again.output
    assert runner.invoke(app, args + ["--force"]).exit_code == 0


@pytest.mark.parametrize(
    "extra, message",
    [
        ([], "--out DIR"),
        (["--out", "x", "--into-capture"], "not both"),
        (["--out", "x", "--id-map", "1:999"], "--id-map"),
        (["--out", "x", "--input-size", "big"], "--input-size"),
    ],
)
def test_cli_errors_are_one_line(capture, models, extra, message):
    result = CliRunner().invoke(app, ["segment", str(capture), "--model", str(models["dynamic"]), *extra])
    assert result.exit_code == 2
    assert message in result.output
    assert len([line for line in result.output.splitlines() if line.strip()]) == 1


def test_cli_missing_model(capture, tmp_path):
    result = CliRunner().invoke(app, ["segment", str(capture), "--model", str(tmp_path / "nope.onnx"), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "nope.onnx: model file not found" in result.output
