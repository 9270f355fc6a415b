"""Malformed files inside the inputs: what a capture, a finished OUT, a model, a checkpoint, a
video or a recipe may hold that is not what it claims (truncated, zero-byte, wrong size, NaN and
infinite poses and intrinsics, duplicate frames, files that would run code when unpickled, ...).
Each case breaks one file of a fresh copy of the world and names what the error line must say."""

from __future__ import annotations

import errno
import json
import os
import pickle
from pathlib import Path
from typing import Callable

import cv2
import h5py
import numpy as np
import torch

from .harness import Case, deny_writes_under, disk_full_after
from .world import TINY_FIELD, World

Setup = Callable[[World], None]

EXPAND = ["expand", "{cap}", "--out", "{out}", "--recipe", "fast", "--device", "cpu"]
EXPAND_GEOMETRY = [*EXPAND, "--geometry", "{run}", *(a for v in TINY_FIELD for a in ("--set", v))]
"""expand reusing the world's run's geometry: same capture, geometry recipe (fast and the tiny
field's overrides) and seed, so it is accepted."""
SUGGEST = ["suggest", "{cap}", "--annotate", "2", "--out", "{out}", "--recipe", "fast", "--device", "cpu"]
SELFTRAIN = ["selftrain", "{cap}", "--model", "{model}", "--out", "{out}", "--rounds", "1", "--steps", "1",
             "--batch-size", "1", "--crop", "32", "--recipe", "fast", "--device", "cpu"]
EXPORT = ["export", "{run}", "--format", "coco", "--to", "{out}"]
BENCH = ["bench", "{cap}", "--truth", "{truth}", "--out", "{out}", "--recipe", "fast", "--device", "cpu"]
TRAIN = ["train", "{cap}", "{h5}", "--out", "{out}", "--steps", "1", "--batch-size", "1", "--crop", "32",
         "--device", "cpu"]
RESUME = ["train", "{cap}", "--out", "{ckpt_dir}", "--steps", "3", "--batch-size", "1", "--crop", "32",
          "--device", "cpu", "--resume"]
SEGMENT = ["segment", "{cap}", "--model", "{model}", "--out", "{out}", "--device", "cpu"]
REPORT = ["report", "{run}", "--device", "cpu", "--no-loo"]
AUGMENT = ["augment", "{run}", "--views", "1", "--device", "cpu"]
POSES = ["poses", "{cap}", "--out", "{out}"]
IMPORT_PHOTOS = ["import", "{photos}", "--out", "{out}", "--frames", "3", "--no-poses"]
IMPORT_VIDEO = ["import", "{video}", "--out", "{out}", "--frames", "3", "--no-poses"]
BATCH = ["batch", "{root}/list.txt", "--out", "{out}", "--recipe", "fast", "--device", "cpu"]


# --- small editors ---------------------------------------------------------------------------
def at(rel: str) -> Callable[[World], Path]:
    return lambda w: Path(rel.format(**w.names()))


def truncate(rel: str, keep: float = 0.5) -> Setup:
    def setup(w: World) -> None:
        p = at(rel)(w)
        data = p.read_bytes()
        p.write_bytes(data[: int(len(data) * keep)])
    return setup


def write(rel: str, data: bytes | str) -> Setup:
    def setup(w: World) -> None:
        p = at(rel)(w)
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data.encode() if isinstance(data, str) else data)
    return setup


def remove(rel: str) -> Setup:
    return lambda w: at(rel)(w).unlink()


def link(rel: str, target: str) -> Setup:
    def setup(w: World) -> None:
        p = at(rel)(w)
        if p.exists() or p.is_symlink():
            p.unlink()
        os.symlink(target, p)
    return setup


def png(rel: str, array: np.ndarray) -> Setup:
    def setup(w: World) -> None:
        cv2.imwrite(str(at(rel)(w)), array)
    return setup


def edit_json(rel: str, change: Callable[[dict], object]) -> Setup:
    def setup(w: World) -> None:
        p = at(rel)(w)
        data = json.loads(p.read_text())
        result = change(data)
        p.write_text(json.dumps(data if result is None else result, allow_nan=True))
    return setup


def both(*setups: Setup) -> Setup:
    def setup(w: World) -> None:
        for s in setups:
            s(w)
    return setup


def frame0(key: str, value) -> Callable[[dict], None]:
    def change(d: dict) -> None:
        d["frames"][0][key] = value
    return change


def set_key(key: str, value) -> Callable[[dict], None]:
    def change(d: dict) -> None:
        d[key] = value
    return change


def matrix_value(row: int, col: int, value: float) -> Callable[[dict], None]:
    def change(d: dict) -> None:
        d["frames"][1]["transform_matrix"][row][col] = value
    return change


# --- files that would run code when unpickled ---------------------------------------------------
class Payload:
    """Unpickled without restriction, writes ``target``: what a tampered .pt file does."""

    def __init__(self, target: str) -> None:
        self.target = target

    def __reduce__(self):
        return (Path(self.target).write_text, ("pwned",))


def tampered_torch(rel: str) -> Setup:
    """Add a payload that writes ROOT/pwned.txt to a torch file (the snapshot then shows any run)."""
    def setup(w: World) -> None:
        p = at(rel)(w)
        state = torch.load(p, weights_only=True)
        state["payload"] = Payload(str(w.root / "pwned.txt"))
        torch.save(state, p)
    return setup


def pickled_npz(rel: str) -> Setup:
    """An .npz whose array is an object array: loading it with allow_pickle would run the payload."""
    def setup(w: World) -> None:
        p = at(rel)(w)
        arr = np.empty(1, dtype=object)
        arr[0] = Payload(str(w.root / "pwned.txt"))
        with open(p, "wb") as f:
            np.savez(f, world_mat_0=arr, scale_mat_0=arr)
    return setup


def pickle_file(rel: str) -> Setup:
    def setup(w: World) -> None:
        at(rel)(w).write_bytes(pickle.dumps(Payload(str(w.root / "pwned.txt"))))
    return setup


