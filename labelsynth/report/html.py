"""report.html: the annotator's review screen, one self-contained page that opens offline.

Reports get mailed around and opened on clinic machines without network access, so the page
references nothing outside itself: its CSS, its few lines of script and every picture are
inline (data URIs), and no link leaves it. What it shows, top to bottom: which frames are
flagged (and, after ``relabel``, which input masks changed and how far the labels moved); the
review gallery, every frame as a thumbnail with the field's mask over it, flagged frames
first, then by agreement, worst first (``gallery.review_order``); a click opens the frame
large with its input mask, the field's mask and their difference side by side; then the
summary, the table of frames, the plots and the labelled surface.

The large views work without the script too (each is the target of its thumbnail's
``#v-N`` link, shown by CSS ``:target``); the script only keeps the page where it was when a
view closes and adds the keys Esc, left and right.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Mapping, Sequence

from ..classes import WOUND_BED
from .gallery import FrameView

CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px}h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ddd;padding-bottom:4px}h3{font-size:14px}
nav a{margin-right:14px;font-size:13px}
table{border-collapse:collapse;font-size:13px;margin:8px 0}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right}
th{background:#f3f3f3}td.l,th.l,td.t{text-align:left}
tr.flag td{background:#fde2e2}
.fig{max-width:100%;height:auto;border:1px solid #eee;margin:6px 0}
.muted{color:#777;font-size:12px}
.ok{color:#1a7f37}.bad{color:#c62828;font-weight:bold}
.legend span{display:inline-block;margin-right:12px;font-size:12px}
.legend i{display:inline-block;width:12px;height:12px;margin-right:4px;vertical-align:-2px;border:1px solid #999}
.gallery{display:grid;grid-template-columns:repeat(auto-fill,minmax(180px,1fr));gap:10px}
.thumb{display:block;border:2px solid #ddd;border-radius:4px;padding:3px;text-decoration:none;color:#222;background:#fff}
.thumb:hover{border-color:#555}.thumb.flag{border-color:#c62828;background:#fde2e2}
.thumb img{display:block;width:100%;height:auto}
.thumb .cap{display:block;font-size:11px;line-height:1.35;margin-top:3px;word-break:break-all}
.view{display:none;position:fixed;inset:0;background:#1b1b1b;color:#eee;overflow:auto;z-index:10;padding:16px 24px}
.view:target,.view.open{display:block}
.view h3{margin:4px 0 6px;font-size:17px}.view a{color:#9cf}
.view .bar{display:flex;gap:18px;align-items:baseline;flex-wrap:wrap;font-size:13px}
.panels{display:grid;grid-template-columns:repeat(auto-fit,minmax(320px,1fr));gap:12px;margin-top:10px}
.panel{margin:0}.panel figcaption{font-size:13px;margin-bottom:3px}.panel small{color:#aaa}
.pic{position:relative;background-size:100% 100%;background-repeat:no-repeat}
.pic img{display:block;width:100%;height:auto}
.pic:hover img{opacity:0}
"""

SCRIPT = """
(function(){
  var views=[].slice.call(document.querySelectorAll('.view')),cur=-1,y=0;
  function show(i){views.forEach(function(v,k){v.classList.toggle('open',k===i);});cur=i;}
  function open(i){if(cur<0){y=window.scrollY;}show(i);}
  function close(){show(-1);if(location.hash.indexOf('#v-')===0){history.replaceState(null,'',location.pathname+location.search);}window.scrollTo(0,y);}
  document.querySelectorAll('a[data-view]').forEach(function(a){a.addEventListener('click',function(e){e.preventDefault();open(+a.dataset.view);});});
  document.querySelectorAll('a[data-close]').forEach(function(a){a.addEventListener('click',function(e){e.preventDefault();close();});});
  document.addEventListener('keydown',function(e){
    if(cur<0){return;}
    if(e.key==='Escape'){close();}
    else if(e.key==='ArrowRight'){show((cur+1)%views.length);}
    else if(e.key==='ArrowLeft'){show((cur+views.length-1)%views.length);}
  });
})();
"""


def data_uri(data: bytes, mime: str = "image/png") -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def img_tag(png: bytes, alt: str, cls: str = "fig") -> str:
    """An <img> with the PNG embedded as a data URI."""
    return f'<img class="{cls}" alt="{html.escape(alt)}" src="{data_uri(png)}">'


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}"
    return html.escape(str(v))


def _pct(v: float | None) -> str:
    return "–" if v is None else f"{v:.1%}"


