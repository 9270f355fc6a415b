"""`labelsynth export OUT` on a real (tiny) expand: every format read back gives OUT's masks
exactly (ignore where the field is less confident than --min-confidence), by labelsynth's capture
loader, pycocotools and Datumaro; bad options are one line before anything is written."""

from __future__ import annotations

import json
import shutil
import zipfile

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from labelsynth.capture import load_capture
from labelsynth.classes import IGNORE_ID
from labelsynth.cli import app
from labelsynth.export import LabelsReader
from labelsynth.export.formats import EXPORT_FORMATS, ExportFrame

C = 0.3  # --min-confidence here, as in test_formats (whose Datumaro checks are reused)

pytestmark = pytest.mark.xdist_group("tiny_expanded")


def out_frames(out) -> list[ExportFrame]:
    with LabelsReader(out / "labels.h5") as reader:
        return [ExportFrame(name, *_mask_image_conf(reader, i), annotated=bool(reader.annotated[i]))
                for i, name in enumerate(reader.frame_names)]


def _mask_image_conf(reader, i):
    image, mask, conf = reader.read(i)
    return mask, image, conf.astype(np.float32)


def expected(frame: ExportFrame) -> np.ndarray:
    m = frame.mask.copy()
    m[frame.confidence < C] = IGNORE_ID
    return m


def run_export(tiny, tmp_path, fmt: str, *extra: str):
    to = tmp_path / ("review.zip" if fmt == "cvat" else fmt)
    res = CliRunner().invoke(app, ["export", str(tiny.out), "--format", fmt, "--to", str(to),
                                   "--min-confidence", str(C), *extra])
    assert res.exit_code == 0, res.output
    return to, res.output


def bare_capture(tiny, tmp_path):
    """The tiny capture's images and cameras without its masks: an export goes into annotations/."""
    root = tmp_path / "cap"
    shutil.copytree(tiny.capture_dir, root, ignore=shutil.ignore_patterns("annotations", "predictions"))
    (root / "annotations").mkdir()
    return root


@pytest.mark.parametrize("fmt", EXPORT_FORMATS)
def test_export_of_an_expand_reads_back_as_its_masks(tiny_expanded, tmp_path, fmt):
    tiny = tiny_expanded
    frames = out_frames(tiny.out)
    assert any((f.confidence < C).any() for f in frames)  # the threshold makes ignore somewhere
    before = {p: p.read_bytes() for p in tiny.out.rglob("*") if p.is_file()}
    to, output = run_export(tiny, tmp_path, fmt)
    assert f"{len(frames)} frames" in output
    assert {p: p.read_bytes() for p in tiny.out.rglob("*") if p.is_file()} == before  # OUT untouched
    flagged = json.loads((tiny.out / "report.json").read_text())["summary"]["flagged"]
    assert tiny.shifted in flagged
    if fmt in ("cvat", "coco", "voc"):  # labelsynth's own capture loader
        root = bare_capture(tiny, tmp_path)
        if fmt == "cvat":
            shutil.copy(to, root / "annotations" / "review.zip")
        elif fmt == "coco":
            shutil.copy(to / "annotations" / "instances.json", root / "annotations" / "instances.json")
        else:
            for p in (to / "SegmentationClass").iterdir():
                shutil.copy(p, root / "annotations" / p.name)
        capture = load_capture(root)
        for i, frame in enumerate(frames):
            assert capture.frames[i].name == frame.name
            np.testing.assert_array_equal(capture.load_annotation(i), expected(frame))
    if fmt == "coco":  # pycocotools
        from pycocotools.coco import COCO

        coco = COCO(str(to / "annotations" / "instances.json"))
        assert coco.dataset["info"]["flagged_frames"] == flagged
        by_name = {im["file_name"]: im for im in coco.loadImgs(coco.getImgIds())}
        for frame in frames:
            ids = np.full(frame.mask.shape, IGNORE_ID, np.uint8)
            for ann in coco.loadAnns(coco.getAnnIds(imgIds=by_name[f"{frame.name}.png"]["id"])):
                ids[coco.annToMask(ann).astype(bool)] = ann["category_id"]
            np.testing.assert_array_equal(ids, expected(frame))
    if fmt == "cityscapes":
        gt = to / "gtFine" / "train" / tiny.capture_dir.name
        for frame in frames:
            with Image.open(gt / f"{frame.name}_gtFine_labelIds.png") as im:
                np.testing.assert_array_equal(np.asarray(im), expected(frame))
    if fmt == "cvat":
        with zipfile.ZipFile(to) as zf:
            readme = zf.read("README.txt").decode()
    else:
        readme = (to / "README.txt").read_text()
    assert "flagged frames" in readme and tiny.shifted in readme.split("flagged frames", 1)[1]


