"""report.html: one self-contained page (inline CSS, base64 PNGs) that opens offline.

Reports get mailed around and opened on clinic machines without network access, so the
page references nothing outside itself: no scripts, fonts, stylesheets or remote images.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence

from ..classes import WOUND_BED

CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ddd;padding-bottom:4px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}
tr.flag td{background:#fde2e2}
img{max-width:100%;height:auto;border:1px solid #eee;margin:6px 0}
.muted{color:#777;font-size:12px}
.ok{color:#1a7f37}.bad{color:#c62828;font-weight:bold}
"""


def img_tag(png: bytes, alt: str) -> str:
    """An <img> with the PNG embedded as a data URI."""
    data = base64.b64encode(png).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}"
    return html.escape(str(v))


def _pct(v: float | None) -> str:
    return "–" if v is None else f"{v:.1%}"


def _table(header: Sequence[str], rows: Sequence[Sequence], left: int = 1, row_classes: Sequence[str] | None = None) -> str:
    head = "".join(f'<th class="l">{html.escape(h)}</th>' if i < left else f"<th>{html.escape(h)}</th>" for i, h in enumerate(header))
    body = []
    for r, row in enumerate(rows):
        cls = f' class="{row_classes[r]}"' if row_classes and row_classes[r] else ""
        cells = "".join(f'<td class="l">{_fmt(v)}</td>' if i < left else f"<td>{_fmt(v)}</td>" for i, v in enumerate(row))
        body.append(f"<tr{cls}>{cells}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def render_html(report: Mapping, figures: Mapping[str, bytes], strips: Mapping[str, bytes]) -> str:
    """The whole page from report.json's content and the PNG figures."""
    s = report["summary"]
    frames = report["frames"]
    keys = s.get("keys", [WOUND_BED])
    parts = [
        "<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">",
        "<title>labelsynth consistency report</title>",
        f"<style>{CSS}</style></head><body>",
        "<h1>labelsynth consistency report</h1>",
        f'<p class="muted">capture: {html.escape(str(s.get("capture", "")))} · labels: {html.escape(str(s.get("labels", "")))}'
        f' · {s.get("num_frames", len(frames))} frames, {s.get("num_annotated", 0)} annotated</p>',
    ]
    flagged = s.get("flagged", [])
    if flagged:
        parts.append(f'<p class="bad">{len(flagged)} frame(s) flagged: {html.escape(", ".join(flagged))}</p>')
    else:
        parts.append('<p class="ok">No input mask disagrees clearly more than the others.</p>')

    # summary
    parts.append("<h2>Summary</h2>")
    rows = []
    for k in keys:
        rows.append([k.replace("_", " "), s.get("median_agreement", {}).get(k), s.get("median_loo_dice", {}).get(k)])
    parts.append(_table(["class", "median agreement Dice", "median leave-one-out Dice"], rows))
    parts.append(f'<p>Mean pairwise wound-bed Dice between labelled views: {_fmt(s.get("mean_pairwise_dice"))}</p>')

    # per frame table
    parts.append("<h2>Frames</h2>")
    header = ["frame", "sources", "agreement (wound bed)", "LOO Dice (wound bed)", "unseen surface", "flagged",
              "reason"]
    rows, classes_ = [], []
    for f in frames:
        unseen = f.get("unseen_share")
        rows.append([
            f["name"], ", ".join(f["sources"]) or "–",
            f["agreement"].get(WOUND_BED) if f["agreement"] else None,
            f["loo_dice"].get(WOUND_BED) if f.get("loo_dice") else None,
            _pct(unseen),
            "yes" if f["flagged"] else "", f["reason"],
        ])
        classes_.append("flag" if f["flagged"] else "")
    parts.append(_table(header, rows, left=2, row_classes=classes_))
    if s.get("unseen_confidence") is not None:
        parts.append('<p class="muted">Unseen surface: the share of the frame\'s pixels whose surface no frame that '
                     'taught the field saw; their label is the field\'s guess from nearby surface, and their '
                     f'labels.h5 confidence is at most {_fmt(s.get("unseen_confidence"))}. Median over the frames '
                     f'{_pct(s.get("median_unseen_share"))}, largest {_pct(s.get("max_unseen_share"))}.</p>')

    for key, title in (("agreement", "Agreement per frame"), ("class_area", "Class area over frames"),
                       ("pairwise", "Cross-view consistency")):
        if key in figures:
            parts.append(f"<h2>{title}</h2>{img_tag(figures[key], title)}")

    # mesh areas
    mesh = s.get("mesh")
    parts.append("<h2>Labelled surface</h2>")
    if mesh:
        areas = mesh["areas"]
        mm = areas.get("by_class_mm2")
        header = ["class", "area (scene units²)"] + (["area (mm²)"] if mm else [])
        rows = []
        for name, a in areas["by_class"].items():
            rows.append([name, a] + ([mm[name]] if mm else []))
        rows.append(["wound bed", areas["wound_bed"]] + ([areas.get("wound_bed_mm2")] if mm else []))
        rows.append(["total", areas["total"]] + ([areas.get("total_mm2")] if mm else []))
        parts.append(_table(header, rows))
        parts.append(f'<p class="muted">{html.escape(", ".join(mesh["files"]))}: {mesh["vertices"]} vertices, '
                     f'{mesh["faces"]} faces; {html.escape(areas["rule"])}.'
                     + ("" if mm else " Pass --mm-per-unit for areas in mm².") + "</p>")
    else:
        parts.append('<p class="muted">No mesh was exported.</p>')

    # flagged frames
    if strips:
        parts.append("<h2>Flagged frames</h2>")
        for name, png in strips.items():
            parts.append(f"<h3>{html.escape(name)}</h3>{img_tag(png, name)}")
    parts.append('<p class="muted">Made by labelsynth. Agreement: Dice of each input mask against the field\'s '
                 "mask of the same frame. Leave-one-out: the semantic stage refitted without the frame. "
                 "Pairwise: masks carried onto the surface and compared where two views see the same points.</p>")
    parts.append("</body></html>")
    return "\n".join(parts)