def checkpoint_edit(change: Callable[[dict, dict], None]) -> Setup:
    """Rewrite the world's checkpoint through its own format (description JSON + tensors)."""
    def setup(w: World) -> None:
        p = w.ckpt_dir / "checkpoint.pt"
        state = torch.load(p, weights_only=True)
        meta = json.loads(state["labelsynth_checkpoint"])
        change(meta, state["tensors"])
        state["labelsynth_checkpoint"] = json.dumps(meta)
        torch.save(state, p)
    return setup


def field_edit(change: Callable[[dict, dict], None]) -> Setup:
    def setup(w: World) -> None:
        p = w.run / "field.pt"
        state = torch.load(p, weights_only=True)
        meta = json.loads(state["labelsynth_field"])
        change(meta, state["tensors"])
        state["labelsynth_field"] = json.dumps(meta)
        torch.save(state, p)
    return setup


def h5_edit(change: Callable[[h5py.File], None]) -> Setup:
    def setup(w: World) -> None:
        with h5py.File(w.h5, "a") as f:
            change(f)
    return setup


def _nan_weight(meta: dict, tensors: dict) -> None:
    key = next(k for k, v in tensors.items() if k.startswith("model.") and v.is_floating_point())
    tensors[key][...] = float("nan")


def _wrong_optimiser_shape(meta: dict, tensors: dict) -> None:
    key = next(k for k in tensors if k.startswith("optimizer.") and k.endswith(".exp_avg"))
    tensors[key] = torch.zeros(3)


def _dup_frame_name(f: h5py.File) -> None:
    f["frame_names"][1] = f["frame_names"][0]


def _drop(name: str) -> Callable[[h5py.File], None]:
    return lambda f: f.__delitem__(name)


def _nan_confidence(f: h5py.File) -> None:
    c = f["confidence"][0]
    c[...] = np.nan
    f["confidence"][0] = c


def _bad_mask_id(f: h5py.File) -> None:
    m = f["masks"][0]
    m[...] = 77
    f["masks"][0] = m


def _attr(name: str, value) -> Callable[[h5py.File], None]:
    def change(f: h5py.File) -> None:
        f.attrs[name] = value
    return change


def _capture_list(lines: str) -> Setup:
    return write("{root}/list.txt", lines)


IMG0 = "{cap}/images/view_00.png"
ANN0 = "{cap}/annotations/view_00.png"
PRED1 = "{cap}/predictions/view_01.png"
TRANSFORMS = "{cap}/transforms.json"
CLASSES = "{cap}/classes.json"


