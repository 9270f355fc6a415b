"""labels.h5 schema and round trip, partial-file safety, the torch Dataset, PNG masks."""

import json
import pickle

import cv2
import h5py
import numpy as np
import pytest
import torch
from PIL import Image

import labelsynth
from labelsynth.classes import ClassMap
from labelsynth.export import (
    ExportError,
    LabelsDataset,
    LabelsReadError,
    LabelsReader,
    LabelsWriter,
    read_labels_h5,
    write_labels_h5,
    write_masks_png,
)

CM = ClassMap.default()
N, H, W = 5, 24, 32


def make_frames(n=N, h=H, w=W, seed=0):
    rng = np.random.default_rng(seed)
    images = rng.integers(0, 256, size=(n, h, w, 3), dtype=np.uint8)
    masks = rng.choice(np.array([0, 1, 2, 3, 4, 5, 255], np.uint8), size=(n, h, w))
    conf = rng.uniform(0, 1, size=(n, h, w)).astype(np.float32)
    names = [f"frame_{i:03d}.png" for i in range(n)]
    annotated = np.array([i % 2 == 0 for i in range(n)])
    return images, masks, conf, names, annotated


@pytest.fixture()
def labels_file(tmp_path):
    images, masks, conf, names, annotated = make_frames()
    path = write_labels_h5(
        tmp_path / "labels.h5", images=images, masks=masks, confidence=conf, annotated=annotated,
        frame_names=names, classes=CM, source="/data/capture_01", recipe={"name": "fast", "iters": 10},
        attrs={"method": "field", "extra": {"a": 1}},
    )
    return path, (images, masks, conf, names, annotated)


def test_schema(labels_file):
    path, (images, masks, conf, names, annotated) = labels_file
    assert path.name == "labels.h5" and path.exists()
    assert not path.with_name("labels.h5.partial").exists()
    with h5py.File(path, "r") as f:
        expected = {
            "images": ((N, H, W, 3), np.uint8, (1, H, W, 3)),
            "masks": ((N, H, W), np.uint8, (1, H, W)),
            "confidence": ((N, H, W), np.float16, (1, H, W)),
        }
        for key, (shape, dtype, chunks) in expected.items():
            d = f[key]
            assert d.shape == shape and d.dtype == dtype and d.chunks == chunks
            assert d.compression == "gzip"
        assert f["annotated"].shape == (N,) and f["annotated"].dtype == bool
        assert f["frame_names"].shape == (N,)
        assert h5py.check_string_dtype(f["frame_names"].dtype).encoding == "utf-8"
        a = f.attrs
        assert list(a["class_names"]) == CM.names
        assert (a["class_ids"] == CM.ids).all()
        assert (a["class_colors"] == CM.colors).all() and a["class_colors"].shape == (6, 3)
        assert list(a["wound_bed_ids"]) == [1, 2, 3, 4, 5]
        assert a["ignore_id"] == 255
        assert a["source"] == "/data/capture_01"
        assert json.loads(a["recipe"]) == {"name": "fast", "iters": 10}
        assert a["labelsynth_version"] == labelsynth.__version__
        assert a["method"] == "field"
        assert json.loads(a["extra"]) == {"a": 1}


def test_round_trip(labels_file):
    path, (images, masks, conf, names, annotated) = labels_file
    d = read_labels_h5(path)
    assert (d["images"] == images).all()
    assert (d["masks"] == masks).all()
    assert np.allclose(d["confidence"].astype(np.float32), conf, atol=1e-3)
    assert (d["annotated"] == annotated).all()
    assert d["frame_names"] == names
    assert d["classes"] == CM
    assert d["attrs"]["class_names"] == CM.names


def test_lzf_callables_iterables_and_default_confidence(tmp_path):
    images, masks, _, names, _ = make_frames()
    path = write_labels_h5(
        tmp_path / "labels.h5", images=lambda i: images[i], masks=iter(list(masks)),
        frame_names=names, classes=CM, compression="lzf",
    )
    with h5py.File(path, "r") as f:
        assert f["masks"].compression == "lzf"
        assert (f["confidence"][()] == 1.0).all()
        assert not f["annotated"][()].any()
        assert (f["masks"][()] == masks).all()


def test_interrupted_writer_leaves_no_labels_h5(tmp_path):
    images, masks, conf, names, _ = make_frames()
    path = tmp_path / "labels.h5"
    with pytest.raises(RuntimeError):
        with LabelsWriter(path, N, CM) as w:
            for i in range(3):
                w.add(names[i], images[i], masks[i], conf[i])
            assert w.partial_path.exists() and not path.exists()
            raise RuntimeError("killed")
    assert not path.exists()
    assert not (tmp_path / "labels.h5.partial").exists()
    # too few frames is an error, not a short file
    with pytest.raises(ExportError, match="2 of 5"):
        with LabelsWriter(path, N, CM) as w:
            w.add(names[0], images[0], masks[0])
            w.add(names[1], images[1], masks[1])
    assert not path.exists()


def test_failed_rewrite_keeps_previous_file(labels_file):
    path, (images, masks, *_rest) = labels_file
    before = path.read_bytes()
    with pytest.raises(ExportError):
        write_labels_h5(path, images=images, masks=masks[:2], frame_names=[f"x{i}" for i in range(N)], classes=CM)
    assert path.read_bytes() == before


