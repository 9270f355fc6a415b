"""`labelsynth augment`: novel views of a fitted capture, with labels consistent with every frame.

After ``expand``, the fitted surface and semantic field can show the wound from viewpoints the
video never had. ``augment(OUT, views=N)`` samples N poses around the captured path
(``poses``), renders each one's mask from the field and its colours from the real frames that
see each surface point (``views``), and writes ``OUT/augment`` (``write``), built in
``OUT/augment.partial`` and renamed when complete. Nothing else in OUT, and nothing in the
capture, is written. (Not to be confused with ``train.augment``, the 2D augmentation of
training crops.)
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import LabelsynthError

__all__ = ["augment", "AugmentResult", "AugmentError"]

AUGMENT_DIR = "augment"
MAX_VIEWS = 100_000


class AugmentError(LabelsynthError, ValueError):
    """An option or input that ``augment`` cannot use (one line, names what is wrong)."""


@dataclass
class AugmentResult:
    out: Path  # OUT/augment
    views: int
    rejected: dict[str, int]
    valid_fraction: float  # mean over the novel views
    seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        rej = sum(self.rejected.values())
        return (f"{self.views} novel views in {self.out} ({self.valid_fraction:.1%} of their pixels seen by real "
                f"frames); {rej} poses rejected ({self.rejected.get('empty', 0)} mostly empty space, "
                f"{self.rejected.get('unseen', 0)} mostly unseen surface); {sum(self.seconds.values()):.0f} s")


def augment(
    out_dir: str | Path,
    views: int,
    *,
    seed: int = 0,
    spread: str | float | None = None,
    method: str = "blend",
    device: str = "auto",
    capture: str | Path | None = None,
    force: bool = False,
    progress: bool = True,
) -> AugmentResult:
    """Add ``views`` novel views to the finished expand output ``out_dir`` (README, "Novel views").

    ``spread``: how far poses stray from the path (``poses.parse_spread``); ``method``:
    ``blend`` (real frames' colours, the default: sharper, see the benchmark) or ``head`` (the
    field's colour head); ``capture``: the capture folder when it moved since expand.
    ``force`` replaces an existing OUT/augment. The same seed gives the same poses.
    """
    from ..device import pick_device
    from ..export.labels_h5 import LabelsReader
    from ..options import DeviceChoice
    from ..outdir import building, check_out
    from ..progress import console, track
    from ..render.renderer import FieldRenderer
    from ..rundir import RunFolder
    from .poses import parse_spread, path_points, sample_poses
    from .views import METHODS, RealFrames, render_view
    from .write import AugmentWriter, world_camera

    from ..options import seed_value, whole_number

    views = whole_number(views, "--views", 1, MAX_VIEWS)
    seed = seed_value(seed)
    if method not in METHODS:
        raise AugmentError(f"--method must be one of {', '.join(METHODS)}, not {method!r}")
    sp = parse_spread(spread)
    dev = pick_device(DeviceChoice.parse(device, "--device").value)
    run = RunFolder(out_dir)
    _, cap = run.open_capture(capture)
    target = run.path / AUGMENT_DIR
    check_out(target, force)
    with LabelsReader(run.labels_path) as real:  # the real frames augment.h5 will copy: checked now
        names = set(cap.names)
        stray = [n for n in real.frame_names if n not in names]
        if stray:
            raise AugmentError(f"{run.labels_path}: frames {stray[:3]} are not in the capture {cap.root} "
                               "(a different capture?)")
    t0 = time.perf_counter()
    fitted = run.load_field(dev)
    run.check_fits(fitted, cap)
    view = FieldRenderer(fitted)
    cams = cap.unit_cameras()
    images = [cap.load_image(i) for i in track(range(len(cap)), "loading images", enabled=progress)]
    real = RealFrames(view, cams, images, progress=progress)
    del images
    seconds = {"load": time.perf_counter() - t0}
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    poses = sample_poses(int(views), rng, path_points(cams, view.render_caster()), sp, view.render_caster(), real)
    seconds["poses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    width = max(4, len(str(views - 1)))
    valid = []
    real_world = {f.name: f.camera for f in cap.frames}
    with building(target, force=force) as partial:
        writer = AugmentWriter(partial, len(poses.cameras), run.labels_path, cap.classes, cap.normalization, real_world,
                               {"augment_seed": seed, "augment_method": method, "augment_spread": asdict(sp),
                                "augment_rejected": poses.rejected})
        try:
            for k, cam in enumerate(track(poses.cameras, "rendering novel views", enabled=progress)):
                novel = render_view(view, real, cam, method=method)
                writer.add_view(f"novel_{k:0{width}d}", novel, cam)
                valid.append(novel.valid_fraction)
            seconds["render"] = time.perf_counter() - t0
            writer.finish({
                "views": len(poses.cameras),
                "rejected": poses.rejected,
                "seed": seed,
                "method": method,
                "spread": asdict(sp),
                "capture": str(cap.root),
                "valid_fraction": [float(v) for v in valid],
                "cameras": [{"name": n, "c2w": world_camera(c, cap.normalization).c2w.tolist(), "fx": c.fx, "fy": c.fy,
                             "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height}
                            for n, c in zip(writer.names, poses.cameras)],
                "seconds": seconds,
            })
        except BaseException:
            writer.abort()
            raise
    result = AugmentResult(target, len(poses.cameras), dict(poses.rejected), float(np.mean(valid)), seconds)
    if progress:
        console.print(f"[bold]labelsynth[/] {result.summary()}")
    return result
