"""``cohort.html``: one row per patient of a cohort's ``cohort.csv`` (thumbnail, error,
confidence, wafer figures, status, link to the patient's ``report.html``), sortable by any column,
failures first. Self-contained: thumbnails are embedded, nothing is fetched."""
from __future__ import annotations

import base64
import csv
import html
from pathlib import Path

COLUMNS = (("patient", "patient"), ("status", "status"), ("error", "problem"), ("design_max_mm", "error vs design mm"),
           ("ambiguous", "ambiguous"), ("interocclusal_mm", "interocclusal mm"), ("regions", "regions in contact"),
           ("error_bound_mm", "ε mm"), ("wafer_ok", "wafer ok"), ("wafer_min_thickness_mm", "wafer thickness mm"),
           ("search_s", "search s"))
THUMBNAILS = ("best.png", "contact_map_maxilla.png", "landscape.png")  # the first a patient has

_SORT = r"""
document.querySelectorAll('th').forEach((th, c) => th.onclick = () => {
  const tb = th.closest('table').tBodies[0], rows = [...tb.rows], up = th.dataset.dir !== 'up';
  const key = r => {const t = r.cells[c].textContent.trim(); const x = parseFloat(t); return isNaN(x) ? t : x;};
  rows.sort((a, b) => {const p = key(a), q = key(b); return (p > q ? 1 : p < q ? -1 : 0) * (up ? 1 : -1);});
  th.dataset.dir = up ? 'up' : 'down'; rows.forEach(r => tb.appendChild(r));});
"""


def _thumb(folder: Path) -> str:
    for name in THUMBNAILS:
        p = folder / name
        if p.exists():
            return f"<img alt='{name}' src='data:image/png;base64,{base64.b64encode(p.read_bytes()).decode()}' width='160'>"
    return ""


def write_cohort(out_dir) -> Path:
    """Write ``cohort.html`` beside ``out_dir/cohort.csv``; return its path."""
    out_dir = Path(out_dir)
    src = out_dir / "cohort.csv"
    if not src.exists():
        raise FileNotFoundError(f"{src} does not exist: give the output folder of mjist cohort")
    with open(src, newline="") as fh:
        rows = list(csv.DictReader(fh))
    rows.sort(key=lambda r: (r.get("status") == "ok", r.get("patient", "")))  # failures first
    body = []
    for r in rows:
        folder = out_dir / "patients" / r["patient"]
        link = folder / "report.html"
        name = html.escape(r["patient"])
        cells = [f"<a href='patients/{name}/report.html'>{name}</a>" if link.exists() else name]
        cells += [html.escape(r.get(k, "")) for k, _ in COLUMNS[1:]]
        cls = "" if r.get("status") == "ok" else " class='failed'"
        body.append(f"<tr{cls}><td>{_thumb(folder)}</td>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    failed = sum(r.get("status") != "ok" for r in rows)
    head = "<th>picture</th>" + "".join(f"<th>{html.escape(h)}</th>" for _, h in COLUMNS)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Cohort {html.escape(out_dir.name)}</title>
<meta http-equiv="Content-Security-Policy" content="default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; img-src data:">
<style>body{{font-family:system-ui,sans-serif;margin:18px}} table{{border-collapse:collapse;font-size:13px}}
td,th{{border:1px solid #ccc;padding:4px 8px;vertical-align:middle}} th{{background:#eef1f5;cursor:pointer}}
tr.failed td{{background:#fbe9e9}}</style></head>
<body><h1>Cohort {html.escape(out_dir.name)}</h1>
<p>{len(rows)} patient(s), {failed} failed (listed first). Click a column to sort; a patient's name opens its 3D report.</p>
<table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>
<script>{_SORT}</script></body></html>
"""
    path = out_dir / "cohort.html"
    path.write_text(page, encoding="utf-8")
    return path
