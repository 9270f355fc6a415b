"""Where the fitted geometry fails on a case with truth masks for every view (issue 31).

    python benchmarks/diagnose_geometry.py OUT CASE [--views 000012,000030] [--figures DIR]

OUT is an ``expand`` output (its ``field.pt`` and ``masks/``), CASE the case folder it came
from (``capture/`` and ``truth/``, e.g. made by make_dtu_capture.py). Per view, at the
geometry stage's training scale (volume rendering, as the geometry was trained):

- PSNR of the rendered colour against the frame;
- holes: the share of the object's pixels (truth) whose ray the surface leaves mostly
  transparent (opacity < 0.5): their colour came from the background model;
- backdrop absorbed by the surface: the share of the truth's background pixels the surface
  makes opaque (inside the cube that is right for a table, wrong for a wall or a dark room);

and at full resolution, from the mesh the masks are rendered from:

- misses: object pixels whose ray meets no surface (labelled background whatever the head says);
- hit but labelled background; labelled object where the truth is background (false
  positives), split by how far their surface point lies from the object's visual hull (carved
  from every view's truth mask) and by the pixel's brightness (dark < 0.15, bright > 0.85
  in every channel, else mid);
- depth sanity: the share of hit pixels whose surface point lies in front of the nearest
  camera's near plane or on the cube's walls (a shell the SDF grew to explain a backdrop);
- unseen surface (``render.support``): the share of the view's pixels whose surface no
  annotated frame saw, and the shares of its object-labelled-background and false-object
  pixels that lie there (labels the head guessed rather than learnt).

Prints one line per view and the totals; writes OUT/diagnose.json, and with ``--figures``
an error image per view (green: missed object, red: false object, blue: hole in the volume
rendering).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

HULL_RES = 128
DARK, BRIGHT = 0.15, 0.85
NEAR_HULL = 0.03  # unit-cube distance within which a false positive counts as at the hull's edge


def visual_hull(cams, truths, res: int = HULL_RES, slack: int = 1) -> np.ndarray:
    """(res,)*3 bool over the unit cube: points that project into the object in every view that
    sees them, but ``slack`` views (hand-drawn masks miss thin parts)."""
    lin = (np.arange(res) + 0.5) / res * 2 - 1
    pts = np.stack(np.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3)
    outside = np.zeros(len(pts), dtype=np.int32)
    for cam, t in zip(cams, truths):
        uv, depth = cam.project(pts)
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        seen = (depth > 0) & (u >= 0) & (v >= 0) & (u < cam.width) & (v < cam.height)
        fg = np.zeros(len(pts), dtype=bool)
        fg[seen] = t[v[seen], u[seen]]
        outside += seen & ~fg
    return (outside <= slack).reshape((res,) * 3)


def hull_distance(hull: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Unit-cube distance of points to the hull (0 inside)."""
    from scipy import ndimage

    res = hull.shape[0]
    dist = ndimage.distance_transform_edt(~hull) * (2.0 / res)
    idx = np.clip(((pts + 1) * 0.5 * res).astype(np.int64), 0, res - 1)
    return dist[idx[:, 0], idx[:, 1], idx[:, 2]]


@torch.no_grad()
def volume_render(fitted, cam, chunk: int = 8192):
    """Colour and opacity of every pixel of ``cam`` (unit cube) by the geometry stage's renderer."""
    from labelsynth.geometry.training import render_rays_rgb

    o, d = cam.rays()
    o = torch.as_tensor(o, dtype=torch.float32, device=fitted.device)
    d = torch.as_tensor(d, dtype=torch.float32, device=fitted.device)
    rgb, opa = [], []
    geo = fitted.recipe.geometry
    for s in range(0, len(o), chunk):
        r, a, _ = render_rays_rgb(fitted.sdf, fitted.grid, o[s:s + chunk], d[s:s + chunk], 1.0, geo.march_steps, train=False)
        rgb.append(r)
        opa.append(a)
    return torch.cat(rgb).cpu().numpy(), torch.cat(opa).cpu().numpy()


