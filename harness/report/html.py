"""HTML building blocks for self-contained report pages (the report and the compare page share them).

Every function returns a string of HTML; `page()` wraps a body into one document with the CSS inlined and a
small inline script that checks every image decoded (it sets `data-images-ok` / `data-images-total` on
<body> and fills `#image-check`). Images are inlined as base64 PNG data URIs, so a page opens from disk with
no server and no network; videos are linked by relative path. Text is escaped unless wrapped in `Raw`.
"""

from __future__ import annotations

import base64
import html
import math
from typing import Iterable, Sequence
from urllib.parse import quote

CSS = """
:root { --fg: #1d2329; --muted: #5c6670; --line: #d8dde2; --bg-soft: #f4f6f8; --warn-bg: #fff3cd;
        --warn-line: #d39e00; --danger-bg: #fde2e1; --danger-line: #c0392b; }
* { box-sizing: border-box; }
body { font: 14px/1.45 -apple-system, "Segoe UI", Roboto, "DejaVu Sans", Arial, sans-serif; color: var(--fg);
       margin: 0; background: #fff; }
header.top { padding: 18px 28px 10px; border-bottom: 1px solid var(--line); }
header.top h1 { margin: 0 0 4px; font-size: 22px; }
header.top .sub { color: var(--muted); }
nav.toc { padding: 8px 28px; background: var(--bg-soft); border-bottom: 1px solid var(--line); font-size: 13px; }
nav.toc a { margin-right: 14px; color: #1f5fa8; text-decoration: none; white-space: nowrap; }
main { padding: 6px 28px 40px; max-width: 1400px; }
section { margin: 22px 0 30px; }
section > h2 { font-size: 19px; border-bottom: 2px solid var(--line); padding-bottom: 4px; margin-bottom: 10px; }
section section > h3 { font-size: 16px; margin: 18px 0 8px; }
p.note { color: var(--muted); margin: 4px 0 10px; }
.banner { border: 2px solid var(--warn-line); background: var(--warn-bg); padding: 10px 14px; margin: 12px 0;
          border-radius: 4px; font-weight: 600; }
.banner.danger { border-color: var(--danger-line); background: var(--danger-bg); font-size: 16px; }
table.data { border-collapse: collapse; margin: 6px 0 12px; font-size: 13px; }
table.data th, table.data td { border: 1px solid var(--line); padding: 3px 8px; text-align: left; vertical-align: top; }
table.data th { background: var(--bg-soft); font-weight: 600; }
table.data td.num { text-align: right; font-variant-numeric: tabular-nums; }
table.kv th { width: 190px; }
.absent { color: var(--muted); font-style: italic; }
figure { margin: 8px 0 16px; }
figure img { max-width: 100%; height: auto; border: 1px solid var(--line); }
figcaption { color: var(--muted); font-size: 12.5px; margin-top: 3px; max-width: 1100px; }
.videos { display: flex; flex-wrap: wrap; gap: 12px; }
.videos figure { margin: 0; }
video { max-width: 520px; width: 100%; background: #000; }
details { margin: 6px 0 12px; }
details > summary { cursor: pointer; color: #1f5fa8; }
.swatch { display: inline-block; width: 11px; height: 11px; border-radius: 2px; margin-right: 5px; vertical-align: -1px; }
code { background: var(--bg-soft); padding: 0 3px; border-radius: 3px; }
footer { color: var(--muted); font-size: 12px; padding: 0 28px 20px; }
"""

# Sets data-images-ok / data-images-total on <body> once every <img> has loaded or failed (read by the browser test).
IMAGE_CHECK_SCRIPT = """
(function () {
  function check() {
    var imgs = Array.prototype.slice.call(document.images);
    var pending = imgs.filter(function (i) { return !i.complete; });
    if (pending.length) { setTimeout(check, 50); return; }
    var ok = imgs.filter(function (i) { return i.naturalWidth > 0 && i.naturalHeight > 0; }).length;
    document.body.setAttribute('data-images-total', String(imgs.length));
    document.body.setAttribute('data-images-ok', String(ok));
    var el = document.getElementById('image-check');
    if (el) { el.textContent = ok + ' of ' + imgs.length + ' images decoded'; }
  }
  if (document.readyState === 'complete') { check(); } else { window.addEventListener('load', check); }
})();
"""


class Raw(str):
    """HTML that must not be escaped."""


def esc(value) -> str:
    """Escaped text (Raw passes through)."""
    if isinstance(value, Raw):
        return value
    return html.escape("" if value is None else str(value), quote=True)


