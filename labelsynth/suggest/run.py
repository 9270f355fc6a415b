"""``labelsynth suggest``: fit the geometry before any annotation exists, and name the frames to annotate.

OUT (built in OUT.partial, renamed when complete) holds:

- ``field.pt``: the geometry-only field (``rundir.save_field``) with what it was fitted on
  (``geometry.fingerprint``), for ``expand --geometry OUT`` once the annotations exist;
- ``suggest.json``: the objective, the chosen frames in order of choice with each one's gain, their
  coverage and frame score, the same for ``spread:K`` (``capture.select``), the surface sampled, the geometry stage's
  statistics and seconds;
- ``suggest.png``: the contact sheet (``sheet``).
"""

from __future__ import annotations

import json
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..capture import check_capture, load_capture
from ..capture.select import select_frames
from ..device import pick_device
from ..errors import LabelsynthError
from ..options import MAX_ANNOTATE, OptionError, SuggestOptions
from ..outdir import building, check_out, write_text_atomic
from ..progress import console
from ..render.renderer import FieldRenderer
from ..rundir import RunFolder
from .coverage import CoverageConfig, Pick, surface_views
from .sheet import contact_sheet

SUGGEST_JSON = "suggest.json"
SHEET_PNG = "suggest.png"
OUT_SUFFIX = "-suggest"


@dataclass
class SuggestResult:
    out: Path
    capture: Path
    picks: list[Pick]
    coverage: float
    spread: list[str]
    spread_coverage: float
    seconds: dict[str, float] = field(default_factory=dict)
    options: SuggestOptions | None = None

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.picks]

    def summary(self) -> str:
        n = len(self.picks)
        lines = [f"annotate {'this frame' if n == 1 else f'these {n} frames'} (in order of the surface they add):"]
        lines += [f"  {i + 1}. {p.name}  +{100 * p.gain:.1f}%  (together {100 * p.coverage:.1f}%)"
                  for i, p in enumerate(self.picks)]
        lines.append(f"they show {100 * self.coverage:.1f}% of the surface the video shows; "
                     f"spread:{len(self.picks)} ({', '.join(self.spread)}) shows {100 * self.spread_coverage:.1f}%")
        lines.append(f"wrote {self.out / SUGGEST_JSON}, {self.out / SHEET_PNG} and the geometry "
                     f"{RunFolder(self.out).field_path} ({sum(self.seconds.values()):.0f} s)")
        lines.append(f"then: {self.expand_command()}")
        return "\n".join(lines)

    def expand_command(self, out: str = "OUT") -> str:
        """The ``expand`` that reuses this geometry once the named frames are annotated."""
        opts = self.options or SuggestOptions(annotate=len(self.picks))
        words = ["labelsynth", "expand", str(self.capture), "--out", out, "--geometry", str(self.out)]
        if opts.recipe != "default":
            words += ["--recipe", opts.recipe]
        for item in opts.overrides:
            words += ["--set", item]
        if opts.seed:
            words += ["--seed", str(opts.seed)]
        return " ".join(shlex.quote(w) for w in words)


def default_out(capture_dir: str | Path) -> Path:
    """Where ``suggest`` writes without ``--out``: beside the capture, ``<capture>-suggest``."""
    capture_dir = Path(capture_dir).resolve()
    return capture_dir.with_name(capture_dir.name + OUT_SUFFIX)


