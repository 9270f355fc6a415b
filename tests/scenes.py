"""Tiny captures of an object filmed all around, for tests of the field on any capture shape.

An object (a box with a sphere on top, coloured by position with a procedural pattern) stands
in front of a plain backdrop; cameras sit on a sphere around it at several elevations, as in
the NeRF-synthetic layout. Everything is ray-cast with trimesh, so colour, masks and truth
come from the same hits.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh

from labelsynth.cameras import Camera, look_at


def object_mesh() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(0.9, 0.6, 0.5))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.32)
    ball.apply_translation((0.1, 0.0, 0.45))
    return trimesh.util.concatenate([box, ball])


def _colour(points: np.ndarray) -> np.ndarray:
    """A smooth, non-repeating pattern over the surface: enough texture to fix depth."""
    x, y, z = points.T
    r = 0.5 + 0.4 * np.sin(5.0 * x + 1.0) * np.cos(3.0 * z)
    g = 0.45 + 0.35 * np.sin(4.0 * y + 2.0 * z)
    b = 0.35 + 0.3 * np.cos(6.0 * x - 3.0 * y)
    return np.clip(np.stack([r, g, b], -1), 0, 1)


def orbit_cameras(n: int, size: int, radius: float = 2.2, elevations=(10.0, 35.0, 60.0)) -> list[Camera]:
    """``n`` cameras on a sphere around the origin, azimuths interleaved over the elevations."""
    f = 1.1 * size
    cams = []
    for i in range(n):
        el = np.radians(elevations[i % len(elevations)])
        az = 2 * np.pi * i / n
        eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cams.append(Camera(size, size, f, f, size / 2, size / 2, look_at(eye, np.zeros(3))))
    return cams


def render(mesh: trimesh.Trimesh, cam: Camera, backdrop: float) -> tuple[np.ndarray, np.ndarray]:
    """(RGB uint8, object mask 0/1) of one view."""
    o, d = cam.rays()
    loc, ray, _ = mesh.ray.intersects_location(o, d, multiple_hits=False)
    rgb = np.full((len(o), 3), backdrop, np.float64)
    rgb[ray] = _colour(loc)
    mask = np.zeros(len(o), np.uint8)
    mask[ray] = 1
    h, w = cam.height, cam.width
    return (rgb.reshape(h, w, 3) * 255).round().astype(np.uint8), mask.reshape(h, w)


def make_object_capture(root: Path, frames: int = 12, size: int = 48, annotated=(0, 6),
                        backdrop: float = 1.0, cameras: list[Camera] | None = None) -> tuple[Path, Path]:
    """Write ROOT/capture (transforms.json, images/, annotations/, classes.json) and ROOT/truth;
    ``cameras`` (square, ``size`` wide, focal 1.1 * size) replace the orbit's."""
    capture, truth = Path(root) / "capture", Path(root) / "truth"
    for sub in (capture / "images", capture / "annotations", truth):
        sub.mkdir(parents=True, exist_ok=True)
    mesh = object_mesh()
    entries = []
    for i, cam in enumerate(cameras if cameras is not None else orbit_cameras(frames, size)):
        rgb, mask = render(mesh, cam, backdrop)
        name = f"view_{i:02d}"
        cv2.imwrite(str(capture / "images" / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(truth / f"{name}.png"), mask)
        if i in annotated:
            cv2.imwrite(str(capture / "annotations" / f"{name}.png"), mask)
        entries.append({"file_path": f"images/{name}.png", "transform_matrix": cam.c2w.tolist()})
    (capture / "transforms.json").write_text(json.dumps({
        "camera_model": "PINHOLE", "fl_x": 1.1 * size, "fl_y": 1.1 * size, "cx": size / 2, "cy": size / 2,
        "w": size, "h": size, "frames": entries}))
    (capture / "classes.json").write_text(json.dumps({"classes": [
        {"id": 0, "name": "background", "color": [0, 0, 0]},
        {"id": 1, "name": "object", "color": [255, 80, 40], "wound_bed": True}]}))
    return capture, truth


def _skin_colour(points: np.ndarray) -> np.ndarray:
    """Skin-like tone with a faint pattern, and a dark red patch (the 'wound') at the centre."""
    x, y, _ = points.T
    skin = np.stack([0.78 + 0.06 * np.sin(7 * x), 0.60 + 0.05 * np.cos(6 * y), 0.50 + 0.04 * np.sin(5 * (x + y))], -1)
    patch = np.stack([0.55 + 0.15 * np.sin(9 * x), 0.15 + 0.08 * np.cos(11 * y), 0.12 + 0.0 * x], -1)
    inside = (x**2 + y**2 < 0.3**2)[:, None]
    return np.where(inside, patch, skin)


def _write_views(capture: Path, truth: Path, size: int, views, annotated, second: dict) -> None:
    """The frames (camera, rgb (size*size, 3) in 0..1, class-id mask (size*size,)) of a square
    PINHOLE capture: images/, annotations/ for ``annotated``, truth/, transforms.json and a
    two-class classes.json (background and ``second``)."""
    entries, f = [], None
    for i, (cam, rgb, mask) in enumerate(views):
        f = cam.fx
        name = f"view_{i:02d}"
        img = (rgb.reshape(size, size, 3) * 255).round().astype(np.uint8)
        cv2.imwrite(str(capture / "images" / f"{name}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(truth / f"{name}.png"), mask.reshape(size, size))
        if i in annotated:
            cv2.imwrite(str(capture / "annotations" / f"{name}.png"), mask.reshape(size, size))
        entries.append({"file_path": f"images/{name}.png", "transform_matrix": cam.c2w.tolist()})
    (capture / "transforms.json").write_text(json.dumps({
        "camera_model": "PINHOLE", "fl_x": f, "fl_y": f, "cx": size / 2, "cy": size / 2,
        "w": size, "h": size, "frames": entries}))
    (capture / "classes.json").write_text(json.dumps({"classes": [
        {"id": 0, "name": "background", "color": [0, 0, 0]}, {"id": 1, **second}]}))


def make_patch_capture(root: Path, frames: int = 10, size: int = 40, annotated=(0, 5)) -> tuple[Path, Path]:
    """A patch on a skin-coloured surface that fills every view, filmed from one side (a phone
    over a wound): the images' rim is the surface itself. Writes ROOT/capture and ROOT/truth."""
    capture, truth = Path(root) / "capture", Path(root) / "truth"
    for sub in (capture / "images", capture / "annotations", truth):
        sub.mkdir(parents=True, exist_ok=True)
    slab = trimesh.creation.box(extents=(6.0, 6.0, 0.2))
    slab.apply_translation((0.0, 0.0, -0.1))  # top face at z = 0
    f = 1.1 * size
    views = []
    for i in range(frames):
        el, az = np.radians(55.0 + 25.0 * (i % 2)), 2 * np.pi * i / frames
        eye = 1.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cam = Camera(size, size, f, f, size / 2, size / 2, look_at(eye, np.zeros(3)))
        o, d = cam.rays()
        loc, ray, _ = slab.ray.intersects_location(o, d, multiple_hits=False)
        rgb = np.zeros((len(o), 3))
        rgb[ray] = _skin_colour(loc)
        mask = np.zeros(len(o), np.uint8)
        mask[ray] = (loc[:, 0] ** 2 + loc[:, 1] ** 2 < 0.3**2).astype(np.uint8)
        views.append((cam, rgb, mask))
    _write_views(capture, truth, size, views, annotated, {"name": "wound", "color": [200, 40, 40], "wound_bed": True})
    return capture, truth


def table_scene(behind: float = 1.2) -> tuple[trimesh.Trimesh, trimesh.Trimesh]:
    """(object, table): a box with a ball on it, standing on a table top at z = 0 that reaches
    far towards +x (where the cameras are) and ends ``behind`` beyond the object's centre."""
    box = trimesh.creation.box(extents=(0.7, 0.5, 0.4))
    box.apply_translation((0.0, 0.0, 0.2))
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.25)
    ball.apply_translation((0.05, 0.0, 0.55))
    table = trimesh.creation.box(extents=(5.0 + behind, 8.0, 0.2))
    table.apply_translation((0.5 * (5.0 - behind), 0.0, -0.1))  # from x = -behind to 5
    return trimesh.util.concatenate([box, ball]), table


TABLE_ANNOTATED = (0, 4, 8)
"""``make_table_capture``'s annotated frames."""
TABLE_WHITE_ABOVE = 0.6
"""``make_table_capture``: the object is saturated white above this height."""


def make_table_capture(root: Path, frames: int = 12, size: int = 48, annotated=TABLE_ANNOTATED,
                       table: float = 0.97, backdrop: float = 0.03, white_above: float = TABLE_WHITE_ABOVE,
                       behind: float = 1.2) -> tuple[Path, Path]:
    """Real photographs' hard parts in a tiny capture (issue 31): an object on a white,
    textureless table, filmed from above on one side as DTU films its objects, with a dark
    backdrop beyond the table's far edge; the object's top (above ``white_above``) is
    saturated white, the colour of the table seen through it, so nothing but its outline
    tells where it is. Writes ROOT/capture and ROOT/truth (object 1, table and backdrop 0).
    """
    capture, truth = Path(root) / "capture", Path(root) / "truth"
    for sub in (capture / "images", capture / "annotations", truth):
        sub.mkdir(parents=True, exist_ok=True)
    obj, table_top = table_scene(behind)
    scene = trimesh.util.concatenate([obj, table_top])
    n_obj = len(obj.faces)
    f = 1.1 * size
    views = []
    for i in range(frames):
        el = np.radians(35.0 + 20.0 * (i % 2))
        az = np.radians(-60.0 + 120.0 * i / max(frames - 1, 1))  # an arc on the table's near side
        eye = 2.6 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        cam = Camera(size, size, f, f, size / 2, size / 2, look_at(eye, np.array([0.0, 0.0, 0.3])))
        o, d = cam.rays()
        loc, ray, tri = scene.ray.intersects_location(o, d, multiple_hits=False)
        rgb = np.full((len(o), 3), backdrop)
        on_obj = tri < n_obj
        colour = np.where(on_obj[:, None], _colour(loc), table)
        colour[on_obj & (loc[:, 2] > white_above)] = 1.0
        rgb[ray] = colour
        mask = np.zeros(len(o), np.uint8)
        mask[ray[on_obj]] = 1
        views.append((cam, rgb, mask))
    _write_views(capture, truth, size, views, annotated, {"name": "object", "color": [255, 80, 40], "wound_bed": True})
    return capture, truth


def table_truth_hits(capture_dir, behind: float = 1.2):
    """Per frame: the exact scene's first hit of every pixel (world), on the object or not."""
    from labelsynth.capture import load_capture

    cap = load_capture(capture_dir)
    obj, table = table_scene(behind)
    scene = trimesh.util.concatenate([obj, table])
    out = []
    for f in cap.frames:
        o, d = f.camera.rays()
        loc, ray, tri = scene.ray.intersects_location(o, d, multiple_hits=False)
        hit = np.zeros(len(o), bool)
        hit[ray] = True
        points = np.zeros((len(o), 3))
        points[ray] = loc
        on_obj = np.zeros(len(o), bool)
        on_obj[ray[tri < len(obj.faces)]] = True
        out.append((hit, points, on_obj))
    return cap, out


def table_scores(capture_dir, out, near: float = 0.1) -> dict[str, int]:
    """How a fit of ``make_table_capture`` (with its default annotated frames and white top) did,
    counted over every frame: ``top`` rays through the saturated top and ``top_hit`` of them whose
    fitted surface hit lies within ``near`` of the truth; ``object`` / ``object_hit`` the same over
    all of the object's rays; over the unannotated frames' masks (OUT/masks), ``backdrop`` pixels
    that see the backdrop and ``backdrop_object`` of them labelled object, and ``inter`` / ``union``
    of the object's pixels and the masks' (foreground Dice = 2 inter / union)."""
    from labelsynth.capture.masks import read_mask
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    cap, hits = table_truth_hits(capture_dir)
    view = FieldRenderer(RunFolder(out).load_field())
    counts = dict.fromkeys(("top", "top_hit", "object", "object_hit", "backdrop", "backdrop_object", "inter",
                            "union"), 0)
    for i, (frame, cam) in enumerate(zip(cap.frames, cap.unit_cameras())):
        hit, points, on_obj = hits[i]
        fitted_hit, fitted_points, _, _ = view.caster().cast(*cam.rays())
        close = fitted_hit & (np.linalg.norm(cap.normalization.to_world(fitted_points) - points, axis=1) < near)
        top = on_obj & (points[:, 2] > TABLE_WHITE_ABOVE)
        counts["top"] += int(top.sum())
        counts["top_hit"] += int((top & close).sum())
        counts["object"] += int(on_obj.sum())
        counts["object_hit"] += int((on_obj & close).sum())
        if i not in TABLE_ANNOTATED:
            pred = read_mask(Path(out) / "masks" / f"{frame.name}.png", None, cap.classes).ravel() == 1
            counts["backdrop"] += int((~hit).sum())
            counts["backdrop_object"] += int(((~hit) & pred).sum())
            counts["inter"] += int((pred & on_obj).sum())
            counts["union"] += int(pred.sum() + on_obj.sum())
    return counts
