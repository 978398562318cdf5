"""One self-contained HTML page: inline CSS, figures as base64 PNG, no network access.

The page carries a small script that, once loaded, records its own health in ``<body data-check="...">``:
JavaScript errors seen (``window.onerror``) and, per figure, its id, natural and shown size, and how many of
its decoded pixels differ from the first one (0 for a blank or undecodable picture).  A headless
browser's ``--dump-dom`` then shows whether every figure loaded with a non-zero size (tests/test_html_report.py).
Draws nothing itself and knows no algorithm: it assembles strings and bytes it is given.
"""

from __future__ import annotations

import base64
import html
import json

CSS = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 24px auto; max-width: 1200px; padding: 0 16px; color: #1d2330; }
h1 { font-size: 22px; } h2 { font-size: 18px; border-bottom: 1px solid #d5d9e0; padding-bottom: 4px; margin-top: 32px; }
table { border-collapse: collapse; margin: 8px 0 16px; font-size: 12px; max-width: 100%; }
th, td { border: 1px solid #d5d9e0; padding: 3px 6px; text-align: right; }
td.l { overflow-wrap: break-word; } td.mono { overflow-wrap: anywhere; }
summary { cursor: pointer; margin: 4px 0; }
th { background: #f1f3f7; font-weight: 600; } td.l, th.l { text-align: left; }
td.mono { font: 11px ui-monospace, monospace; text-align: left; }
figure { margin: 12px 0; } figure img { max-width: 100%; border: 1px solid #d5d9e0; }
figcaption { color: #5a6273; font-size: 12px; }
.gallery { display: flex; flex-wrap: wrap; gap: 12px; } .gallery figure { width: 440px; max-width: 100%; }
pre { background: #f6f8fa; padding: 8px; font-size: 12px; white-space: pre-wrap; overflow-wrap: anywhere; }
code { background: #f1f3f7; padding: 1px 4px; overflow-wrap: anywhere; }
p.note { color: #5a6273; font-size: 12px; }
"""

CHECK_JS = """
window.__errors = [];
window.onerror = function (msg) { window.__errors.push(String(msg)); };
window.addEventListener('load', function () {
  var figs = [];
  document.querySelectorAll('img[data-figure]').forEach(function (im) {
    var varied = 0;
    try {
      var c = document.createElement('canvas');
      c.width = im.naturalWidth; c.height = im.naturalHeight;
      var g = c.getContext('2d'); g.drawImage(im, 0, 0);
      var d = g.getImageData(0, 0, c.width, c.height).data;
      for (var i = 4; i < d.length; i += 4) {
        if (d[i] !== d[0] || d[i + 1] !== d[1] || d[i + 2] !== d[2] || d[i + 3] !== d[3]) { varied++; }
      }
    } catch (e) { window.__errors.push('figure ' + im.dataset.figure + ': ' + e); }
    figs.push({id: im.dataset.figure, w: im.naturalWidth, h: im.naturalHeight, shown: im.getBoundingClientRect().width,
               varied: varied});
  });
  var wide = [];
  document.querySelectorAll('table, pre, div, figure, code, p').forEach(function (el) {
    if (el.scrollWidth > el.clientWidth + 1 && getComputedStyle(el).overflowX !== 'visible') {
      wide.push(el.tagName + ' ' + el.scrollWidth + '>' + el.clientWidth);
    }
  });
  document.body.dataset.check = JSON.stringify({errors: window.__errors, figures: figs, wide: wide,
    scrollWidth: document.documentElement.scrollWidth, viewport: window.innerWidth});
});
"""


def esc(x) -> str:
    return html.escape("" if x is None else str(x))


def fmt(v, nd: int = 4) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "-" if v != v else f"{v:.{nd}g}"
    return str(v)


def header(name) -> str:
    """A column name as a header that can wrap: SQL's underscores become spaces."""
    return str(name).replace("_", " ")


def table(cols, rows, left: int = 1, mono: tuple[int, ...] = ()) -> str:
    """An HTML table; the first ``left`` columns are left-aligned (labels), columns ``mono`` in monospace
    (commands).  Headers and cells wrap, so the table keeps to the page's width."""
    def cls(i):
        return "mono" if i in mono else ("l" if i < left else "")
    head = "".join(f'<th class="{cls(i)}">{esc(header(c))}</th>' for i, c in enumerate(cols))
    body = "".join("<tr>" + "".join(f'<td class="{cls(i)}">{esc(fmt(v))}</td>'
                                    for i, v in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def flatten(d, prefix: str = "") -> list[tuple[str, object]]:
    """Nested mappings as (dotted key, leaf value) pairs in key order: ``{"camera": {"fx": 1.0}}`` ->
    ``[("camera.fx", 1.0)]``; a list of mappings gets its index as a key (``images.0.path``), other lists are
    leaves."""
    out = []
    if isinstance(d, dict):
        for k in sorted(d, key=str):
            out += flatten(d[k], f"{prefix}{k}.")
    elif isinstance(d, (list, tuple)) and d and all(isinstance(v, dict) for v in d):
        for i, v in enumerate(d):
            out += flatten(v, f"{prefix}{i}.")
    else:
        out.append((prefix[:-1], d))
    return out


def leaf_text(v) -> str:
    """A spec value as text: numbers in full (the spec is what reproduces the run), lists comma-separated,
    None as "none"."""
    if v is None:
        return "none"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(leaf_text(x) for x in v) + "]"
    return str(v)


def definitions(d: dict) -> str:
    """A nested mapping (a spec) as a two-column definition table of its flattened keys."""
    return table(["key", "value"], [(k, leaf_text(v)) for k, v in flatten(d)], left=2)


def figure(png: bytes, fig_id: str, caption: str, width: int | None = None, data: dict | None = None) -> str:
    """A figure from PNG bytes, inlined as base64, tagged for the load check; ``data``: attributes
    ``data-<key>`` of the figure (JSON), e.g. the positions a crop marks."""
    src = "data:image/png;base64," + base64.b64encode(png).decode()
    w = f' width="{int(width)}"' if width else ""
    extra = "".join(f' data-{esc(k)}="{esc(json.dumps(v))}"' for k, v in (data or {}).items())
    return (f'<figure{extra}><img data-figure="{esc(fig_id)}" alt="{esc(caption)}" src="{src}"{w}>'
            f"<figcaption>{esc(caption)}</figcaption></figure>")


def pre(text: str) -> str:
    return f"<pre>{esc(text)}</pre>"


def page(title: str, sections: list[tuple[str, str]], subtitle: str = "") -> str:
    """The whole document: ``sections`` are (heading, inner HTML) pairs."""
    body = "".join(f"<section><h2>{esc(h)}</h2>{inner}</section>" for h, inner in sections)
    meta = json.dumps({"generator": "dualsight"})
    return (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{esc(title)}</title>"
            f"<meta name=\"generator\" content=\"{esc(meta)}\"><style>{CSS}</style><script>{CHECK_JS}</script>"
            f"</head><body><h1>{esc(title)}</h1><p>{esc(subtitle)}</p>{body}</body></html>")