def _table(header: Sequence[str], rows: Sequence[Sequence], left: int = 1, row_classes: Sequence[str] | None = None,
           raw_first: bool = False) -> str:
    head = "".join(f'<th class="l">{html.escape(h)}</th>' if i < left else f"<th>{html.escape(h)}</th>" for i, h in enumerate(header))
    body = []
    for r, row in enumerate(rows):
        cls = f' class="{row_classes[r]}"' if row_classes and row_classes[r] else ""
        cells = []
        for i, v in enumerate(row):
            text = v if (raw_first and i == 0) else _fmt(v)
            cells.append(f'<td class="l">{text}</td>' if i < left else
                         f'<td class="t">{text}</td>' if isinstance(v, str) and i == len(row) - 1 else f"<td>{text}</td>")
        body.append(f"<tr{cls}>{''.join(cells)}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _changed_text(f: Mapping, pixels: int | None) -> str:
    n = f.get("pixels_changed")
    if n is None:
        return ""
    share = f" ({100.0 * n / pixels:.1f}%)" if pixels else ""
    return f"{n} px changed{share}"


def _legend(classes: Sequence[Mapping]) -> str:
    items = "".join(f'<span><i style="background:rgb({",".join(str(int(v)) for v in c["color"])})"></i>'
                    f'{html.escape(str(c["name"]))}</span>' for c in classes)
    return f'<p class="legend">{items}</p>'


def _gallery(frames: Sequence[Mapping], views: Sequence[FrameView], number: Mapping[str, int]) -> list[str]:
    """The thumbnails (in the views' order) and one large view per frame."""
    by_name = {f["name"]: f for f in frames}
    parts = ['<div class="gallery" id="gallery">']
    for k, v in enumerate(views):
        f = by_name[v.name]
        bits = [html.escape(v.name)]
        score = (f.get("loo_dice") or {}).get(WOUND_BED)
        if score is not None:
            bits.append(f"LOO Dice {score:.3f}")
        elif (f.get("agreement") or {}).get(WOUND_BED) is not None:
            bits.append(f"agreement {f['agreement'][WOUND_BED]:.3f}")
        changed = _changed_text(f, v.pixels)
        if changed:
            bits.append(changed)
        if f.get("flagged"):
            bits.append("<b>flagged</b>")
        cls = "thumb flag" if f.get("flagged") else "thumb"
        parts.append(f'<a class="{cls}" href="#v-{k}" data-view="{k}" data-frame="{html.escape(v.name)}" '
                     f'title="{html.escape(f.get("reason") or v.name)}">'
                     f'<img alt="{html.escape(v.name)}" src="{data_uri(v.thumb, "image/jpeg")}">'
                     f'<span class="cap">{" · ".join(bits)}</span></a>')
    parts.append("</div>")
    # each frame's pixels once, as a CSS background every panel of its view shares
    backgrounds = "".join(f'.bg{k}{{background-image:url("{data_uri(v.frame, "image/jpeg")}")}}'
                          for k, v in enumerate(views))
    parts.append(f"<style>{backgrounds}</style>")
    n = len(views)
    for k, v in enumerate(views):
        f = by_name[v.name]
        status = (f'<span class="bad">flagged: {html.escape(f.get("reason", ""))}</span>' if f.get("flagged")
                  else f'<span>{html.escape(", ".join(f.get("sources") or []) or "no input mask")}</span>')
        changed = _changed_text(f, v.pixels)
        panels = [f'<figure class="panel"><figcaption>frame</figcaption>'
                  f'<div class="pic bg{k}" style="aspect-ratio:{v.width}/{v.height}"></div></figure>']
        for p in v.panels:
            note = f" <small>{html.escape(p.note)}</small>" if p.note else ""
            panels.append(f'<figure class="panel"><figcaption>{html.escape(p.title)}{note}</figcaption>'
                          f'<div class="pic bg{k}"><img alt="{html.escape(p.title)}" src="{data_uri(p.png)}" '
                          f'width="{v.width}" height="{v.height}"></div></figure>')
        parts.append(
            f'<div class="view" id="v-{k}" role="dialog" aria-label="{html.escape(v.name)}" data-frame="{html.escape(v.name)}">'
            f'<div class="bar"><h3>{html.escape(v.name)}</h3>{status}'
            + (f"<span>{changed} since the previous run</span>" if changed else "")
            + f'<span>frame {number[v.name] + 1} of {len(frames)}</span>'
            f'<a href="#v-{(k + n - 1) % n}" data-view="{(k + n - 1) % n}">‹ previous</a>'
            f'<a href="#v-{(k + 1) % n}" data-view="{(k + 1) % n}">next ›</a>'
            f'<a href="#review" data-close="1">close (Esc)</a>'
            f'<span class="muted">hover a picture to see the frame without the mask</span></div>'
            f'<div class="panels">{"".join(panels)}</div></div>'
        )
    return parts


def render_html(report: Mapping, figures: Mapping[str, bytes], views: Sequence[FrameView] = (),
                classes: Sequence[Mapping] = ()) -> str:
    """The whole page from report.json's content, the PNG figures and the frames' views
    (``gallery.frame_view``, in review order); ``classes``: the class table's rows (id, name,
    color) for the legend."""
    s = report["summary"]
    frames = report["frames"]
    keys = s.get("keys", [WOUND_BED])
    number = {f["name"]: i for i, f in enumerate(frames)}
    view_of = {v.name: k for k, v in enumerate(views)}
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
        parts.append(f'<p class="bad" id="flagged">{len(flagged)} frame(s) flagged: {html.escape(", ".join(flagged))}</p>')
    else:
        parts.append('<p class="ok" id="flagged">No input mask disagrees clearly more than the others.</p>')
    relabel = s.get("relabel")
    if relabel is not None:
        moved = [f for f in frames if f.get("pixels_changed")]
        changed = relabel.get("masks_changed") or []
        parts.append(
            f'<p id="relabel">Relabelled (relabel {relabel.get("relabels", 1)} on this geometry): '
            f'{len(changed)} input mask(s) changed since the previous run'
            + (f" ({html.escape(', '.join(changed))})" if changed else "")
            + f"; the labels of {len(moved)} of {len(frames)} frames moved, "
            f"{sum(int(f['pixels_changed']) for f in moved)} pixels in all (per frame below).</p>")
    parts.append('<nav><a href="#review">Review</a><a href="#summary">Summary</a><a href="#frames">Frames</a>'
                 '<a href="#plots">Plots</a><a href="#surface">Labelled surface</a></nav>')

    # the review gallery
    if views:
        parts.append('<h2 id="review">Review: every frame, flagged first</h2>')
        parts.append('<p class="muted">The field\'s mask over each frame; flagged frames first, then by how well '
                     "the input mask agrees with the field (worst first). Click a frame for its input mask, the "
                     "field's mask and their difference.</p>")
        if classes:
            parts.append(_legend(classes))
        parts += _gallery(frames, views, number)

    # summary
    parts.append('<h2 id="summary">Summary</h2>')
    rows = []
    for k in keys:
        rows.append([k.replace("_", " "), s.get("median_agreement", {}).get(k), s.get("median_loo_dice", {}).get(k)])
    parts.append(_table(["class", "median agreement Dice", "median leave-one-out Dice"], rows))
    parts.append(f'<p>Mean pairwise wound-bed Dice between labelled views: {_fmt(s.get("mean_pairwise_dice"))}</p>')

    # per frame table
    parts.append('<h2 id="frames">Frames</h2>')
    header = ["frame", "sources", "agreement (wound bed)", "LOO Dice (wound bed)", "unseen surface", "flagged",
              "reason"]
    with_changes = any("pixels_changed" in f for f in frames)
    if with_changes:
        header.insert(4, "pixels changed")
    rows, classes_ = [], []
    for f in frames:
        unseen = f.get("unseen_share")
        name = html.escape(f["name"])
        link = f'<a href="#v-{view_of[f["name"]]}" data-view="{view_of[f["name"]]}">{name}</a>' if f["name"] in view_of else name
        row = [
            link, ", ".join(f["sources"]) or "–",
            f["agreement"].get(WOUND_BED) if f["agreement"] else None,
            f["loo_dice"].get(WOUND_BED) if f.get("loo_dice") else None,
            _pct(unseen),
            "yes" if f["flagged"] else "", f["reason"],
        ]
        if with_changes:
            row.insert(4, f.get("pixels_changed"))
        rows.append(row)
        classes_.append("flag" if f["flagged"] else "")
    parts.append(_table(header, rows, left=2, row_classes=classes_, raw_first=True))
    if s.get("unseen_confidence") is not None:
        parts.append('<p class="muted">Unseen surface: the share of the frame\'s pixels whose surface no frame that '
                     'taught the field saw; their label is the field\'s guess from nearby surface, and their '
                     f'labels.h5 confidence is at most {_fmt(s.get("unseen_confidence"))}. Median over the frames '
                     f'{_pct(s.get("median_unseen_share"))}, largest {_pct(s.get("max_unseen_share"))}.</p>')

    parts.append('<h2 id="plots">Plots</h2>')
    for key, title in (("agreement", "Agreement per frame"), ("pixels_changed", "What the relabel changed"),
                       ("class_area", "Class area over frames"), ("pairwise", "Cross-view consistency")):
        if key in figures:
            parts.append(f"<h3>{title}</h3>{img_tag(figures[key], title)}")

    # mesh areas
    mesh = s.get("mesh")
    parts.append('<h2 id="surface">Labelled surface</h2>')
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

    parts.append('<p class="muted">Made by labelsynth. Agreement: Dice of each input mask against the field\'s '
                 "mask of the same frame. Leave-one-out: the semantic stage refitted without the frame. "
                 "Pairwise: masks carried onto the surface and compared where two views see the same points.</p>")
    parts.append(f"<script>{SCRIPT}</script>")
    parts.append("</body></html>")
    return "\n".join(parts)
