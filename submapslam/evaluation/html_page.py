"""The building blocks of the HTML reports: one self-contained page (inline PNG figures,
inline CSS and a few lines of plain JavaScript for sortable, filterable tables), nothing
fetched at view time.

Figures are matplotlib PNGs embedded as ``data:`` URIs: a page of a dozen figures stays around
a megabyte, opens offline in any browser, prints, and looks the same in a screenshot as on
screen; a bundled plotting library (plotly.js alone is ~4.6 MB) would cost more than the
figures and still need the map as an image.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Iterable, Sequence

GENERATOR = "submapslam report"
"""Content of the page's ``<meta name="generator">``: marks a file the report commands may replace."""

_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1280px;padding:0 18px 40px;color:#222}
h1{font-size:1.5em;margin:18px 0 4px}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:3px;margin-top:28px}
.sub{color:#666;margin:0 0 10px}
.figs{display:flex;flex-wrap:wrap;gap:12px}.figs figure{margin:0;flex:1 1 480px}
figure img{max-width:100%;height:auto;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
table{border-collapse:collapse;font-size:.86em;margin:6px 0}th,td{border:1px solid #ddd;padding:3px 7px;text-align:right}
th{background:#f2f2f2;cursor:pointer;user-select:none}td.t,th.t{text-align:left}
tr.ok td:first-child{border-left:4px solid #2a2}tr.no td:first-child{border-left:4px solid #d22}
.kv td:first-child{text-align:left;color:#555}.kv td{text-align:left}
pre{background:#f7f7f7;border:1px solid #ddd;padding:8px;font-size:.8em;max-height:420px;overflow:auto}
.filters{margin:8px 0;font-size:.9em}.filters input{width:220px}.count{color:#555;margin-left:8px}
.note{color:#a60}.layers{margin:8px 0;font-size:.9em}.layers label{margin-right:14px}
"""

_JS = """
function sortTable(th){const t=th.closest('table'),b=t.tBodies[0],k=th.cellIndex,
 asc=th.dataset.dir!=='asc';th.dataset.dir=asc?'asc':'desc';
 const rows=[...b.rows];const v=r=>{const s=r.cells[k].dataset.v??r.cells[k].textContent;const n=parseFloat(s);return isNaN(n)?s:n};
 rows.sort((a,c)=>{const x=v(a),y=v(c);return (x<y?-1:x>y?1:0)*(asc?1:-1)});rows.forEach(r=>b.appendChild(r))}
let loopPage=0;const LOOP_PAGE=50;
function filterLoops(keepPage){if(keepPage!==true)loopPage=0;const q=document.getElementById('lq').value.toLowerCase(),
 st=document.getElementById('ls').value,src=document.getElementById('lsrc').value;const hit=[];
 for(const r of document.querySelectorAll('#loops tbody tr')){const ok=(st==='all'||r.dataset.accepted===st)&&
 (src==='all'||r.dataset.source===src)&&r.textContent.toLowerCase().includes(q);r.style.display='none';if(ok)hit.push(r)}
 const pages=Math.max(1,Math.ceil(hit.length/LOOP_PAGE));loopPage=Math.min(Math.max(loopPage,0),pages-1);
 hit.slice(loopPage*LOOP_PAGE,(loopPage+1)*LOOP_PAGE).forEach(r=>r.style.display='');
 document.getElementById('lcount').textContent=hit.length+' shown';const p=document.getElementById('lpage');
 if(p)p.textContent=pages>1?'page '+(loopPage+1)+' of '+pages+' ('+LOOP_PAGE+' rows each)':''}
function loopPageStep(d){loopPage+=d;filterLoops(true)}
document.addEventListener('DOMContentLoaded',()=>{for(const th of document.querySelectorAll('table.sortable th'))
 th.addEventListener('click',()=>{sortTable(th);if(th.closest('#loops'))filterLoops(true)});
 if(document.getElementById('lq'))filterLoops()});
"""


def esc(value: object) -> str:
    """HTML-escaped text of ``value``."""
    return html.escape(str(value))


def png_data_uri(fig, dpi: int = 100) -> str:
    """A matplotlib figure as a ``data:image/png;base64`` URI (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def figure(uri: str, caption: str, ident: str = "") -> str:
    """An ``<img>`` with its caption; ``ident`` becomes the image's id."""
    id_attr = f' id="{esc(ident)}"' if ident else ""
    return f'<figure><img{id_attr} src="{uri}" alt="{esc(caption)}"><figcaption>{esc(caption)}</figcaption></figure>'


def layered_figure(layers: Sequence[tuple[str, str, str, bool]], caption: str) -> str:
    """Images of the same size stacked on the first (``layers``: ``(key, label, data URI, shown)``),
    each after the first with a checkbox that shows or hides it; the first image's id is its key."""
    boxes, imgs = [], []
    for k, (key, label, uri, shown) in enumerate(layers):
        ident = esc(key if k == 0 else f"layer-{key}")
        if k == 0:
            imgs.append(f'<img id="{ident}" src="{uri}" alt="{esc(caption)}" style="width:100%;display:block">')
            continue
        style = "position:absolute;left:0;top:0;width:100%;border-color:transparent" + ("" if shown else ";display:none")
        imgs.append(f'<img id="{ident}" src="{uri}" alt="{esc(label)}" style="{style}">')
        boxes.append(f'<label><input type="checkbox" {"checked " if shown else ""}'
                     f"onchange=\"document.getElementById('{ident}').style.display=this.checked?'':'none'\"> "
                     f"{esc(label)}</label>")
    return (f'<div class="layers">{" ".join(boxes)}</div><figure><div style="position:relative">{"".join(imgs)}'
            f"</div><figcaption>{esc(caption)}</figcaption></figure>")


def fmt(value: object, digits: int = 4) -> str:
    """Numbers to ``digits`` significant digits, NaN/None as a dash, anything else as text."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return "–" if value != value else f"{value:.{digits}g}"
    return str(value)


def table(header: Sequence[str], rows: Iterable[Sequence[object]], *, ident: str = "", sortable: bool = True,
          text_columns: Sequence[int] = (0,), row_attrs: Iterable[str] | None = None) -> str:
    """A table; ``sortable`` adds click-to-sort headers, ``text_columns`` are left-aligned,
    ``row_attrs`` (one string per row) go into each ``<tr>``."""
    cls = ' class="sortable"' if sortable else ""
    id_attr = f' id="{esc(ident)}"' if ident else ""
    head = "".join(f'<th class="t">{esc(h)}</th>' if k in text_columns else f"<th>{esc(h)}</th>"
                   for k, h in enumerate(header))
    attrs = iter(row_attrs) if row_attrs is not None else None
    body = []
    for row in rows:
        cells = "".join(f'<td class="t">{esc(fmt(v))}</td>' if k in text_columns else f"<td>{esc(fmt(v))}</td>"
                        for k, v in enumerate(row))
        body.append(f"<tr {next(attrs) if attrs else ''}>{cells}</tr>")
    return f"<table{id_attr}{cls}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def key_values(pairs: Iterable[tuple[str, object]]) -> str:
    """A two-column table of names and values."""
    rows = "".join(f"<tr><td>{esc(k)}</td><td>{esc(fmt(v))}</td></tr>" for k, v in pairs)
    return f'<table class="kv"><tbody>{rows}</tbody></table>'


def page(title: str, subtitle: str, sections: Iterable[tuple[str, str]]) -> str:
    """The whole document: ``sections`` are ``(heading, inner HTML)``."""
    body = "".join(f"<section><h2>{esc(h)}</h2>{inner}</section>" for h, inner in sections)
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
            f'<meta name="generator" content="{GENERATOR}"><title>{esc(title)}</title>'
            f"<style>{_CSS}</style><script>{_JS}</script></head><body>"
            f'<h1>{esc(title)}</h1><p class="sub">{esc(subtitle)}</p>{body}</body></html>\n')


def is_report(head: bytes) -> bool:
    """Whether a file starting with ``head`` (its first kilobyte or so) is a page this module wrote."""
    return f'content="{GENERATOR}"'.encode() in head


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values covering ``[lo, hi]``."""
    import math

    span = max(hi - lo, 1e-12)
    raw = span / n
    step = 10 ** math.floor(math.log10(raw))
    for m in (1, 2, 2.5, 5, 10):
        if raw <= m * step:
            step *= m
            break
    first = math.ceil(lo / step) * step
    return [first + k * step for k in range(int((hi - first) / step + 1e-9) + 1)]


def svg_line_chart(x: Sequence[float], y: Sequence[float], *, xlabel: str, ylabel: str, color: str = "#d65f00",
                   step: bool = False, hline: float | None = None, width: int = 440, height: int = 260) -> str:
    """A small line chart as inline SVG (no plotting library): axes with round ticks, the line
    (``step``: held until the next x), an optional dashed horizontal line (e.g. a peak)."""
    import numpy as np

    X, Y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    left, right, top, bottom = 58, 12, 10, 42
    w, h = width - left - right, height - top - bottom
    x0, x1 = float(X.min()), float(X.max()) if X.max() > X.min() else float(X.min()) + 1.0
    y_hi = max(float(Y.max()), hline or -np.inf)
    y0, y1 = min(0.0, float(Y.min())), y_hi * 1.05 if y_hi > 0 else 1.0

    def px(v):
        return left + (v - x0) / (x1 - x0) * w

    def py(v):
        return top + h - (v - y0) / (y1 - y0) * h

    if step and len(X) > 1:
        pts = [(X[0], Y[0])]
        for k in range(1, len(X)):
            pts += [(X[k], Y[k - 1]), (X[k], Y[k])]
    else:
        pts = list(zip(X, Y))
    line = " ".join(f"{px(a):.1f},{py(b):.1f}" for a, b in pts)
    parts = [f'<svg width="{width}" height="{height}" font-size="11" '
             f'font-family="sans-serif"><rect x="{left}" y="{top}" width="{w}" height="{h}" fill="none" stroke="#444"/>']
    for t in _ticks(x0, x1):
        parts.append(f'<line x1="{px(t):.1f}" x2="{px(t):.1f}" y1="{top + h}" y2="{top + h + 4}" stroke="#444"/>'
                     f'<text x="{px(t):.1f}" y="{top + h + 16}" text-anchor="middle">{t:g}</text>')
    for t in _ticks(y0, y1):
        parts.append(f'<line x1="{left}" x2="{left + w}" y1="{py(t):.1f}" y2="{py(t):.1f}" stroke="#e4e4e4"/>'
                     f'<text x="{left - 6}" y="{py(t) + 4:.1f}" text-anchor="end">{t:g}</text>')
    if hline is not None:
        parts.append(f'<line x1="{left}" x2="{left + w}" y1="{py(hline):.1f}" y2="{py(hline):.1f}" stroke="#777" '
                     f'stroke-dasharray="5,3"/><text x="{left + w - 4}" y="{py(hline) - 4:.1f}" text-anchor="end">'
                     f"peak {hline:g}</text>")
    parts.append(f'<polyline points="{line}" fill="none" stroke="{color}" stroke-width="1.5"/>')
    parts.append(f'<text x="{left + w / 2}" y="{height - 6}" text-anchor="middle">{esc(xlabel)}</text>'
                 f'<text transform="translate(14,{top + h / 2}) rotate(-90)" text-anchor="middle">{esc(ylabel)}</text>')
    return "".join(parts) + "</svg>"


def bar_rows(items: Sequence[tuple[str, float]], unit: str) -> str:
    """A table of names and values with a CSS bar proportional to each value (no image)."""
    top = max((v for _, v in items), default=0.0) or 1.0
    rows = "".join(f'<tr><td class="t">{esc(k)}</td><td>{v:.3g}</td><td class="t" style="width:320px">'
                   f'<div style="background:#4878cf;height:11px;width:{100 * v / top:.1f}%"></div></td></tr>'
                   for k, v in items)
    return (f'<table class="sortable"><thead><tr><th class="t">stage</th><th>{esc(unit)}</th><th class="t"></th>'
            f"</tr></thead><tbody>{rows}</tbody></table>")