def test_bad_frames_are_clear_errors(tmp_path):
    images, masks, _, names, _ = make_frames()
    with LabelsWriter(tmp_path / "a.h5", 2, CM, keep_partial=False) as w:
        w.add("a", images[0], masks[0])
        with pytest.raises(ExportError, match="same size"):
            w.add("b", np.zeros((H + 2, W, 3), np.uint8), np.zeros((H + 2, W), np.uint8))
        with pytest.raises(ExportError, match="not in the class map"):
            w.add("b", images[1], np.full((H, W), 9, np.uint8))
        with pytest.raises(ExportError, match="duplicate"):
            w.add("a", images[1], masks[1])
        with pytest.raises(ExportError, match="uint8"):
            w.add("b", images[1].astype(np.float32), masks[1])
        with pytest.raises(ExportError, match="mask is"):
            w.add("b", images[1], masks[1][:, :-1])
        w.add("b", images[1], masks[1])
    assert (tmp_path / "a.h5").exists()
    with pytest.raises(ExportError, match="set by labelsynth"):
        LabelsWriter(tmp_path / "b.h5", 1, CM, attrs={"class_ids": [1]})


def _check_item(item, images, masks, conf, names, annotated):
    i = item["index"]
    assert item["name"] == names[i]
    assert item["image"].dtype == torch.float32 and item["image"].shape == (3, H, W)
    assert torch.allclose(item["image"], torch.from_numpy(images[i]).permute(2, 0, 1).float() / 255)
    assert item["mask"].dtype == torch.int64 and (item["mask"].numpy() == masks[i]).all()
    assert np.allclose(item["confidence"].numpy(), conf[i], atol=1e-3)
    assert bool(item["annotated"]) == bool(annotated[i])


def test_dataset_and_dataloader_with_workers(labels_file):
    path, frames = labels_file
    images, masks, conf, names, annotated = frames
    ds = LabelsDataset(path)
    assert len(ds) == N and ds.classes == CM and ds.frame_names == names
    _check_item(ds[0], *frames)  # the parent opens a handle before the workers fork
    _check_item(ds[-1], *frames)
    with pytest.raises(IndexError):
        ds[N]
    pickle.loads(pickle.dumps(ds))  # the open handle is not pickled
    loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=2, shuffle=False)
    seen = []
    for batch in loader:
        assert batch["image"].shape[1:] == (3, H, W)
        for j, i in enumerate(batch["index"].tolist()):
            item = {k: v[j] for k, v in batch.items()}
            _check_item(item, *frames)
            seen.append(i)
    assert sorted(seen) == list(range(N))
    ds.close()


@pytest.mark.slow
def test_dataset_spawn_workers(labels_file):
    path, frames = labels_file
    ds = LabelsDataset(path, uint8=True)
    loader = torch.utils.data.DataLoader(ds, batch_size=None, num_workers=2, multiprocessing_context="spawn")
    items = list(loader)
    assert [it["index"] for it in items] == list(range(N))
    assert items[3]["image"].dtype == torch.uint8
    assert (items[3]["image"].permute(1, 2, 0).numpy() == frames[0][3]).all()


def test_dataset_transform(labels_file):
    import albumentations as A

    path, (images, masks, conf, names, annotated) = labels_file
    flip = A.Compose([A.HorizontalFlip(p=1.0)], additional_targets={"confidence": "mask"})
    it = LabelsDataset(path, transform=flip)[1]
    assert (it["mask"].numpy() == masks[1][:, ::-1]).all()
    assert np.allclose(it["confidence"].numpy(), conf[1][:, ::-1], atol=1e-3)
    assert torch.allclose(it["image"], torch.from_numpy(images[1][:, ::-1].copy()).permute(2, 0, 1).float() / 255)
    crop = A.Compose([A.CenterCrop(16, 16)])  # changes size, confidence not declared
    with pytest.raises(ExportError, match="additional_targets"):
        LabelsDataset(path, transform=crop)[0]


def test_reader_checks_up_front_and_streams(labels_file):
    path, (images, masks, conf, names, annotated) = labels_file
    reader = LabelsReader(path)
    assert len(reader) == N and reader.size(0) == (H, W) and reader.frame_sizes is None
    assert reader.frame_names == names and reader.annotated.tolist() == annotated.tolist()
    copy = pickle.loads(pickle.dumps(reader))  # no handle travels
    for r in (reader, copy):
        image, mask, confidence = r.read(2)
        assert np.array_equal(image, images[2]) and np.array_equal(mask, masks[2])
        assert np.allclose(confidence, conf[2], atol=1e-3)
        r.close()
    with h5py.File(path, "a") as f:
        f.create_dataset("frame_sizes", data=np.full((N, 2), H + 1, np.int32))  # larger than the datasets
    with pytest.raises(LabelsReadError, match="frame_sizes"):
        LabelsDataset(path)
    with h5py.File(path, "a") as f:
        del f["frame_sizes"]
        del f.attrs["format"]
    with pytest.raises(LabelsReadError, match=f"{path}: not a labelsynth labels.h5"):
        LabelsDataset(path)


def test_png_mask_round_trip_cv2_and_pil(tmp_path):
    mask = np.zeros((H, W), np.uint8)
    mask[2:10, 3:20] = 1
    mask[12:20, 5:9] = 5
    mask[0, :] = 255
    p = write_masks_png(tmp_path / "masks", "images/frame_007.jpg", mask, CM)
    assert p == tmp_path / "masks" / "frame_007.png"
    via_cv2 = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    assert via_cv2.ndim == 2 and via_cv2.dtype == np.uint8 and (via_cv2 == mask).all()
    via_pil = np.array(Image.open(p))
    assert via_pil.ndim == 2 and via_pil.dtype == np.uint8 and (via_pil == mask).all()
    with pytest.raises(ExportError, match="not in the class map"):
        write_masks_png(tmp_path, "bad", np.full((4, 4), 7, np.uint8), CM)
