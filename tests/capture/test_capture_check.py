"""capture.check: every input decoded before training, every problem listed at once, masks decoded once."""

from __future__ import annotations

import json
import os
import time

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from labelsynth.capture import CheckError, ExtraMask, check_capture, load_capture, read_image
from labelsynth.capture import masks as masks_module
from labelsynth.capture.check import compare_class_tables
from labelsynth.classes import ClassInfo, ClassMap
from labelsynth.cli import app
from labelsynth.errors import CaptureError

from .test_capture_support import H, W, make_capture, snapshot


def _ids(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 6, size=(H, W), dtype=np.uint8)


def _with_masks(root, n: int = 4, annotated=(0, 2)):
    """A capture of ``n`` frames, annotations for ``annotated``, predictions for every frame."""
    make_capture(root, n=n)
    (root / "annotations").mkdir()
    (root / "predictions").mkdir()
    for i in annotated:
        cv2.imwrite(str(root / "annotations" / f"frame_{i:03d}.png"), _ids(i))
    for i in range(n):
        cv2.imwrite(str(root / "predictions" / f"frame_{i:03d}.png"), _ids(10 + i))
    return root


def _break_three(root):
    """The issue's three broken files: unknown id 77 (100 px), a truncated image, a prediction of the wrong size."""
    ann = root / "annotations" / "frame_000.png"
    m = _ids(0)
    m[:10, :10] = 77
    cv2.imwrite(str(ann), m)
    img = root / "images" / "frame_001.png"
    img.write_bytes(img.read_bytes()[: img.stat().st_size // 2])
    pred = root / "predictions" / "frame_003.png"
    cv2.imwrite(str(pred), np.zeros((H // 2, W // 2), np.uint8))
    return ann, img, pred


def test_clean_capture_passes_and_caches_its_masks(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    before = snapshot(root)
    cap = load_capture(root)
    rep = check_capture(cap)
    assert rep.ok and rep.problems == []
    assert rep.files == 4 + 2 + 4 and rep.cached_masks == 6
    assert "checked 10 files" in rep.summary()
    rep.raise_if_problems()  # nothing to raise
    np.testing.assert_array_equal(cap.load_annotation(2), _ids(2))
    np.testing.assert_array_equal(cap.load_prediction(1), _ids(11))
    assert snapshot(root) == before  # nothing in the capture was written


def test_every_problem_is_listed_one_line_per_file(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    ann, img, pred = _break_three(root)
    rep = check_capture(load_capture(root))
    assert len(rep.problems) == 3
    for problem, path, words in zip(rep.problems, (ann, img, pred), ("100 pixels", "truncated", "16x12")):
        assert problem.startswith(f"{path}: ") and words in problem and "\n" not in problem
    assert "(77)" in rep.problems[0]
    with pytest.raises(CheckError) as err:
        rep.raise_if_problems()
    assert err.value.problems == rep.problems
    assert isinstance(err.value, CaptureError)  # callers that catch CaptureError still do
    assert str(err.value).splitlines()[1:] == rep.problems and "3 problems" in str(err.value).splitlines()[0]


def test_a_single_problem_keeps_its_one_line_message(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    cv2.imwrite(str(root / "annotations" / "frame_002.png"), np.zeros((H // 2, W // 2), np.uint8))
    with pytest.raises(CheckError, match="frame_002.png: mask is 16x12") as err:
        check_capture(load_capture(root)).raise_if_problems()
    assert "\n" not in str(err.value)


def test_only_what_the_run_reads_is_checked(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    cv2.imwrite(str(root / "predictions" / "frame_001.png"), np.full((H, W), 77, np.uint8))
    cap = load_capture(root)
    assert check_capture(cap, labels="annotations").ok  # predictions are not decoded
    assert not check_capture(cap, labels="predictions").ok
    rep = check_capture(cap, labels=None, images=False)
    assert rep.ok and rep.files == 0
    with pytest.raises(ValueError, match="labels"):
        check_capture(cap, labels="everything")


def test_truncated_jpeg_is_caught(tmp_path) -> None:
    """OpenCV decodes a truncated JPEG without complaint; the check must not."""
    root = make_capture(tmp_path / "cap", n=3, ext=".jpg")
    img = root / "images" / "frame_001.jpg"
    img.write_bytes(img.read_bytes()[:-40])
    cap = load_capture(root)
    rep = check_capture(cap)
    assert len(rep.problems) == 1 and rep.problems[0] == f"{img}: cannot read image (file is truncated)"
    with pytest.raises(CaptureError, match="truncated"):
        read_image(img)
    # data appended after the end marker (phone "motion photos") is fine, in JPEG and PNG
    good = root / "images" / "frame_002.jpg"
    good.write_bytes(good.read_bytes() + b"\x00\x11trailer" * 10)
    assert read_image(good).shape == (H, W, 3)
    png = tmp_path / "a.png"
    cv2.imwrite(str(png), np.zeros((H, W, 3), np.uint8))
    png.write_bytes(png.read_bytes() + b"trailer")
    assert read_image(png).shape == (H, W, 3)


def test_extra_masks_and_missing_files(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    truth = tmp_path / "truth"
    truth.mkdir()
    cv2.imwrite(str(truth / "frame_000.png"), _ids(0))
    cap = load_capture(root)
    extra = [ExtraMask(truth / "frame_000.png", (W, H), "truth"), ExtraMask(truth / "frame_001.png", (W, H), "truth")]
    rep = check_capture(cap, extra_masks=extra)
    assert rep.problems == [f"{truth / 'frame_001.png'}: truth mask missing"]
    np.testing.assert_array_equal(cap.read_mask_file(truth / "frame_000.png", (W, H)), _ids(0))


def test_class_tables_must_agree(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    other = ClassMap((ClassInfo(0, "background", (0, 0, 0)), ClassInfo(1, "granulation", (1, 2, 3), True),
                      ClassInfo(2, "scab", (9, 9, 9), True)))
    rep = check_capture(load_capture(root), class_tables={"OUT/field.pt": other, "same": ClassMap.default()})
    assert len(rep.problems) == 1
    p = rep.problems[0]
    assert "default class table" in p and "OUT/field.pt" in p
    assert "'slough' here, 'scab' there" in p and "id 5 (unknown) only here" in p
    recoloured = ClassMap(tuple(ClassInfo(c.id, c.name, (7, 7, 7), c.wound_bed) for c in ClassMap.default().classes))
    assert compare_class_tables(ClassMap.default(), "a", recoloured, "b") is None  # colours only draw


def test_masks_are_decoded_once(tmp_path, monkeypatch) -> None:
    """The semantic stage takes the masks the check decoded instead of reading the files again."""
    from labelsynth.pipeline import labelled_frames
    from labelsynth.recipe import load_recipe

    root = _with_masks(tmp_path / "cap")
    calls: list[str] = []
    real = masks_module.read_mask

    def counting(path, *args, **kwargs):
        calls.append(os.path.basename(path))
        return real(path, *args, **kwargs)

    monkeypatch.setattr(masks_module, "read_mask", counting)
    cap = load_capture(root)
    check_capture(cap).raise_if_problems()
    assert len(calls) == 6
    frames = labelled_frames(cap, "both", load_recipe("fast"))
    assert len(frames) == 4 and len(calls) == 6  # every mask came from the cache
    frames[0].mask[:] = 0  # callers get a copy: the cache is not changed through it
    np.testing.assert_array_equal(cap.load_annotation(0), _ids(0))
    assert len(calls) == 6
    # a file changed after the check is read again, not served stale
    path = root / "annotations" / "frame_002.png"
    cv2.imwrite(str(path), _ids(5))
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    np.testing.assert_array_equal(cap.load_annotation(2), _ids(5))
    assert calls[-1] == "frame_002.png" and len(calls) == 7


def test_cache_respects_its_limit(tmp_path) -> None:
    root = _with_masks(tmp_path / "cap")
    cap = load_capture(root)
    cap.mask_cache_limit = 2 * W * H  # room for two masks
    rep = check_capture(cap)
    assert rep.ok and rep.cached_masks == 2 and len(cap.mask_cache) == 2
    np.testing.assert_array_equal(cap.load_prediction(3), _ids(13))  # the uncached ones still load


def test_expand_cli_fails_fast_naming_all_three_files(tmp_path) -> None:
    """The issue's test: three broken files, one run, all three named, no training, no OUT."""
    root = _with_masks(tmp_path / "cap")
    broken = _break_three(root)
    before = snapshot(root)
    out = tmp_path / "out"
    t0 = time.perf_counter()
    result = CliRunner().invoke(app, ["expand", str(root), "--out", str(out), "--recipe", "fast", "--device", "cpu"])
    elapsed = time.perf_counter() - t0
    assert result.exit_code == 2, result.output
    assert elapsed < 15.0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 4  # one per file, then the summary
    for line, path in zip(lines, broken):
        assert line.startswith(f"labelsynth: error: {path}: ")
    assert "3 problems" in lines[-1] and "nothing was trained" in lines[-1]
    assert "geometry" not in result.output and "loading images" not in result.output
    assert not out.exists() and not out.with_name("out.partial").exists()
    assert snapshot(root) == before


def test_bench_checks_truths_with_the_capture(tmp_path) -> None:
    from labelsynth.evaluation.bench import run_bench

    root = _with_masks(tmp_path / "cap", annotated=())
    (root / "annotations").rmdir()
    truth = tmp_path / "truth"
    truth.mkdir()
    for i in range(3):  # frame_003's truth is missing
        cv2.imwrite(str(truth / f"frame_{i:03d}.png"), _ids(i))
    cv2.imwrite(str(root / "predictions" / "frame_001.png"), np.full((H, W), 77, np.uint8))
    with pytest.raises(CheckError) as err:
        run_bench(root, truth, tmp_path / "o", methods="2d", recipe="fast", device="cpu", progress=False)
    assert [p.split(": ")[0] for p in err.value.problems] == [
        str(root / "predictions" / "frame_001.png"), str(truth / "frame_003.png")]
    assert not (tmp_path / "o").exists()


def test_report_rebuild_checks_inputs_and_the_field_classes(tmp_path, monkeypatch) -> None:
    """`labelsynth report` on an OUT whose capture changed: every problem before any refit."""
    from labelsynth import rundir
    from labelsynth.pipeline import rebuild_report

    root = _with_masks(tmp_path / "cap")
    (root / "classes.json").write_text(json.dumps({"classes": [
        {"id": 0, "name": "background"}, {"id": 1, "name": "wound", "wound_bed": True}]}))
    for folder in ("annotations", "predictions"):
        for p in (root / folder).glob("*.png"):
            cv2.imwrite(str(p), (_ids(0) % 2).astype(np.uint8))
    cv2.imwrite(str(root / "predictions" / "frame_002.png"), np.full((H, W), 3, np.uint8))  # not in the new table
    out = tmp_path / "out"
    out.mkdir()
    (out / "run.json").write_text(json.dumps({"capture": str(root), "labels": "annotations"}))
    (out / "field.pt").write_bytes(b"stub")
    (out / "labels.h5").write_bytes(b"stub")
    (out / "masks").mkdir()

    class Stub:
        classes = ClassMap.default()

    monkeypatch.setattr(rundir, "load_field", lambda path, device: Stub())
    with pytest.raises(CheckError) as err:
        rebuild_report(out, device="cpu", progress=False)
    probs = err.value.problems
    assert len(probs) == 2
    assert probs[0].startswith(f"{root / 'classes.json'}: class table differs from the one in {out / 'field.pt'}")
    assert probs[1].startswith(f"{root / 'predictions' / 'frame_002.png'}: ")