def suggest(
    capture_dir: str | Path,
    options: SuggestOptions | None = None,
    out: str | Path | None = None,
    *,
    force: bool = False,
    progress: bool = True,
    coverage: CoverageConfig | None = None,
    **values: Any,
) -> SuggestResult:
    """Fit stage 1 on ``capture_dir``'s images, save it in OUT, and choose ``annotate`` frames by
    ``objective`` (greedy surface coverage or the frame objective, ``coverage``), compared with
    ``spread:K``.

    ``options`` or its fields as keywords (``annotate=``, ``objective=``, ``recipe=``, ``device=``, ``seed=``,
    ``overrides=``). Every option, OUT (absent or empty, never inside the capture) and every
    image are checked first: a bad one is one line before OUT.partial exists and before any
    fitting.
    """
    opts = options.replace(**values) if options is not None else SuggestOptions(**values)
    rec = opts.check()
    capture_dir = Path(capture_dir)
    out = default_out(capture_dir) if out is None else Path(out)
    check_out(out, force)  # first: a looping or dangling link is refused there, before resolve() meets it
    if capture_dir.is_dir() and out.resolve().is_relative_to(capture_dir.resolve()):
        raise OptionError(f"--out {out}: inside the capture {capture_dir} (labelsynth never writes there); "
                          "choose a folder outside it")
    capture = load_capture(capture_dir)
    if opts.annotate > len(capture):
        raise OptionError(f"--annotate {opts.annotate}: {capture_dir} has only {len(capture)} frames")
    check = check_capture(capture, labels=None)
    check.raise_if_problems()
    dev = pick_device(opts.device.value)
    from ..pipeline import fit_geometry  # the orchestration imports this package's siblings

    seconds: dict[str, float] = {"check": check.seconds}
    with building(out, force=force) as partial:
        if progress:
            console.print(f"[bold]labelsynth[/] {check.summary()}")
            console.print(f"[bold]labelsynth[/] {len(capture)} frames, recipe={rec.name}, device={dev}: "
                          "fitting the geometry (no labels needed)")
        t0 = time.time()
        fitted, gstats = fit_geometry(capture, rec, dev, seed=opts.seed, progress=progress)
        seconds["geometry"] = time.time() - t0
        run = RunFolder(partial)

        t0 = time.time()
        view = FieldRenderer(fitted)
        run.save_field(view.field_with_surface())  # expand --geometry renders it without extracting it again
        mesh, caster = view.mesh(), view.caster()
        cams = capture.unit_cameras()
        cfg = coverage or CoverageConfig(seed=opts.seed)
        views = surface_views(mesh, cams, capture.names, cfg, caster=caster, progress=progress)
        upto = min(MAX_ANNOTATE, len(capture))
        if opts.objective == "frames":  # its K-choice is not the first K of a longer one: one choice per K
            by_k = [views.ordered(views.frame_choice(k)) for k in range(1, upto + 1)]
            picks = by_k[opts.annotate - 1]
            suggested_curve = [c[-1].coverage for c in by_k]
        else:
            ranked = views.greedy(upto)  # greedy: the first K of a longer run are the K it would pick
            picks = ranked[: opts.annotate]
            suggested_curve = [p.coverage for p in ranked]
        spread = _spread(capture.names, opts.annotate)
        spread_gains = _gains(views, spread)
        curves = {"suggested": suggested_curve,
                  "spread:k": views.curve([_spread(capture.names, k) for k in range(1, upto + 1)])}
        seconds["coverage"] = time.time() - t0

        t0 = time.time()
        images = {i: capture.load_image(i) for i in {*(p.index for p in picks), *spread}}
        tolerance = cfg.occlusion_tolerance * float(np.linalg.norm(np.ptp(views.points, axis=0)))
        contact_sheet(partial / SHEET_PNG,
                      [(f"suggested ({100 * picks[-1].coverage:.0f}%)", [p.index for p in picks], [p.gain for p in picks]),
                       (f"spread:{opts.annotate} ({100 * views.coverage(spread):.0f}%)", spread, spread_gains)],
                      images, cams, mesh, caster, views, curves, tolerance, progress=progress)
        seconds["sheet"] = time.time() - t0

        result = SuggestResult(out=out, capture=capture_dir, picks=picks, coverage=picks[-1].coverage,
                               spread=[capture.names[i] for i in spread], spread_coverage=views.coverage(spread),
                               seconds=seconds, options=opts)
        write_text_atomic(partial / SUGGEST_JSON, json.dumps(_record(result, views, curves, opts, rec, dev, gstats,
                                                                     mesh_faces=len(mesh.faces), cfg=cfg), indent=2, default=float))
    return result


def _spread(names: list[str], k: int) -> list[int]:
    """The indices ``spread:k`` picks (``capture.select``), in frame order."""
    index = {n: i for i, n in enumerate(names)}
    return [index[n] for n in select_frames(f"spread:{k}", names)]


def _gains(views, order: list[int]) -> list[float]:
    """Each frame's gain when added in ``order``."""
    covered = [views.coverage(order[: j + 1]) for j in range(len(order))]
    return [c - (covered[j - 1] if j else 0.0) for j, c in enumerate(covered)]


def _record(result: SuggestResult, views, curves, opts: SuggestOptions, rec, dev, gstats, *, mesh_faces: int,
            cfg: CoverageConfig) -> dict:
    """suggest.json's contents."""
    seen = views.seen
    return {
        "version": __version__,
        "capture": str(Path(result.capture).resolve()),
        "annotate": opts.annotate,
        "objective": opts.objective,
        "frame_score": views.frame_score([p.index for p in result.picks]),
        "frames": [{"name": p.name, "index": p.index, "gain": p.gain, "coverage": p.coverage} for p in result.picks],
        "coverage": result.coverage,
        "spread": {"rule": f"spread:{opts.annotate}", "frames": result.spread, "coverage": result.spread_coverage,
                   "frame_score": views.frame_score([views.names.index(n) for n in result.spread])},
        "coverage_by_k": curves,
        "surface": {"samples": len(seen), "seen": int(seen.sum()), "mesh_faces": mesh_faces,
                    "reference_density_px": views.reference, "reference_quantile": cfg.reference_quantile},
        "geometry_file": RunFolder(result.out).field_path.name,
        "sheet": SHEET_PNG,
        "recipe": rec.name, "overrides": opts.overrides, "seed": opts.seed, "device": str(dev),
        "geometry": gstats,
        "seconds": result.seconds,
        "expand": result.expand_command(),
    }


def read_suggestion(folder: str | Path) -> dict:
    """A suggest OUT's suggest.json (one line if it is missing or unreadable)."""
    path = Path(folder) / SUGGEST_JSON
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LabelsynthError(f"{path}: not found (not the output folder of labelsynth suggest)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LabelsynthError(f"{path}: not a suggest.json ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise LabelsynthError(f"{path}: not a suggest.json (no frames)")
    return data