def fmt(value, digits: int = 3) -> str:
    """Number for display: significant digits, 'n/a' for None / NaN."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    if isinstance(value, (bool, int)):
        return str(value)
    return f"{float(value):.{digits}g}"


def fmt_ci(value, low, high, digits: int = 3) -> Raw:
    """'v [lo, hi]' with the absent parts shown as n/a."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return absent("n/a")
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return Raw(esc(fmt(value, digits)))
    return Raw(f"{esc(fmt(value, digits))} <span class='absent'>[{esc(fmt(low, digits))}, {esc(fmt(high, digits))}]</span>")


def absent(text: str = "absent") -> Raw:
    return Raw(f"<span class='absent'>{esc(text)}</span>")


def png_data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def image(png: bytes, alt: str, caption: str | None = None, width: int | None = None) -> Raw:
    """A <figure> with the PNG inlined (and an optional caption)."""
    style = f" style='width:{int(width)}px'" if width else ""
    cap = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return Raw(f"<figure><img src='{png_data_uri(png)}' alt='{esc(alt)}'{style}>{cap}</figure>")


def video(relative_src: str, caption: str | None = None) -> Raw:
    """An HTML5 video player for an MP4 linked by a relative path (not embedded); preload=none keeps pages light."""
    src = quote(relative_src.replace("\\", "/"), safe="/.-_~")
    cap = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return Raw(f"<figure><video controls preload='none' src='{src}'></video>{cap}"
               f"<figcaption><a href='{src}'>{esc(relative_src)}</a></figcaption></figure>")


def table(header: Sequence[str], rows: Iterable[Sequence], numeric: Sequence[int] = (), cls: str = "data") -> Raw:
    """A table; `numeric` column indices are right-aligned. Cells are escaped unless Raw."""
    numeric = set(numeric)
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = []
    for row in rows:
        cells = "".join(
            f"<td class='num'>{esc(c)}</td>" if i in numeric else f"<td>{esc(c)}</td>" for i, c in enumerate(row)
        )
        body.append(f"<tr>{cells}</tr>")
    return Raw(f"<table class='{esc(cls)}'><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>")


def key_values(pairs: Iterable[tuple[str, object]]) -> Raw:
    """A two-column table of labelled values."""
    rows = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in pairs)
    return Raw(f"<table class='data kv'><tbody>{rows}</tbody></table>")


def banner(text, danger: bool = False) -> Raw:
    """A prominent warning box (danger: red, e.g. random weights)."""
    return Raw(f"<div class='banner{' danger' if danger else ''}' role='alert'>{esc(text)}</div>")


def note(text) -> Raw:
    return Raw(f"<p class='note'>{esc(text)}</p>")


def swatch(colour: str, label: str) -> Raw:
    return Raw(f"<span class='swatch' style='background:{esc(colour)}'></span>{esc(label)}")


def details(summary: str, body: str, open_: bool = False) -> Raw:
    return Raw(f"<details{' open' if open_ else ''}><summary>{esc(summary)}</summary>{body}</details>")


def section(title: str, body: str, anchor: str | None = None, level: int = 2) -> Raw:
    """<section id=anchor><hN>title</hN>body</section>."""
    ident = f" id='{esc(anchor)}'" if anchor else ""
    return Raw(f"<section{ident}><h{level}>{esc(title)}</h{level}>{body}</section>")


def anchor_id(text: str) -> str:
    """A stable, HTML-safe id from any text."""
    safe = "".join(c if c.isalnum() or c in "-_" else "-" for c in text)
    return "s-" + safe.strip("-").lower()


def page(title: str, body: str, subtitle: str = "", toc: Sequence[tuple[str, str]] = (), footer: str = "") -> str:
    """A complete HTML5 document: inlined CSS, header, table of contents [(anchor, label)], body, image check."""
    nav = "".join(f"<a href='#{esc(a)}'>{esc(label)}</a>" for a, label in toc)
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{esc(title)}</title><style>{CSS}</style></head>\n<body>"
        f"<header class='top'><h1>{esc(title)}</h1><div class='sub'>{esc(subtitle)}</div></header>"
        + (f"<nav class='toc'>{nav}</nav>" if nav else "")
        + f"<main>{body}</main><footer>{esc(footer)} <span id='image-check'></span></footer>"
        f"<script>{IMAGE_CHECK_SCRIPT}</script></body></html>\n"
    )
