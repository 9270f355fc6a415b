"""The batch's result table: one row per capture, printed with rich and written as
``OUT/batch.json`` and a self-contained ``OUT/batch.html`` (inline style, no scripts, no links
out), so the outcome of a long batch can be read, mailed or archived without labelsynth."""

from __future__ import annotations

import html
import json
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from rich.table import Table

from .. import __version__
from ..classes import WOUND_BED
from ..errors import LabelsynthError
from ..outdir import write_text_atomic
from ..rundir import RunFolder

BATCH_JSON = "batch.json"
BATCH_HTML = "batch.html"
STATUSES = ("done", "skipped", "failed")


@dataclass
class BatchRow:
    """One capture's outcome. ``seconds``: this run's expand (for ``skipped``: the earlier run's,
    from its run.json). Quality columns come from the capture's report.json when it ran."""

    name: str
    capture: str
    status: str
    reason: str = ""
    seconds: float | None = None
    output: str = ""
    frames: int | None = None
    wound_bed_agreement: float | None = None
    wound_bed_loo_dice: float | None = None
    flagged: list[str] = field(default_factory=list)
    attempts: int | None = None

    def line(self) -> str:
        """The line printed when the capture lands."""
        t = "" if self.seconds is None else f" in {self.seconds:.0f} s"
        if self.status == "failed":
            return f"{self.name}: failed{t}: {self.reason}"
        extra = []
        if self.wound_bed_agreement is not None:
            extra.append(f"wound-bed agreement {self.wound_bed_agreement:.3f}")
        if self.flagged:
            extra.append(f"{len(self.flagged)} flagged")
        tail = f" ({', '.join(extra)})" if extra else ""
        if self.status == "skipped":
            took = "" if self.seconds is None else f"; its run took {self.seconds:.0f} s"
            return f"{self.name}: skipped, unchanged since the last run{took}{tail}"
        return f"{self.name}: {self.status}{t}{tail}"


def read_quality(output: Path, row: BatchRow) -> None:
    """Fill frames, time, wound-bed agreement / leave-one-out Dice and flagged frames from a
    finished output's run.json and report.json (absent with --no-report: left empty)."""
    run = RunFolder(output)
    if row.seconds is None:
        try:
            row.seconds = run.read_run().total_seconds
        except LabelsynthError:
            pass
    summary = run.read_report_summary()
    if not summary:
        return
    row.frames = summary.get("num_frames", row.frames)
    row.wound_bed_agreement = (summary.get("median_agreement") or {}).get(WOUND_BED)
    row.wound_bed_loo_dice = (summary.get("median_loo_dice") or {}).get(WOUND_BED)
    row.flagged = list(summary.get("flagged") or [])


def counts(rows: list[BatchRow]) -> dict[str, int]:
    return {s: sum(r.status == s for r in rows) for s in STATUSES}


def _fmt(v: float | None, spec: str = ".3f") -> str:
    return "–" if v is None else format(v, spec)


def _cells(r: BatchRow) -> list[str]:
    flagged = ", ".join(r.flagged) if r.flagged else ("–" if r.wound_bed_agreement is None else "none")
    return [r.name, r.status, r.reason or "", _fmt(r.seconds, ".0f"), _fmt(r.wound_bed_agreement),
            _fmt(r.wound_bed_loo_dice), flagged]


HEADERS = ["capture", "status", "reason", "time (s)", "wound-bed agreement", "wound-bed LOO Dice", "flagged frames"]


def rich_table(rows: list[BatchRow]) -> Table:
    """The table as rich renders it in a terminal."""
    c = counts(rows)
    table = Table(title=f"labelsynth batch: {c['done']} done, {c['skipped']} skipped, {c['failed']} failed")
    for h in HEADERS:
        table.add_column(h, overflow="fold", justify="right" if h.startswith(("time", "wound")) else "left")
    colour = {"done": "green", "skipped": "cyan", "failed": "bold red"}
    for r in rows:
        cells = _cells(r)
        cells[1] = f"[{colour[r.status]}]{r.status}[/]"
        table.add_row(*cells)
    return table


def write_batch_json(out: Path, rows: list[BatchRow], info: dict[str, Any]) -> Path:
    """OUT/batch.json: every row plus what the batch was run with."""
    doc = {"version": __version__, "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           **info, "counts": counts(rows), "captures": [asdict(r) for r in rows]}
    return write_text_atomic(Path(out) / BATCH_JSON, json.dumps(doc, indent=2, default=str))


_STYLE = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse}th,td{border:1px solid #ccc;padding:4px 8px;text-align:left;vertical-align:top}
th{background:#f2f2f2}td.num{text-align:right;font-variant-numeric:tabular-nums}
tr.failed td{background:#fde8e8}tr.skipped td{color:#555}.meta{color:#555;font-size:90%}
"""


def write_batch_html(out: Path, rows: list[BatchRow], info: dict[str, Any]) -> Path:
    """OUT/batch.html: the same table, one file with its style inline."""
    c = counts(rows)
    head = "".join(f"<th>{html.escape(h)}</th>" for h in HEADERS)
    body = []
    for r in rows:
        cells = _cells(r)
        tds = "".join(
            f'<td class="num">{html.escape(v)}</td>' if i >= 3 and i <= 5 else f"<td>{html.escape(v)}</td>"
            for i, v in enumerate(cells)
        )
        body.append(f'<tr class="{r.status}">{tds}</tr>')
    meta = "; ".join(f"{html.escape(str(k))}: {html.escape(str(v))}" for k, v in info.items())
    text = (
        "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>labelsynth batch</title>"
        f"<style>{_STYLE}</style></head><body>\n"
        f"<h1>labelsynth batch</h1><p>{c['done']} done, {c['skipped']} skipped, {c['failed']} failed "
        f"({len(rows)} captures)</p>\n<p class=\"meta\">{meta}</p>\n"
        f"<table><thead><tr>{head}</tr></thead><tbody>\n" + "\n".join(body) + "\n</tbody></table>\n"
        f"<p class=\"meta\">labelsynth {html.escape(__version__)}</p></body></html>\n"
    )
    return write_text_atomic(Path(out) / BATCH_HTML, text)