def main() -> None:
    import cv2

    from labelsynth.capture import load_capture
    from labelsynth.capture.masks import read_mask
    from labelsynth.device import pick_device
    from labelsynth.pipeline import teaching_support
    from labelsynth.render.renderer import FieldRenderer
    from labelsynth.rundir import RunFolder

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("case", type=Path)
    ap.add_argument("--views", default="", help="comma-separated frame names (default: all)")
    ap.add_argument("--figures", type=Path, default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path, default=None, help="where to write the numbers (default OUT/diagnose.json)")
    args = ap.parse_args()

    cap = load_capture(args.case / "capture")
    dev = pick_device(args.device)
    fitted = RunFolder(args.out).load_field(dev)
    cams = cap.unit_cameras()
    truths = [read_mask(args.case / "truth" / f"{n}.png", None, cap.classes) for n in cap.names]
    fg_truth = [(t != 0) & (t != 255) for t in truths]
    annotated = {f.name for f in cap.frames if f.annotation_path is not None}
    hull = visual_hull(cams, fg_truth)
    print(f"visual hull: {hull.mean():.3%} of the cube")
    scale = fitted.recipe.geometry.train_scale
    view = FieldRenderer(fitted)
    caster = view.render_caster()
    support = teaching_support(view, cap, "annotations")
    names = [n for n in args.views.split(",") if n] or cap.names
    rows = []
    if args.figures:
        args.figures.mkdir(parents=True, exist_ok=True)
    print(f"{'view':>10s} {'psnr':>6s} {'holes':>6s} {'absorb':>6s} | {'dice':>5s} {'miss':>6s} {'hit-bg':>6s} "
          f"{'FP':>6s} {'FPfar':>6s} {'FPdark':>6s} {'FPbrt':>6s} {'walls':>6s} | {'unseen':>6s} {'hbg-u':>6s} "
          f"{'FP-u':>6s}")
    for name in names:
        i = cap.names.index(name)
        img = cap.load_image(i)
        tf = fg_truth[i]
        valid = truths[i] != 255
        # volume rendering at the training scale
        small = cams[i].scaled(scale)
        rgb, opa = volume_render(fitted, small)
        img_s = cv2.resize(img, (small.width, small.height), interpolation=cv2.INTER_AREA).reshape(-1, 3) / 255.0
        mse = float(((rgb - img_s) ** 2).mean())
        psnr = -10 * np.log10(max(mse, 1e-10))
        tf_s = cv2.resize(tf.astype(np.uint8), (small.width, small.height), interpolation=cv2.INTER_NEAREST).ravel() > 0
        holes = float((opa[tf_s] < 0.5).mean()) if tf_s.any() else 0.0
        absorb = float((opa[~tf_s] > 0.5).mean()) if (~tf_s).any() else 0.0
        # the mesh at full resolution
        hit, pts, faces, _ = caster.cast(*cams[i].rays())
        unseen = support.unseen(hit, pts, faces).reshape(tf.shape)
        hit = hit.reshape(tf.shape)
        pred = read_mask(args.out / "masks" / f"{name}.png", None, cap.classes)
        pf = (pred != 0) & (pred != 255)
        miss = tf & ~hit & valid
        hit_bg = tf & hit & ~pf & valid
        fp = pf & ~tf & valid
        fp_pts = pts.reshape(-1, 3)[fp.ravel()]
        far = hull_distance(hull, fp_pts) > NEAR_HULL if len(fp_pts) else np.zeros(0, bool)
        px = img.reshape(-1, 3)[fp.ravel()] / 255.0
        dark = (px.max(1) < DARK) if len(px) else np.zeros(0, bool)
        bright = (px.min(1) > BRIGHT) if len(px) else np.zeros(0, bool)
        walls = float((np.abs(pts.reshape(-1, 3)[hit.ravel()]).max(1) > 0.97).mean()) if hit.any() else 0.0
        inter = int((pf & tf & valid).sum())
        dice = 2 * inter / max(int((pf & valid).sum()) + int(tf.sum()), 1)
        n_obj = max(int(tf.sum()), 1)
        row = {"view": name, "annotated": name in annotated, "psnr": psnr, "holes": holes, "absorbed": absorb,
               "dice": dice, "miss": int(miss.sum()) / n_obj, "hit_labelled_bg": int(hit_bg.sum()) / n_obj,
               "fp": int(fp.sum()) / n_obj, "fp_far_from_hull": int(far.sum()) / n_obj,
               "fp_dark": int(dark.sum()) / n_obj, "fp_bright": int(bright.sum()) / n_obj, "hits_on_walls": walls,
               "unseen": float(unseen.mean()),
               "hit_bg_unseen": int((hit_bg & unseen).sum()) / max(int(hit_bg.sum()), 1),
               "fp_unseen": int((fp & unseen).sum()) / max(int(fp.sum()), 1)}
        rows.append(row)
        print(f"{name:>10s}{'*' if name in annotated else ' '}{psnr:6.2f} {holes:6.3f} {absorb:6.3f} | {dice:5.3f} "
              f"{row['miss']:6.3f} {row['hit_labelled_bg']:6.3f} {row['fp']:6.3f} {row['fp_far_from_hull']:6.3f} "
              f"{row['fp_dark']:6.3f} {row['fp_bright']:6.3f} {walls:6.3f} | {row['unseen']:6.3f} "
              f"{row['hit_bg_unseen']:6.3f} {row['fp_unseen']:6.3f}", flush=True)
        if args.figures:
            fig = (img * 0.5).astype(np.uint8)
            fig[miss] = (0, 255, 0)
            fig[hit_bg] = (0, 128, 0)
            fig[fp] = (255, 0, 0)
            hole_big = cv2.resize(((opa < 0.5) & tf_s).reshape(small.height, small.width).astype(np.uint8),
                                  (tf.shape[1], tf.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
            fig[hole_big & ~miss] = (0, 0, 255)
            cv2.imwrite(str(args.figures / f"{name}.png"), cv2.cvtColor(fig, cv2.COLOR_RGB2BGR))
    keys = [k for k in rows[0] if k not in ("view", "annotated")]
    scored = [r for r in rows if not r["annotated"]] or rows
    mean = {k: float(np.mean([r[k] for r in scored])) for k in keys}
    print("mean (unannotated views): " + ", ".join(f"{k} {v:.3f}" for k, v in mean.items()))
    (args.json or args.out / "diagnose.json").write_text(json.dumps({"views": rows, "mean": mean, "hull_share": float(hull.mean())},
                                                       indent=1))


if __name__ == "__main__":
    main()
