"""``labelsynth segment``: run an ONNX semantic segmenter over every frame of a capture.

It runs what ``labelsynth train`` exports (and is the "2D" baseline the paper compares the
3D field with): per-frame masks (e.g. ``predictions/``) with onnxruntime, so any exported
model (SegFormer from HF transformers, a torchvision DeepLab, ...) works without torch.

Conventions (SegFormer-style by default; the input side is the segmenter contract, ``contract``,
which training uses too, so a model sees at inference the pixels it was trained on):
- input: the input named ``pixel_values`` (else the model's first input), NCHW float32 RGB,
  ImageNet mean/std normalised, resized (``contract.resize_image``: area when shrinking) to the
  model's static input size, else to ``input_size``, else to 512x512;
- output: the model's first output, logits (N, C, h, w) at any resolution; the logits are
  upsampled bilinearly to the frame size and then arg-maxed (upsampling labels instead would
  give blocky edges);
- class ids: the arg-max index is the class id unless ``id_map`` says otherwise; indices that
  the map does not name map to themselves. A target of 255 marks a class as "ignore".
- a model written by ``labelsynth train`` carries its index -> id map and its training input
  size in the ONNX metadata (``labelsynth_id_map``, ``labelsynth_input_size``): they are used
  when ``id_map`` / ``input_size`` are not given.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..capture.check import check_image_files
from ..capture.images import list_images, read_image
from ..capture.load import capture_white_background
from ..capture.masks import write_mask
from ..classes import IGNORE_ID, ClassMap, parse_id_pairs
from ..errors import LabelsynthError
from ..outdir import building, check_apart
from ..progress import make_progress
from .contract import (IMAGENET_MEAN, IMAGENET_STD, INPUT_NAME, META_INPUT_SIZE, metadata_id_map, model_input,
                       parse_input_size)

DEFAULT_INPUT_SIZE = (512, 512)  # (width, height) of a foreign model with no size of its own
DEVICES = ("auto", "cpu", "cuda")
MAX_BATCH = 4096
_RESIZE_CHANNELS = 4  # cv2.resize is only safe for a few channels at a time


class SegmentError(LabelsynthError, ValueError):
    """A model, option or image folder that ``segment`` cannot use (one line, names the file)."""


# --- option parsing (shared by the CLI and the library) ----------------------------------
def parse_id_map(text: str | Mapping[int, int] | None) -> dict[int, int] | None:
    """``"0:0,1:1,2:3"`` -> ``{0: 0, 1: 1, 2: 3}`` (model output index -> class id).

    Targets must be class ids 0..254, or 255 to mark a model class as ignore.
    """
    if text is None:
        return None
    if isinstance(text, str) and not text.strip():
        raise SegmentError("--id-map must not be empty (leave the option out to keep the model's own map)")
    pairs = parse_id_pairs(text, int, "--id-map", "source:target", "0:0,1:1,2:3", SegmentError)
    result: dict[int, int] = {}
    for src, dst in pairs:
        if src < 0:
            raise SegmentError(f"--id-map: model class index {src} is negative")
        if not 0 <= dst <= IGNORE_ID:
            raise SegmentError(f"--id-map: target id {dst} for index {src} is outside 0..254 (or 255 = ignore)")
        if src in result and result[src] != dst:
            raise SegmentError(f"--id-map: index {src} is mapped twice ({result[src]} and {dst})")
        result[src] = dst
    return result


def resolve_out_dir(capture: Path, out: Path | None, into_capture: bool) -> Path:
    """Where masks go: ``--out DIR`` or, only when asked explicitly, CAPTURE/predictions/."""
    if out is not None and into_capture:
        raise SegmentError("give either --out DIR or --into-capture, not both")
    if out is None and not into_capture:
        raise SegmentError("say where the masks go: --out DIR, or --into-capture to write CAPTURE/predictions/")
    if into_capture:
        return Path(capture) / "predictions"
    out = Path(out)  # type: ignore[arg-type]
    try:
        check_apart(out, {"the capture": capture})
    except LabelsynthError as exc:
        raise SegmentError(f"{exc} (segment writes into a capture only with --into-capture: CAPTURE/predictions/)") \
            from None
    return out


# --- the segmenter ------------------------------------------------------------------------
def _select_providers(device: str) -> list[str]:
    import onnxruntime as ort

    if device not in DEVICES:
        raise SegmentError(f"--device {device!r}: expected one of {', '.join(DEVICES)}")
    available = ort.get_available_providers()
    if device == "cuda" and "CUDAExecutionProvider" not in available:
        raise SegmentError("--device cuda: onnxruntime has no CUDAExecutionProvider (install onnxruntime-gpu)")
    if device in ("cuda", "auto") and "CUDAExecutionProvider" in available:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


def _static_dim(value: object) -> int | None:
    return value if isinstance(value, int) and value > 0 else None


class OnnxSegmenter:
    """One onnxruntime session plus the SegFormer-style pre- and post-processing.

    ``predict`` takes one RGB uint8 frame and returns its (H, W) uint8 class-id mask at the
    frame's own size; ``predict_batch`` does the same for several frames in one model call.
    """

    def __init__(
        self,
        model_path: str | Path,
        device: str = "auto",
        input_size: tuple[int, int] | str | None = None,
        *,
        id_map: Mapping[int, int] | str | None = None,
        mean: Sequence[float] = IMAGENET_MEAN,
        std: Sequence[float] = IMAGENET_STD,
    ) -> None:
        import onnxruntime as ort

        self.model_path = Path(model_path)
        if not self.model_path.is_file():
            raise SegmentError(f"{self.model_path}: model file not found")
        self.session = self._open_session(ort, device)
        self.providers = self.session.get_providers()
        if device == "cuda" and "CUDAExecutionProvider" not in self.providers:
            raise SegmentError(f"{self.model_path}: --device cuda, but onnxruntime could not start CUDA for this model")
        self.provider = self.providers[0]
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map or {})
        if input_size is None and self.metadata.get(META_INPUT_SIZE):
            input_size = self.metadata[META_INPUT_SIZE]  # the size `labelsynth train` trained at
        self._read_input(input_size)
        self._read_output()
        if id_map is None:
            id_map = self._metadata_id_map()
        self.id_map = parse_id_map(id_map) or {}
        self.mean, self.std = tuple(mean), tuple(std)
        self._lut: np.ndarray | None = None
        self.num_model_classes: int | None = None

    def _metadata_id_map(self) -> dict[int, int] | None:
        """The index -> class id map that ``labelsynth train`` stores in the ONNX metadata, if any."""
        try:
            return metadata_id_map(self.metadata)
        except ValueError as exc:
            raise SegmentError(f"{self.model_path}: {exc}") from None

    def _open_session(self, ort, device: str):
        """An onnxruntime session on the chosen providers; a file it cannot load is a one-line error."""
        providers = _select_providers(device)
        options = ort.SessionOptions()
        options.log_severity_level = 3  # keep onnxruntime's warnings off the user's terminal
        try:
            return ort.InferenceSession(str(self.model_path), sess_options=options, providers=providers)
        except Exception as exc:  # onnxruntime raises its own classes, not RuntimeError
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise SegmentError(f"{self.model_path}: not a usable ONNX model ({reason})") from exc

    def _read_input(self, input_size: tuple[int, int] | str | None) -> None:
        """Sets the input's name, batch, size and dtype, checking it takes (N, 3, H, W) images;
        a model with a fixed size refuses any other ``--input-size`` rather than fail mid-run."""
        inputs = self.session.get_inputs()
        self._input = next((i for i in inputs if i.name == INPUT_NAME), inputs[0])
        self.input_name = self._input.name
        shape = list(self._input.shape)
        if len(shape) != 4:
            raise SegmentError(f"{self.model_path}: input {self.input_name!r} has shape {shape}, expected (N, 3, H, W)")
        channels = _static_dim(shape[1])
        if channels is not None and channels != 3:
            raise SegmentError(f"{self.model_path}: input {self.input_name!r} takes {channels} channels, expected 3 (RGB)")
        self._static_batch = _static_dim(shape[0])
        static_w, static_h = _static_dim(shape[3]), _static_dim(shape[2])
        requested = parse_input_size(input_size, error=SegmentError)
        if static_w is not None and static_h is not None:
            if requested is not None and requested != (static_w, static_h):
                raise SegmentError(
                    f"{self.model_path}: the model takes a fixed {static_w}x{static_h} input; "
                    f"--input-size {requested[0]}x{requested[1]} does not fit"
                )
            self.input_size = (static_w, static_h)
        else:
            self.input_size = requested or DEFAULT_INPUT_SIZE
        self._input_dtype = np.float16 if self._input.type == "tensor(float16)" else np.float32

    def _read_output(self) -> None:
        """Sets the output's name, checking (when the model states it) that it gives logits (N, C, h, w)."""
        output = self.session.get_outputs()[0]
        self.output_name = output.name
        if output.shape and len(output.shape) != 4:  # an empty shape means "unknown": checked at run time
            raise SegmentError(
                f"{self.model_path}: output {output.name!r} has shape {list(output.shape)}, expected logits (N, C, h, w)"
            )

    # --- pieces ---------------------------------------------------------------------------
    def preprocess(self, image_rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB -> (3, h_in, w_in) normalised float: ``contract.model_input``, the
        pixels ``labelsynth train`` trained the model on."""
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3:
            raise SegmentError(f"expected an (H, W, 3) RGB image, got shape {image_rgb.shape}")
        return model_input(image_rgb, self.input_size, self.mean, self.std)

    def _class_lut(self, num_classes: int) -> np.ndarray:
        """Arg-max index -> class id, checked once against the 0..254 (+255 ignore) range."""
        if self._lut is None or len(self._lut) != num_classes:
            lut = np.array([self.id_map.get(i, i) for i in range(num_classes)], dtype=np.int64)
            bad = [i for i in range(num_classes) if lut[i] > 254 and i not in self.id_map]
            if bad:
                raise SegmentError(
                    f"{self.model_path}: the model has {num_classes} classes; indices {bad[0]}..{bad[-1]} "
                    "have no class id in 0..254 (map them with --id-map)"
                )
            self._lut = lut.astype(np.uint8)
            self.num_model_classes = num_classes
        return self._lut

    def postprocess(self, logits: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(C, h, w) logits -> (H, W) uint8 ids: upsample bilinearly to ``size`` (W, H), then arg-max.

        Channels are resized a few at a time with a running max, so 150-class models at full
        HD stay within a few hundred MB.
        """
        lut = self._class_lut(logits.shape[0])
        width, height = size
        logits = logits.astype(np.float32, copy=False)
        if logits.shape[1:] == (height, width):
            best_index = logits.argmax(axis=0)
        else:
            best_value = np.full((height, width), -np.inf, dtype=np.float32)
            best_index = np.zeros((height, width), dtype=np.int64)
            for start in range(0, logits.shape[0], _RESIZE_CHANNELS):
                chunk = np.ascontiguousarray(logits[start : start + _RESIZE_CHANNELS].transpose(1, 2, 0))
                up = cv2.resize(chunk, (width, height), interpolation=cv2.INTER_LINEAR)
                if up.ndim == 2:
                    up = up[:, :, None]
                value, index = up.max(axis=2), up.argmax(axis=2) + start
                better = value > best_value  # strict: ties keep the lower index, like np.argmax
                best_value[better] = value[better]
                best_index[better] = index[better]
        return lut[best_index]

    def run(self, batch: np.ndarray) -> np.ndarray:
        """(N, 3, h_in, w_in) preprocessed frames -> (N, C, h, w) logits; honours a fixed batch size."""
        n = batch.shape[0]
        step = self._static_batch or n
        outs = []
        for start in range(0, n, step):
            part = batch[start : start + step]
            if self._static_batch and part.shape[0] < step:  # pad a short last batch with copies
                part = np.concatenate([part, np.repeat(part[-1:], step - part.shape[0], axis=0)])
            try:
                out = self.session.run([self.output_name], {self.input_name: part.astype(self._input_dtype)})[0]
            except Exception as exc:
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise SegmentError(f"{self.model_path}: inference failed ({reason})") from exc
            out = np.asarray(out)
            if out.ndim != 4:
                raise SegmentError(
                    f"{self.model_path}: output {self.output_name!r} has shape {list(out.shape)}, expected logits (N, C, h, w)"
                )
            outs.append(out[: min(step, n - start)])
        return np.concatenate(outs, axis=0)

    # --- public ---------------------------------------------------------------------------
    def predict_batch(self, images_rgb: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Several RGB uint8 frames (any sizes) -> their class-id masks, one model call."""
        if not images_rgb:
            return []
        batch = np.stack([self.preprocess(im) for im in images_rgb])
        logits = self.run(batch)
        return [self.postprocess(lg, (im.shape[1], im.shape[0])) for lg, im in zip(logits, images_rgb)]

    def predict(self, image_rgb_uint8: np.ndarray) -> np.ndarray:
        """One RGB uint8 frame (H, W, 3) -> (H, W) uint8 class ids at the frame's size."""
        return self.predict_batch([image_rgb_uint8])[0]


# --- the capture-level driver ---------------------------------------------------------------
@dataclass
class SegmentReport:
    """What ``segment_capture`` did: enough for a one-line summary and for the benchmark."""

    frames: int
    seconds: float
    out_dir: Path
    provider: str
    input_size: tuple[int, int]
    class_pixels: dict[int, int] = field(default_factory=dict)  # class id -> predicted pixel count
    class_names: dict[int, str] = field(default_factory=dict)
    unknown_ids: list[int] = field(default_factory=list)  # predicted ids the capture's class table lacks
    replaced: int = 0  # masks that already existed in out_dir and were overwritten

    @property
    def class_fractions(self) -> dict[int, float]:
        total = sum(self.class_pixels.values())
        return {k: v / total for k, v in sorted(self.class_pixels.items())} if total else {}

    def summary(self) -> str:
        rate = self.frames / self.seconds if self.seconds > 0 else float("inf")
        fractions = ", ".join(
            f"{self.class_names.get(k, f'id {k}')} {100 * v:.1f}%" for k, v in self.class_fractions.items()
        )
        line = (
            f"segmented {self.frames} frames in {self.seconds:.1f} s ({rate:.1f} frames/s, {self.provider}, "
            f"input {self.input_size[0]}x{self.input_size[1]}) -> {self.out_dir}; pixels: {fractions}"
        )
        if self.replaced:
            line += f"; replaced {self.replaced} existing masks"
        if self.unknown_ids:
            line += f"; warning: ids {self.unknown_ids} are not in the capture's class table (use --id-map)"
        return line


def segment_capture(
    capture: Path,
    model: Path,
    out_dir: Path,
    *,
    input_size: tuple[int, int] | str | None = None,
    id_map: Mapping[int, int] | str | None = None,
    device: str = "auto",
    batch_size: int = 1,
    progress: bool = True,
    overwrite: bool = True,
) -> SegmentReport:
    """Segment every frame of CAPTURE/images with an ONNX model; write ``OUT_DIR/<stem>.png``.

    Frames are read as the field reads them (``capture.images.read_image``: RGBA composited
    over the capture's background), listed by ``capture.images.list_images``, and the masks
    (greyscale class ids, ``capture.masks.write_mask``) are built in ``OUT_DIR.partial`` and
    moved into OUT_DIR only when every frame is done (``outdir.building``, merge: other files
    in OUT_DIR stay). ``overwrite=False`` refuses to replace masks already in ``out_dir`` (the CLI uses it to
    protect an existing CAPTURE/predictions/). The capture's images are only read.
    """
    capture, model, out_dir = Path(capture), Path(model), Path(out_dir)
    from ..options import whole_number

    batch_size = whole_number(batch_size, "--batch-size", 1, MAX_BATCH)
    images = list_images(capture / "images")
    classes = ClassMap.of_capture(capture)
    white_background = capture_white_background(capture)  # RGBA frames: the field's pixels
    segmenter = OnnxSegmenter(model, device=device, input_size=input_size, id_map=id_map)
    check_image_files(images, capture, white_background=white_background).raise_if_problems()

    targets = [out_dir / f"{p.stem}.png" for p in images]
    existing = sum(t.exists() for t in targets)
    if existing and not overwrite:
        raise SegmentError(f"{out_dir}: already holds {existing} of these masks; pass --force to replace them")

    start = time.perf_counter()
    with building(out_dir, merge=True) as partial:
        counts = _segment_frames(segmenter, images, partial, batch_size=batch_size,
                                 white_background=white_background, progress=progress)
    seconds = time.perf_counter() - start

    known = set(int(i) for i in classes.ids) | {IGNORE_ID}
    predicted = [int(i) for i in np.flatnonzero(counts)]
    names = {c.id: c.name for c in classes.classes}
    names[IGNORE_ID] = "ignore"
    return SegmentReport(
        frames=len(images),
        seconds=seconds,
        out_dir=out_dir,
        provider=segmenter.provider,
        input_size=segmenter.input_size,
        class_pixels={i: int(counts[i]) for i in predicted},
        class_names=names,
        unknown_ids=[i for i in predicted if i not in known],
        replaced=existing,
    )


def _segment_frames(segmenter: OnnxSegmenter, images: list[Path], folder: Path, *, batch_size: int,
                    white_background: bool, progress: bool) -> np.ndarray:
    """Segment the frames batch by batch into ``folder``; returns the pixel count per class id
    (256 bins), which the report uses to flag ids missing from the capture's class table."""
    counts = np.zeros(256, dtype=np.int64)
    with make_progress(progress) as bar:
        task = bar.add_task("segment", total=len(images), status="")
        for first in range(0, len(images), batch_size):
            paths = images[first : first + batch_size]
            frames = [read_image(p, white_background=white_background) for p in paths]
            for path, mask in zip(paths, segmenter.predict_batch(frames)):
                write_mask(folder / f"{path.stem}.png", mask)
                counts += np.bincount(mask.ravel(), minlength=256)
            bar.update(task, advance=len(paths), status=paths[-1].name)
    return counts