def file_cases() -> list[Case]:
    c: list[Case] = []

    def add(id_: str, argv: list[str], expect: tuple[str, ...], setup: Setup | None = None, **kw) -> None:
        c.append(Case(id_, argv, expect, setup=setup, **kw))

    # --- a capture's images, masks, poses and class table (expand, bench, segment, train, poses) ---
    image_breaks = {
        "truncated": truncate(IMG0),
        "zero-byte": write(IMG0, b""),
        "text": write(IMG0, "not a picture\n"),
        "wrong-size": png(IMG0, np.zeros((30, 50, 3), np.uint8)),
        "a-folder": both(remove(IMG0), lambda w: at(IMG0)(w).mkdir()),
        "symlink-loop": link(IMG0, "view_00.png"),
        "dangling-link": link(IMG0, "/nonexistent/view_00.png"),
    }
    for name, setup in image_breaks.items():
        for cmd, argv in (("expand", EXPAND), ("bench", BENCH), ("segment", SEGMENT), ("train", TRAIN)):
            if cmd == "train" and name in ("wrong-size",):
                continue  # train reads annotated frames only; view_00 is annotated, covered by the others
            if cmd == "segment" and name in ("wrong-size", "a-folder"):
                continue  # segment takes frames of any size, and lists files only (a folder is skipped)
            add(f"{cmd}-image-{name}", argv, ("view_00",), setup)
    mask_breaks = {
        "truncated": truncate(ANN0),
        "zero-byte": write(ANN0, b""),
        "text": write(ANN0, "not a mask\n"),
        "wrong-size": png(ANN0, np.zeros((20, 40), np.uint8)),
        "unknown-id": png(ANN0, np.full((40, 40), 77, np.uint8)),
        "unknown-colour": png(ANN0, np.full((40, 40, 3), (1, 2, 3), np.uint8)),
        "16-bit-id-300": png(ANN0, np.full((40, 40), 300, np.uint16)),
    }
    for name, setup in mask_breaks.items():
        for cmd, argv in (("expand", EXPAND), ("bench", BENCH), ("train", TRAIN)):
            add(f"{cmd}-annotation-{name}", argv, ("annotations/view_00",), setup)
    for name, setup in (("truncated", truncate(PRED1)), ("wrong-size", png(PRED1, np.zeros((40, 20), np.uint8))),
                        ("unknown-id", png(PRED1, np.full((40, 40), 200, np.uint8)))):
        add(f"expand-prediction-{name}", [*EXPAND, "--labels", "predictions"], ("predictions/view_01",), setup)
        add(f"bench-prediction-{name}", BENCH, ("predictions/view_01",), setup)
    truth0 = "{truth}/view_01.png"
    add("bench-truth-wrong-size", BENCH, ("view_01",), png(truth0, np.zeros((10, 10), np.uint8)))
    add("bench-truth-truncated", BENCH, ("view_01",), truncate(truth0))
    add("bench-truth-unknown-id", BENCH, ("view_01",), png(truth0, np.full((40, 40), 99, np.uint8)))

    transforms_breaks = {
        "not-json": write(TRANSFORMS, "{not json"),
        "truncated": truncate(TRANSFORMS, 0.7),
        "zero-byte": write(TRANSFORMS, b""),
        "non-utf8": write(TRANSFORMS, b"\xff\xfe{}"),
        "a-list": write(TRANSFORMS, "[1, 2, 3]"),
        "no-frames": edit_json(TRANSFORMS, set_key("frames", [])),
        "frames-not-a-list": edit_json(TRANSFORMS, set_key("frames", {"a": 1})),
        "nan-pose": edit_json(TRANSFORMS, matrix_value(0, 3, float("nan"))),
        "inf-pose": edit_json(TRANSFORMS, matrix_value(1, 1, float("inf"))),
        "singular-pose": edit_json(TRANSFORMS, frame0("transform_matrix", [[0.0] * 4] * 3 + [[0, 0, 0, 1.0]])),
        "3x3-pose": edit_json(TRANSFORMS, frame0("transform_matrix", [[1.0, 0, 0], [0, 1, 0], [0, 0, 1]])),
        "text-pose": edit_json(TRANSFORMS, frame0("transform_matrix", "identity")),
        "nan-focal": edit_json(TRANSFORMS, set_key("fl_x", float("nan"))),
        "inf-focal": edit_json(TRANSFORMS, set_key("fl_y", float("inf"))),
        "zero-focal": edit_json(TRANSFORMS, set_key("fl_x", 0.0)),
        "negative-focal": edit_json(TRANSFORMS, set_key("fl_x", -44.0)),
        "nan-centre": edit_json(TRANSFORMS, set_key("cx", float("nan"))),
        "text-focal": edit_json(TRANSFORMS, set_key("fl_x", "44")),
        "zero-width": edit_json(TRANSFORMS, set_key("w", 0)),
        "huge-width": edit_json(TRANSFORMS, set_key("w", 10**12)),
        "nan-distortion": edit_json(TRANSFORMS, set_key("k1", float("nan"))),
        "duplicate-frame": edit_json(TRANSFORMS, lambda d: d["frames"].append(dict(d["frames"][0]))),
        "missing-image": edit_json(TRANSFORMS, frame0("file_path", "images/nowhere.png")),
        "no-file-path": edit_json(TRANSFORMS, lambda d: d["frames"][0].pop("file_path")),
        "path-escapes": edit_json(TRANSFORMS, frame0("file_path", "../../../../etc/passwd")),
    }
    for name, setup in transforms_breaks.items():
        expect = {"huge-width": ("1000000000000x40",), "duplicate-frame": ("view_00", "unique"),
                  "missing-image": ("nowhere",), "path-escapes": ("view_00",)}.get(name, ("transforms.json",))
        add(f"expand-transforms-{name}", EXPAND, expect, setup)
    for name in ("not-json", "nan-pose", "duplicate-frame", "zero-focal"):
        expect = ("view_00", "unique") if name == "duplicate-frame" else ("transforms.json",)
        add(f"bench-transforms-{name}", BENCH, expect, transforms_breaks[name])
        add(f"train-transforms-{name}", TRAIN, expect, transforms_breaks[name])

    classes_breaks = {
        "not-json": write(CLASSES, "{classes"),
        "a-list": write(CLASSES, "[]"),
        "duplicate-id": edit_json(CLASSES, lambda d: d["classes"].append(dict(d["classes"][1]))),
        "id-300": edit_json(CLASSES, lambda d: d["classes"][1].update(id=300)),
        "bad-colour": edit_json(CLASSES, lambda d: d["classes"][1].update(color=[999, 0, 0])),
        "no-classes": edit_json(CLASSES, set_key("classes", [])),
        "nan-id": edit_json(CLASSES, lambda d: d["classes"][1].update(id=float("nan"))),
    }
    for name, setup in classes_breaks.items():
        add(f"expand-classes-{name}", EXPAND, ("classes.json",), setup)
        add(f"segment-classes-{name}", SEGMENT, ("classes.json",), setup)
    add("train-classes-duplicate-id", TRAIN, ("classes.json",), classes_breaks["duplicate-id"])

    # NeuS and COLMAP pose sources, and archives in annotations/
    neus = "{cap}/cameras_sphere.npz"
    to_neus = remove(TRANSFORMS)
    add("expand-neus-pickled-npz", EXPAND, ("cameras_sphere.npz",), both(to_neus, write(neus, b""), pickled_npz(neus)))
    add("expand-neus-truncated", EXPAND, ("cameras_sphere.npz",), both(to_neus, write(neus, b"PK\x03\x04trunc")))
    add("expand-neus-text", EXPAND, ("cameras_sphere.npz",), both(to_neus, write(neus, "not numpy")))
    colmap = "{cap}/sparse/0/cameras.bin"
    add("expand-colmap-garbage", EXPAND, ("sparse/0",),
        both(to_neus, write(colmap, b"\x01\x02"), write("{cap}/sparse/0/images.bin", b""),
             write("{cap}/sparse/0/points3D.bin", b"")))
    add("expand-cvat-zip-garbage", EXPAND, ("annotations",),
        both(lambda w: [p.unlink() for p in (w.cap / "annotations").glob("*.png")],
             write("{cap}/annotations/task.zip", b"PK\x05\x06" + b"\x00" * 18)))
    add("expand-coco-json-garbage", EXPAND, ("annotations",),
        both(lambda w: [p.unlink() for p in (w.cap / "annotations").glob("*.png")],
             write("{cap}/annotations/instances.json", '{"images": 5, "annotations": "x"}')))
    add("expand-annotations-loop", EXPAND, ("annotations",), link("{cap}/annotations/view_01.png", "view_01.png"))
    add("expand-images-is-a-file", EXPAND, ("images",),
        both(lambda w: __import__("shutil").rmtree(w.cap / "images"), write("{cap}/images", "x")))

    # --- recipes and --set --------------------------------------------------------------------
    recipe = "{root}/my.yaml"
    recipe_breaks = {
        "python-tag": "geometry: !!python/object/apply:os.system ['touch {root}/pwned.txt']\n",
        "nan-lr": "geometry:\n  lr: .nan\n",
        "inf-iterations": "geometry:\n  iterations: .inf\n",
        "huge-iterations": f"geometry:\n  iterations: {10**30}\n",
        "bool-for-number": "semantic:\n  lr: true\n",
        "section-scalar": "geometry: 5\n",
        "non-utf8": b"geometry:\n  lr: \xff\n",
        "tabs": "geometry:\n\tlr: 1\n",
        "unknown-section": "nonsense:\n  a: 1\n",
        "zero-byte-is-default": None,
    }
    for name, text in recipe_breaks.items():
        if text is None:
            continue
        for cmd, argv in (("expand", EXPAND), ("bench", BENCH), ("batch", ["batch", "{cap}", "--out", "{out}",
                                                                          "--device", "cpu"])):
            add(f"{cmd}-recipe-{name}", [*argv, "--recipe", recipe], ("my.yaml",),
                write(recipe, text if isinstance(text, bytes) else text.replace("{root}", "ROOT")))
    for value in ("geometry.lr=.nan", "geometry.lr=.inf", "geometry.iterations=1e400", "geometry.iterations=" + "9" * 30,
                  "geometry.sdf=5", "semantic.dropout=[1]", "render=1", "geometry.lr=!!python/name:os.system",
                  "=1", "geometry..lr=1"):
        named = "--set" if value.startswith(("=", "geometry..")) else value.split("=")[0]
        add(f"expand-set-{value}"[:60], [*EXPAND, "--set", value], (named,))
        add(f"bench-set-{value}"[:60], [*BENCH, "--set", value], (named,))

    add("expand-set-line-break", [*EXPAND, "--set", "geometry.\nlr=1"], ("unknown key",))
    add("expand-annotated-frames-line-break", [*EXPAND, "--annotated-frames", "view_00\nview_01"],
        ("--annotated-frames",))

    # --- a finished OUT: field.pt, run.json, masks (report, augment) ---------------------------------
    field = "{run}/field.pt"
    run_breaks = {
        "field-tampered": (tampered_torch(field), ("field.pt", "refused")),
        "field-truncated": (truncate(field), ("field.pt",)),
        "field-zero-byte": (write(field, b""), ("field.pt",)),
        "field-text": (write(field, "a field\n"), ("field.pt",)),
        "field-a-pickle": (pickle_file(field), ("field.pt",)),
        "field-a-folder": (both(remove(field), lambda w: (w.run / "field.pt").mkdir()), ("field.pt",)),
        "field-newer": (field_edit(lambda m, t: m.update(version=99)), ("field.pt", "newer")),
        "field-nan-scale": (field_edit(lambda m, t: m["normalization"].update(scale=float("nan"))), ("field.pt",)),
        "field-missing-tensor": (field_edit(lambda m, t: t.pop(next(iter(t)))), ("field.pt",)),
        "field-wrong-shape": (field_edit(lambda m, t: t.update({next(iter(t)): torch.zeros(2)})), ("field.pt",)),
        "field-nan-weights": (field_edit(lambda m, t: [v.fill_(float("nan")) for k, v in t.items()
                                                      if k.startswith("sdf.") and v.is_floating_point()]),
                              ("field.pt",)),
        "field-bad-recipe": (field_edit(lambda m, t: m["recipe"]["geometry"].update(iterations=-1)), ("field.pt",)),
        "field-other-classes": (field_edit(lambda m, t: m["classes"]["classes"][1].update(name="other")),
                                ("field",)),
        "run-not-json": (write("{run}/run.json", "{"), ("run.json",)),
        "run-a-list": (write("{run}/run.json", "[]"), ("run.json",)),
        "run-zero-byte": (write("{run}/run.json", b""), ("run.json",)),
        "run-no-capture": (edit_json("{run}/run.json", lambda d: d.pop("capture")), ("run.json",)),
        "run-capture-moved": (edit_json("{run}/run.json", set_key("capture", "/nowhere/capture")), ("/nowhere/capture",)),
        "run-bad-labels": (edit_json("{run}/run.json", set_key("labels", "everything")), ("run.json",)),
        "run-bad-seed": (edit_json("{run}/run.json", set_key("seed", "zero")), ("run.json",)),
        "run-frames-not-names": (edit_json("{run}/run.json", set_key("annotated_frames", [1, 2])), ("run.json",)),
        "run-unknown-frame": (edit_json("{run}/run.json", set_key("annotated_frames", ["view_99"])), ("view_99",)),
        "masks-missing": (remove("{run}/masks/view_01.png"), ("view_01",)),
        "no-masks-folder": (lambda w: __import__("shutil").rmtree(w.run / "masks"), ("masks",)),
        "no-labels": (remove("{run}/labels.h5"), ("labels.h5",)),
        "partial-only": (lambda w: os.rename(w.run, w.root / "run.partial"), ("run",)),
        "capture-image-truncated": (truncate(IMG0), ("view_00",)),
        "capture-transforms-nan": (transforms_breaks["nan-pose"], ("transforms.json",)),
        "capture-classes-changed": (edit_json(CLASSES, lambda d: d["classes"][1].update(name="ulcer")), ("class",)),
    }
    for name, (setup, expect) in run_breaks.items():
        add(f"report-{name}", REPORT, expect, setup)
        if name != "masks-missing":  # augment reads no mask of OUT
            add(f"augment-{name}", AUGMENT, expect, setup)
    add("report-mask-wrong-size", REPORT, ("view_01",), png("{run}/masks/view_01.png", np.zeros((8, 8), np.uint8)))
    add("report-mask-truncated", REPORT, ("view_01",), truncate("{run}/masks/view_01.png"))
    add("report-mask-unknown-id", REPORT, ("view_01",), png("{run}/masks/view_01.png", np.full((40, 40), 99, np.uint8)))
    add("augment-labels-truncated", AUGMENT, ("labels.h5",), truncate("{run}/labels.h5"))
    add("augment-capture-option-other", [*AUGMENT, "--capture", "{truth}"], ("{truth}",))
    add("augment-exists", AUGMENT, ("augment",), write("{run}/augment/keep.txt", "mine"))

    # --- train: labels.h5 sources and checkpoints ------------------------------------------------------
    h5_breaks = {
        "truncated": truncate("{h5}"),
        "zero-byte": write("{h5}", b""),
        "text": write("{h5}", "HDF5? no\n"),
        "a-pickle": pickle_file("{h5}"),
        "no-masks": h5_edit(_drop("masks")),
        "no-frame-names": h5_edit(_drop("frame_names")),
        "duplicate-frame": h5_edit(_dup_frame_name),
        "nan-confidence": h5_edit(_nan_confidence),
        "unknown-id": h5_edit(_bad_mask_id),
        "bad-classes-json": h5_edit(_attr("classes_json", "{not json")),
        "other-format": h5_edit(_attr("format", "somebody-else")),
        "newer-version": h5_edit(_attr("format_version", 99)),
    }
    for name, setup in h5_breaks.items():
        add(f"train-labels-{name}", TRAIN, ("labels.h5",), setup)
    ckpt = "{ckpt_dir}/checkpoint.pt"
    ckpt_breaks = {
        "tampered": (tampered_torch(ckpt), ("checkpoint.pt", "refused")),
        "truncated": (truncate(ckpt), ("checkpoint.pt",)),
        "zero-byte": (write(ckpt, b""), ("checkpoint.pt",)),
        "text": (write(ckpt, "checkpoint\n"), ("checkpoint.pt",)),
        "a-pickle": (pickle_file(ckpt), ("checkpoint.pt",)),
        "a-state-dict": (lambda w: torch.save({"weight": torch.zeros(2)}, w.ckpt_dir / "checkpoint.pt"),
                         ("checkpoint.pt",)),
        "newer": (checkpoint_edit(lambda m, t: m.update(version=99)), ("checkpoint.pt", "newer")),
        "negative-step": (checkpoint_edit(lambda m, t: m.update(step=-3)), ("checkpoint.pt",)),
        "history-not-list": (checkpoint_edit(lambda m, t: m.update(history="x")), ("checkpoint.pt",)),
        "bad-classes": (checkpoint_edit(lambda m, t: m.update(classes={"classes": 5})), ("checkpoint.pt",)),
        "other-classes": (checkpoint_edit(lambda m, t: m["classes"]["classes"][1].update(name="ulcer")),
                          ("checkpoint.pt", "class table")),
        "nan-weights": (checkpoint_edit(_nan_weight), ("checkpoint.pt", "NaN")),
        "missing-weight": (checkpoint_edit(lambda m, t: t.pop(next(k for k in t if k.startswith("model.")))),
                           ("checkpoint.pt",)),
        "wrong-weight-shape": (checkpoint_edit(lambda m, t: t.update({next(k for k in t if k.startswith("model.")):
                                                                      torch.zeros(1)})), ("checkpoint.pt",)),
        "no-param-groups": (checkpoint_edit(lambda m, t: m["optimizer"].pop("param_groups")), ("checkpoint.pt",)),
        "other-arch": (checkpoint_edit(lambda m, t: m["config"].update(arch="unet")), ("unet",)),
    }
    for name, (setup, expect) in ckpt_breaks.items():
        add(f"train-checkpoint-{name}", RESUME, expect, setup, checkpoint=True)
    add("train-resume-without-checkpoint", [*TRAIN, "--resume"], ("checkpoint.pt",))
    add("train-small-frames", ["train", "{root}/small", "--out", "{out}", "--device", "cpu"], ("small", "32"),
        lambda w: _small_capture(w))
    add("train-small-input-size", [*TRAIN, "--input-size", "24x24"], ("--input-size", "32"))
    add("train-small-crop", [*TRAIN, "--crop", "24"], ("--crop", "32"))
    add("train-source-twice", [*TRAIN[:2], "{cap}", *TRAIN[2:]], ("{cap}", "twice"))
    add("train-out-is-source", ["train", "{run}/labels.h5", "--out", "{run}", "--device", "cpu"], ("{run}",))
    add("train-no-annotations", ["train", "{cap}", "--out", "{out}", "--device", "cpu"], ("annotations",),
        lambda w: __import__("shutil").rmtree(w.cap / "annotations"))
    add("train-val-captures-unknown", [*TRAIN, "--val-captures", "nobody"], ("--val-captures", "nobody"))
    add("train-val-captures-empty-item", [*TRAIN, "--val-captures", "capture,,x"], ("--val-captures",))
    add("train-class-weights-unknown-id", [*TRAIN, "--class-weights", "9:2"], ("--class-weights",))
    add("train-class-weights-nan", [*TRAIN, "--class-weights", "1:nan"], ("--class-weights",))
    add("train-class-weights-negative", [*TRAIN, "--class-weights", "1:-2"], ("--class-weights",))
    add("train-input-size-huge", [*TRAIN, "--input-size", "100000x100000"], ("--input-size",))
    add("train-unet-without-smp", [*TRAIN, "--arch", "unet", "--encoder", "nope"], ("--arch unet",))

    # --- segment: the model ------------------------------------------------------------------------
    model_breaks = {
        "truncated": truncate("{model}"),
        "zero-byte": write("{model}", b""),
        "text": write("{model}", "onnx\n"),
        "a-pickle": pickle_file("{model}"),
        "a-folder": both(remove("{model}"), lambda w: w.model.mkdir()),
        "two-channels": lambda w: _export_model(w.model, channels=2),
        "flat-output": lambda w: _export_model(w.model, flat=True),
    }
    for name, setup in model_breaks.items():
        add(f"segment-model-{name}", SEGMENT, ("model.onnx",), setup)
    add("segment-input-size-bad", [*SEGMENT, "--input-size", "axb"], ("--input-size",))
    add("segment-input-size-huge", [*SEGMENT, "--input-size", "99999x99999"], ("--input-size",))
    add("segment-id-map-bad", [*SEGMENT, "--id-map", "0:x"], ("--id-map",))
    add("segment-id-map-out-of-range", [*SEGMENT, "--id-map", "0:300"], ("--id-map",))
    add("segment-id-map-twice", [*SEGMENT, "--id-map", "0:1,0:2"], ("--id-map",))
    add("segment-out-and-into", [*SEGMENT, "--into-capture"], ("--into-capture",))
    add("segment-nowhere", ["segment", "{cap}", "--model", "{model}", "--device", "cpu"], ("--out",))
    add("segment-into-existing", ["segment", "{cap}", "--model", "{model}", "--into-capture", "--device", "cpu"],
        ("predictions", "--force"))
    add("segment-out-inside-capture", ["segment", "{cap}", "--model", "{model}", "--out", "{cap}/masks2"],
        ("{cap}",))
    add("segment-no-images", SEGMENT, ("images",), lambda w: __import__("shutil").rmtree(w.cap / "images"))

    # --- poses -------------------------------------------------------------------------------------
    add("poses-exists", ["poses", "{cap}"], ("transforms.json", "--force"))
    add("poses-two-images", POSES, ("images",), both(remove("{cap}/images/view_00.png"), remove("{cap}/images/view_01.png")))
    add("poses-out-is-folder", ["poses", "{cap}", "--out", "{root}/t.json"], ("t.json",),
        lambda w: (w.root / "t.json").mkdir())
    add("poses-image-truncated", POSES, ("view_00",), truncate(IMG0))

    # --- import ------------------------------------------------------------------------------------
    add("import-video-truncated", IMPORT_VIDEO, ("clip.mp4",), truncate("{video}", 0.3))
    add("import-video-text", IMPORT_VIDEO, ("clip.mp4",), write("{video}", "ftyp but not really"))
    add("import-video-a-png", ["import", "{photos}/view_00.png", "--out", "{out}"], ("view_00.png",))
    add("import-too-many-frames", [*IMPORT_VIDEO[:-1], "--frames", "500"], ("clip.mp4", "--frames"))
    add("import-photos-truncated", IMPORT_PHOTOS, ("view_01",), truncate("{photos}/view_01.png"))
    add("import-photos-text", IMPORT_PHOTOS, ("view_01",), write("{photos}/view_01.png", "no"))
    add("import-photos-zero-byte", IMPORT_PHOTOS, ("view_01",), write("{photos}/view_01.png", b""))
    add("import-photos-loop", IMPORT_PHOTOS, ("view_01",), link("{photos}/view_01.png", "view_01.png"))
    add("import-out-inside-photos", ["import", "{photos}", "--out", "{photos}/cap", "--no-poses"], ("{photos}",))
    add("import-poses-two-frames", ["import", "{video}", "--out", "{out}", "--frames", "2"], ("--frames",))

    # --- batch: capture lists ----------------------------------------------------------------------
    add("batch-list-missing-capture", BATCH, ("list.txt", "nowhere"), _capture_list("{cap}\n/nowhere\n".replace("{cap}", "capture")))
    add("batch-list-not-a-capture", BATCH, ("list.txt", "truth"), _capture_list("truth\n"))
    add("batch-list-twice", BATCH, ("capture", "twice"), _capture_list("capture\ncapture/\n"))
    add("batch-list-non-utf8", BATCH, ("list.txt",), write("{root}/list.txt", b"\xff\xfe\n"))
    add("batch-list-empty", BATCH, ("list.txt",), write("{root}/list.txt", "# nothing\n"))
    add("batch-root-without-captures", ["batch", "{truth}", "--out", "{out}"], ("{truth}",))
    add("batch-out-inside-capture", ["batch", "{cap}", "--out", "{cap}/batch"], ("{cap}",))
    add("batch-address-bad", ["batch", "{cap}", "--out", "{out}", "--address", "http//x"], ("--address",))
    add("batch-cuda-without-gpus", ["batch", "{cap}", "--out", "{out}", "--device", "cuda"], ("--device cuda",))

    # --- bench options beyond the generic ones -------------------------------------------------------
    add("bench-mesh-garbage", [*BENCH, "--mesh", "{root}/m.ply"], ("m.ply",), write("{root}/m.ply", "ply\nnonsense\n"))
    add("bench-mesh-zero-byte", [*BENCH, "--mesh", "{root}/m.ply"], ("m.ply",), write("{root}/m.ply", b""))
    add("bench-mesh-unknown-suffix", [*BENCH, "--mesh", "{root}/m.xyz"], ("m.xyz",), write("{root}/m.xyz", "1 2 3\n"))
    add("bench-cutoff-zero", [*BENCH, "--cutoff", "0"], ("--cutoff",))
    add("bench-cutoff-over-90", [*BENCH, "--cutoff", "120"], ("--cutoff",))
    add("bench-methods-empty-item", [*BENCH, "--methods", "2d,,field"], ("--methods",))
    add("bench-no-predictions", BENCH, ("predictions",), lambda w: __import__("shutil").rmtree(w.cap / "predictions"))
    add("bench-out-inside-truth", ["bench", "{cap}", "--truth", "{truth}", "--out", "{truth}/b"], ("{truth}",))

    # --- expand options beyond the generic ones --------------------------------------------------------
    add("expand-annotated-frames-unknown", [*EXPAND, "--annotated-frames", "view_00,view_77"], ("--annotated-frames",))
    add("expand-annotated-frames-index", [*EXPAND, "--annotated-frames", "99"], ("--annotated-frames",))
    add("expand-annotated-frames-huge-index", [*EXPAND, "--annotated-frames", "9" * 30], ("--annotated-frames",))
    add("expand-annotated-frames-spread-huge", [*EXPAND, "--annotated-frames", "spread:" + "9" * 30],
        ("--annotated-frames",))
    add("expand-labels-annotations-none", [*EXPAND, "--labels", "annotations"], ("annotations",),
        lambda w: __import__("shutil").rmtree(w.cap / "annotations"))
    add("expand-out-exists", EXPAND, ("{out}", "--force"), write("{out}/mine.txt", "keep me"))
    add("expand-mm-per-unit-huge", [*EXPAND, "--mm-per-unit", "1e400"], ("--mm-per-unit",))

    # --- expand --geometry: the geometry of another run (suggest's or expand's OUT, or its field.pt) ----
    geometry_breaks = {
        "partial-only": (lambda w: os.rename(w.run, w.root / "run.partial"), ("{run}", "not finished")),
        "no-field": (remove("{run}/field.pt"), ("{run}", "field.pt")),
        "field-tampered": (tampered_torch("{run}/field.pt"), ("field.pt", "refused")),
        "field-truncated": (truncate("{run}/field.pt"), ("field.pt",)),
        "field-zero-byte": (write("{run}/field.pt", b""), ("field.pt",)),
        "field-a-pickle": (pickle_file("{run}/field.pt"), ("field.pt",)),
        "field-nan-weights": (field_edit(lambda m, t: [v.fill_(float("nan")) for k, v in t.items()
                                                       if k.startswith("sdf.") and v.is_floating_point()]),
                              ("field.pt",)),
        "fingerprint-not-a-dict": (field_edit(lambda m, t: m.update(fitted_on=[1, 2])), ("field.pt",)),
        "no-fingerprint": (field_edit(lambda m, t: m.pop("fitted_on")), ("field.pt",)),
        "surface-not-a-mesh": (field_edit(lambda m, t: (m.update(surface_resolution=8), t.update({
            "surface.vertices": torch.zeros(3, 3), "surface.normals": torch.zeros(3, 3),
            "surface.faces": torch.tensor([[0, 1, 7]])}))), ("field.pt", "surface")),
        "image-changed": (png(IMG0, np.full((40, 40, 3), 90, np.uint8)), ("view_00",)),
        "pose-changed": (edit_json(TRANSFORMS, matrix_value(0, 3, 0.123)), ("view_01",)),
    }
    for name, (setup, expect) in geometry_breaks.items():
        add(f"expand-geometry-{name}", EXPAND_GEOMETRY, expect, setup)
    add("expand-geometry-other-seed", [*EXPAND_GEOMETRY, "--seed", "1"], ("seed",))
    add("expand-geometry-other-recipe", [*EXPAND, "--geometry", "{run}"], ("field.pt", "recipe"))
    add("expand-geometry-the-partial", [*EXPAND_GEOMETRY, "--geometry", "{root}/run.partial"], ("run.partial",),
        lambda w: os.rename(w.run, w.root / "run.partial"))
    add("expand-geometry-the-capture", [*EXPAND_GEOMETRY, "--geometry", "{cap}"], ("{cap}", "field.pt"))
    add("expand-geometry-other-capture", [*EXPAND_GEOMETRY[:1], "{root}/small", *EXPAND_GEOMETRY[2:]],
        ("field.pt",), lambda w: _small_capture(w))

    # --- suggest beyond the generic cases --------------------------------------------------------------
    add("suggest-annotate-more-than-frames", [*SUGGEST, "--annotate", "5"], ("--annotate",))
    add("suggest-out-inside-capture", [*SUGGEST, "--out", "{cap}/suggest"], ("{cap}",))
    add("suggest-out-exists", SUGGEST, ("{out}", "--force"), write("{out}/mine.txt", "keep me"))
    add("suggest-default-out-exists", SUGGEST[:-6] + ["--annotate", "2", "--recipe", "fast", "--device", "cpu"],
        ("capture-suggest", "--force"), write("{root}/capture-suggest/mine.txt", "keep me"))
    for name in ("truncated", "zero-byte", "a-folder", "symlink-loop"):
        add(f"suggest-image-{name}", SUGGEST, ("view_00",), image_breaks[name])
    for name in ("not-json", "nan-pose", "inf-focal", "duplicate-frame", "missing-image", "no-frames"):
        expect = {"duplicate-frame": ("view_00", "unique"), "missing-image": ("nowhere",)}.get(name, ("transforms.json",))
        add(f"suggest-transforms-{name}", SUGGEST, expect, transforms_breaks[name])
    add("suggest-no-poses", SUGGEST, ("{cap}",), remove(TRANSFORMS))
    for name in ("python-tag", "nan-lr", "section-scalar", "unknown-section"):
        add(f"suggest-recipe-{name}", [*SUGGEST, "--recipe", recipe], ("my.yaml",),
            write(recipe, recipe_breaks[name].replace("{root}", "ROOT")))
    add("suggest-set-nan", [*SUGGEST, "--set", "geometry.lr=.nan"], ("geometry.lr",))
    add("suggest-set-unknown", [*SUGGEST, "--set", "geometry.nope=1"], ("nope",))

    # --- selftrain beyond the generic cases -----------------------------------------------------------
    add("selftrain-out-inside-capture", [*SELFTRAIN, "--out", "{cap}/rounds"], ("{cap}",))
    add("selftrain-out-not-selftrain", SELFTRAIN, ("{out}", "--force"), write("{out}/mine.txt", "keep me"))
    add("selftrain-state-not-json", SELFTRAIN, ("selftrain.json",), write("{out}/selftrain.json", "{"))
    add("selftrain-state-a-list", SELFTRAIN, ("selftrain.json",), write("{out}/selftrain.json", "[]"))
    add("selftrain-state-non-utf8", SELFTRAIN, ("selftrain.json",), write("{out}/selftrain.json", b"\xff\xfe"))
    add("selftrain-other-settings", SELFTRAIN, ("{out}", "other settings"),
        write("{out}/selftrain.json", json.dumps({"settings": {"captures": ["elsewhere"]}, "rounds": []})))
    add("selftrain-holdout-trained", [*SELFTRAIN, "--holdout", "{cap}"], ("{cap}", "--holdout"))
    add("selftrain-holdout-no-annotations", [*SELFTRAIN, "--holdout", "{root}/small"], ("annotations",),
        both(lambda w: _small_capture(w), lambda w: __import__("shutil").rmtree(w.root / "small" / "annotations")))
    add("selftrain-both-without-annotations", [*SELFTRAIN, "--labels", "both"], ("annotations",),
        lambda w: __import__("shutil").rmtree(w.cap / "annotations"))
    add("selftrain-capture-twice", [*SELFTRAIN[:2], "{cap}", *SELFTRAIN[2:]], ("{cap}",))
    add("selftrain-cross-fit-one-capture", [*SELFTRAIN, "--cross-fit"], ("--cross-fit", "2 captures"))
    add("selftrain-cross-fit-warm-start", [*SELFTRAIN[:2], "{root}/small", *SELFTRAIN[2:], "--cross-fit", "--warm-start"],
        ("--cross-fit", "--warm-start"), lambda w: _small_capture(w))
    add("selftrain-also-labels-truncated", [*SELFTRAIN, "--also", "{h5}"], ("labels.h5",), truncate("{h5}"))
    add("selftrain-also-other-classes", [*SELFTRAIN, "--also", "{h5}"], ("--also", "class table"),
        h5_edit(lambda f: f.attrs.__setitem__("classes_json", json.dumps({"classes": [
            {"id": 0, "name": "background", "color": [0, 0, 0]}, {"id": 1, "name": "ulcer", "color": [200, 0, 0]}]}))))
    add("selftrain-model-two-channels", SELFTRAIN, ("model.onnx",), lambda w: _export_model(w.model, channels=2))
    add("selftrain-image-truncated", SELFTRAIN, ("view_00",), truncate(IMG0))
    add("selftrain-transforms-nan", SELFTRAIN, ("transforms.json",), transforms_breaks["nan-pose"])
    add("selftrain-recipe-python-tag", [*SELFTRAIN, "--recipe", recipe], ("my.yaml",),
        write(recipe, recipe_breaks["python-tag"].replace("{root}", "ROOT")))
    add("selftrain-set-nan", [*SELFTRAIN, "--set", "geometry.lr=.nan"], ("geometry.lr",))

    # --- export beyond the generic cases --------------------------------------------------------------
    for name in ("field-a-folder", "run-not-json", "run-a-list", "run-no-capture", "no-labels", "partial-only"):
        add(f"export-{name}", EXPORT, run_breaks[name][1], run_breaks[name][0])
    for name in ("truncated", "zero-byte", "text", "a-pickle", "no-masks", "no-frame-names", "duplicate-frame",
                 "bad-classes-json", "other-format", "newer-version"):
        add(f"export-labels-{name}", EXPORT, ("labels.h5",), h5_breaks[name])
    for name in ("nan-confidence", "unknown-id"):  # met while exporting (frames are read one at a time)
        add(f"export-labels-{name}", EXPORT, ("labels.h5",), h5_breaks[name], keep=("export",))
    add("export-report-not-json", [*EXPORT, "--frames", "flagged"], ("--frames flagged", "report"),
        write("{run}/report.json", "{"))
    add("export-flagged-without-report", [*EXPORT, "--frames", "flagged"], ("report",))
    add("export-cvat-not-zip", ["export", "{run}", "--format", "cvat", "--to", "{root}/x.tar"], ("x.tar", ".zip"))
    add("export-cvat-zip-exists", ["export", "{run}", "--format", "cvat", "--to", "{root}/x.zip"], ("x.zip", "--force"),
        write("{root}/x.zip", b"PK"))
    add("export-cvat-to-folder", ["export", "{run}", "--format", "cvat", "--to", "{root}/x.zip", "--force"],
        ("x.zip", "folder"), lambda w: (w.root / "x.zip").mkdir())
    add("export-into-the-run", [*EXPORT[:-1], "{run}/coco"], ("{run}",))
    add("export-into-the-capture", [*EXPORT[:-1], "{cap}/annotations/coco"], ("{cap}",))
    add("export-replaces-the-run", [*EXPORT[:-1], "{run}", "--force"], ("{run}",))
    add("export-exists", EXPORT, ("{out}", "--force"), write("{out}/mine.txt", "keep me"))
    add("export-min-confidence-over-1", [*EXPORT, "--min-confidence", "1.5"], ("--min-confidence",))
    add("export-disk-full", EXPORT, ("{out}.partial", "No space left"), patch=disk_full_after(200), keep=("export",))
    add("export-cvat-disk-full", ["export", "{run}", "--format", "cvat", "--to", "{root}/x.zip"], ("x.zip", "No space left"),
        patch=disk_full_after(200), keep=("export",))

    # --- full disk and no permission: the failure comes while writing, the partial output goes -------
    add("synth-disk-full", ["synth", "{out}", "--frames", "4", "--annotated", "2", "--width", "32", "--height", "32"],
        ("{out}.partial", "No space left"), patch=disk_full_after(3000), keep=("synth",))
    add("segment-disk-full", SEGMENT, ("{out}.partial", "No space left"), patch=disk_full_after(100), keep=("segment",))
    add("import-disk-full", IMPORT_PHOTOS, ("{out}.partial", "No space left"), patch=disk_full_after(500),
        keep=("import-photos",))
    add("synth-permission-denied", ["synth", "{root}/locked/deep/out", "--frames", "4"], ("{root}/locked",),
        setup=lambda w: (w.root / "locked").mkdir(), patch=deny_writes_under(lambda w: w.root / "locked"))
    add("segment-into-read-only-capture", ["segment", "{cap}", "--model", "{model}", "--into-capture", "--force",
                                          "--device", "cpu"], ("{cap}", "read-only"),
        patch=deny_writes_under(lambda w: w.cap, errno.EROFS))
    add("report-read-only-disk", REPORT, ("{root}", "read-only"), patch=deny_writes_under(lambda w: w.root, errno.EROFS),
        keep=("report",))
    return c


def _small_capture(w: World) -> None:
    from ..scenes import make_patch_capture

    make_patch_capture(w.root / "small_root", frames=3, size=24, annotated=(0, 1))
    os.rename(w.root / "small_root" / "capture", w.root / "small")


def _export_model(path: Path, *, channels: int = 3, flat: bool = False) -> None:
    import warnings

    class Net(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.conv = torch.nn.Conv2d(channels, 2, 1)

        def forward(self, x):
            y = self.conv(x)
            return y.mean(dim=(2, 3)) if flat else y

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(Net().eval(), (torch.zeros(1, channels, 32, 32),), str(path), input_names=["pixel_values"],
                          output_names=["logits"], dynamic_axes={"pixel_values": {0: "n", 2: "h", 3: "w"}},
                          dynamo=False)