def test_datumaro_imports_every_export_of_an_expand(tiny_expanded, tmp_path):
    """Datumaro, CVAT's own dataset library, finds exactly OUT's masks in all four exports."""
    from datumaro.components.dataset import Dataset

    from .test_formats_datumaro import _check_masks

    tiny = tiny_expanded
    frames = out_frames(tiny.out)
    for fmt in EXPORT_FORMATS:
        to, _ = run_export(tiny, tmp_path, fmt)
        if fmt == "cvat":
            unpacked = tmp_path / "unpacked"
            with zipfile.ZipFile(to) as zf:
                zf.extractall(unpacked)
            dataset, item_id, uncovered = Dataset.import_from(str(unpacked), "voc_segmentation"), None, (0, IGNORE_ID)
        elif fmt == "voc":
            dataset, item_id, uncovered = Dataset.import_from(str(to), "voc_instance_segmentation"), None, (0, IGNORE_ID)
        elif fmt == "coco":
            dataset = Dataset.import_from(str(to / "annotations" / "instances.json"), "coco_instances")
            item_id, uncovered = None, (IGNORE_ID,)
        else:
            dataset, uncovered = Dataset.import_from(str(to), "cityscapes"), (0, IGNORE_ID)
            item_id = lambda name: f"{tiny.capture_dir.name}/{name}"  # noqa: E731
        # _check_masks compares with test_formats.expected: the mask, ignore where confidence < C
        _check_masks(dataset, frames, **({"item_id": item_id} if item_id else {}), uncovered=uncovered)


def test_frames_choices(tiny_expanded, tmp_path):
    tiny = tiny_expanded
    to, output = run_export(tiny, tmp_path, "coco", "--frames", "flagged")
    flagged = json.loads((tiny.out / "report.json").read_text())["summary"]["flagged"]
    names = [im["file_name"][:-4] for im in json.loads((to / "annotations" / "instances.json").read_text())["images"]]
    assert names == [n for n in tiny.result.frames if n in flagged] and names
    shutil.rmtree(to)
    to, _ = run_export(tiny, tmp_path, "coco", "--frames", "unannotated")
    names = [im["file_name"][:-4] for im in json.loads((to / "annotations" / "instances.json").read_text())["images"]]
    assert names == [n for n in tiny.result.frames if n not in tiny.result.annotated]


def test_bad_options_are_one_line_and_write_nothing(tiny_expanded, tmp_path):
    tiny = tiny_expanded
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "file").write_text("x")
    x = str(tmp_path / "x")
    cases = [
        (tiny.out, ["--format", "yolo", "--to", x], "--format 'yolo': expected one of cvat, voc, coco"),
        (tiny.out, ["--format", "voc", "--to", x, "--frames", "some"], "--frames 'some': expected one of"),
        (tiny.out, ["--format", "voc", "--to", x, "--min-confidence", "1.5"], "--min-confidence 1.5"),
        (tiny.out, ["--format", "cvat", "--to", x], "a cvat export is a .zip file"),
        (tiny.out, ["--format", "voc", "--to", str(tmp_path / "taken")], "exists (use --force to replace it)"),
        (tiny.out, ["--format", "voc", "--to", str(tiny.out / "voc")], "inside the run folder"),
        (tiny.out, ["--format", "voc", "--to", str(tiny.capture_dir / "annotations" / "voc")], "inside the capture"),
        (tiny.out, ["--format", "voc", "--to", str(tiny.out.parent), "--force"], "would replace the run folder"),
        (tmp_path / "nowhere", ["--format", "voc", "--to", x], "not found (expected the output folder of labelsynth"),
    ]
    for out, args, message in cases:
        res = CliRunner().invoke(app, ["export", str(out), *args])
        assert res.exit_code == 2, (args, res.output)
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and message in lines[0], (args, res.output)
    assert (tmp_path / "taken" / "file").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken"]  # nothing else was written
    assert not (tiny.out / "voc").exists() and not (tiny.capture_dir / "annotations" / "voc").exists()
