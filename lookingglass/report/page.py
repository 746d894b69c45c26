"""Lay out a `ReportData` as report.html: template.html filled with tables, inline SVG charts,
pictures, the 3D view's JSON and the bundled scripts."""

from __future__ import annotations

import json
import re
import time
from html import escape
from importlib import resources
from pathlib import Path

from .. import __version__
from .build import ReportData

METRICS = [("cd", "CD (x1e4)"), ("metro", "Metro (x1e3)"), ("cdn_mean", "CDN-mean (deg)"), ("cdn_med", "CDN-med (deg)")]
STAGE_LABELS = {"load": "load", "visual_hull": "visual hull", "normals": "normals (network + latent opt.)",
                "surface": "surface (features + PNet + Poisson)", "refine": "refine (silhouettes)"}
HULL, MESH = "#e0a040", "#3f7fc0"


def _asset(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def _script_safe(text: str, what: str) -> str:
    """`text` to sit inside <script>: a closing tag in it would end the element early."""
    if "</script" in text.lower() or "<!--" in text:
        raise ValueError(f"{what} holds '</script' or '<!--' and cannot be inlined")
    return text


def fmt(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, float):
        return f"{x:.{digits}g}" if abs(x) < 1000 else f"{x:,.0f}"
    return escape(str(x))


# ---------------------------------------------------------------------------------------------
# Charts (inline SVG)
# ---------------------------------------------------------------------------------------------
def bar_chart(rows: list[tuple[str, list[float | None]]], series: list[tuple[str, str]], *, width: int = 420,
              per_row_scale: bool = False, digits: int = 3, unit: str = "") -> str:
    """Horizontal grouped bars: rows of (label, one value per series); series: (name, colour).
    per_row_scale: each row's bars scaled to that row's largest value (rows of different units)."""
    label_w, bar_h, gap, value_w = 110, 11, 7, 56
    plot_w = width - label_w - value_w
    group_h = bar_h * len(series) + gap
    legend_h = 18 if len(series) > 1 else 4
    height = legend_h + group_h * len(rows) + 4
    top = max((v for _, vals in rows for v in vals if v is not None), default=1.0) or 1.0
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" role="img">']
    if len(series) > 1:
        x = label_w
        for name, colour in series:
            parts.append(f'<rect x="{x}" y="3" width="10" height="10" fill="{colour}"/>'
                         f'<text x="{x + 14}" y="12">{escape(name)}</text>')
            x += 24 + 7 * len(name)
    for r, (label, values) in enumerate(rows):
        y0 = legend_h + r * group_h
        scale = (max((v for v in values if v is not None), default=1.0) or 1.0) if per_row_scale else top
        parts.append(f'<text x="{label_w - 6}" y="{y0 + bar_h * len(series) / 2 + 4:.1f}" '
                     f'text-anchor="end">{escape(label)}</text>')
        for s, ((_, colour), v) in enumerate(zip(series, values)):
            if v is None:
                continue
            w = max(plot_w * v / scale, 1.0)
            y = y0 + s * bar_h
            parts.append(f'<rect x="{label_w}" y="{y}" width="{w:.1f}" height="{bar_h - 2}" fill="{colour}"/>'
                         f'<text x="{label_w + w + 4:.1f}" y="{y + bar_h - 3}">{fmt(float(v), digits)}{unit}</text>')
    parts.append("</svg>")
    return "".join(parts)


# ---------------------------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------------------------
def _stage(report: dict, name: str) -> dict:
    return next((s for s in report.get("stages", []) if s.get("name") == name), {})


def metrics_table(metrics: dict) -> str:
    rows = []
    for key, label in METRICS:
        h, m = metrics["hull"][key], metrics["mesh"][key]
        cls = "better" if m < h else "worse" if m > h else ""
        rows.append(f'<tr><td>{label}</td><td class="num">{h:.3g}</td><td class="num {cls}">{m:.3g}</td>'
                    f'<td class="num {cls}">{m / h:.2f}</td></tr>' if h else
                    f'<tr><td>{label}</td><td class="num">{h:.3g}</td><td class="num">{m:.3g}</td><td></td></tr>')
    chart = bar_chart([(label, [metrics["hull"][k], metrics["mesh"][k]]) for k, label in METRICS],
                      [("visual hull", HULL), ("result", MESH)], per_row_scale=True, width=400)
    return ('<table><tr><th>vs ground truth</th><th class="num">hull</th><th class="num">result</th>'
            '<th class="num">result / hull</th></tr>' + "".join(rows) + "</table>"
            f'<div class="muted">lower is better; unit-sphere scale of the ground truth, '
            f'{metrics["mesh"].get("samples", 20000)} samples a surface</div>{chart}')


def side_panel(data: ReportData) -> str:
    """The first screen's right column: the figures at a glance, the metrics, the first view."""
    r = data.report
    views = data.views
    mean = sum(v.error for v in views) / max(len(views), 1)
    hull_errors = [v.error_hull for v in views if v.error_hull is not None]
    rows = [("scene", f'<span title="{escape(r.get("scene", ""))}">{escape(scene_name(r))}</span>'),
            ("views", f'{r.get("num_views")} at {r["image_size"][0]}x{r["image_size"][1]}' if r.get("image_size") else "?"),
            ("stages", escape(" → ".join(r.get("stages_run", [])) or "–") + f' (mesh from {escape(str(r.get("mesh_from")))})'),
            ("time", f'{r.get("total_seconds", 0):.1f} s on {escape(str(r.get("device", "?")))}, '
                     f'peak memory {r.get("peak_memory_mb", 0):,.0f} MiB'),
            ("re-rendering error", f'{mean:.4f}' + (f' (hull {sum(hull_errors) / len(hull_errors):.4f})' if hull_errors else "")
             + ' <span class="muted">mean |photo − render|, all views</span>')]
    if r.get("ior") is not None:
        found = r.get("ior_estimate")
        rows.append(("IoR", f'{r["ior"]:.4f} <span class="muted">({escape(str(r.get("ior_source")))})</span>' +
                     (f'; estimated {found["value"]:.3f} ± {found["uncertainty"]:.3f} from the photos'
                      + (' <span class="muted">(the IoR net)</span>' if found.get("method") == "learned" else "")
                      + ('' if found["reliable"] else ' <span class="worse">(not reliable)</span>') if found else "")))
    if r.get("warnings"):
        rows.append(("warnings", f'<a href="#warnings" class="worse">{len(r["warnings"])}</a>'))
    html = ['<div class="card"><table class="kv">' +
            "".join(f"<tr><td>{k}</td><td>{v}</td></tr>" for k, v in rows) + "</table></div>"]
    if data.metrics:
        html.append(f'<div class="card">{metrics_table(data.metrics)}</div>')
    if views:
        v = views[0]
        html.append(f'<div class="card"><h3>view {v.index:02d} <span class="muted">(<a href="#views">all views</a>)</span>'
                    f'</h3><div class="strip small">' + "".join(
                        f'<figure><img src="{uri}" alt="{escape(cap)}"><figcaption>{escape(cap)}</figcaption></figure>'
                        for cap, uri in v.pictures if len(v.pictures) <= 4 or cap != "visual hull normals")
                    + "</div></div>")
    return "\n".join(html)


def views_section(data: ReportData) -> str:
    out = []
    for v in data.views:
        cls = "" if v.error_hull is None else "better" if v.error < v.error_hull else "worse"
        figures = [f're-rendering error <b class="{cls}">{v.error:.4f}</b>'
                   + (f" (the hull's {v.error_hull:.4f})" if v.error_hull is not None else "")]
        if v.iou is not None:
            figures.append(f"silhouette IoU {v.iou:.4f}")
        strip = "".join(f'<figure><img src="{uri}" alt="{escape(cap)}"><figcaption>{escape(cap)}</figcaption></figure>'
                        for cap, uri in v.pictures)
        out.append(f'<div class="view card" id="view-{v.index:02d}"><div class="title"><b>view {v.index:02d}</b>'
                   f'<span class="muted">{escape(v.name)}</span> · {" · ".join(figures)}</div>'
                   f'<div class="strip">{strip}</div></div>')
    return "\n".join(out)


def numbers_section(data: ReportData) -> str:
    r = data.report
    parts = []
    stages = [s for s in r.get("stages", []) if "seconds" in s]
    if stages:
        rows = "".join(f'<tr><td>{escape(STAGE_LABELS.get(s["name"], s["name"]))}</td><td class="num">{s["seconds"]:.2f}</td>'
                       f'<td class="num">{s.get("peak_memory_mb", 0):,.0f}</td></tr>' for s in stages)
        chart = bar_chart([(s["name"].replace("_", " "), [s["seconds"]]) for s in stages],
                          [("seconds", MESH)], width=460, unit=" s")
        parts.append('<div class="card"><h3>Time and memory per stage</h3><div class="charts"><table>'
                     '<tr><th>stage</th><th class="num">seconds</th><th class="num">peak MiB</th></tr>' + rows +
                     f'<tr><td><b>total</b></td><td class="num"><b>{r.get("total_seconds", 0):.2f}</b></td>'
                     f'<td class="num"><b>{r.get("peak_memory_mb", 0):,.0f}</b></td></tr></table>{chart}</div>'
                     '<div class="muted">peak memory: the process\'s peak resident memory when the stage ended'
                     + (f'; GPU peak {r["gpu_peak_memory_mb"]:,.0f} MiB' if "gpu_peak_memory_mb" in r else "")
                     + f'. This page took {data.seconds:.1f} s to make.</div></div>')
    errors = []
    normals = _stage(r, "normals")
    if "render_error" in normals:
        errors.append(f'<p>Normals stage (rendering layer at {normals["network_size"][0]}x{normals["network_size"][1]}, '
                      f'mean squared error over the mask): hull\'s normals <b>{normals["render_error_vh"]:.4f}</b>, '
                      f'the network\'s <b>{normals["render_error"]:.4f}</b> '
                      f'({normals["render_error"] / max(normals["render_error_vh"], 1e-12):.2f} x).</p>')
    refine = _stage(r, "refine")
    if "rerender_error" in refine:
        before, after = refine["rerender_error"]
        width = r.get("config", {}).get("refine", {}).get("rerender_width", "?")
        surface = "surface stage's mesh" + (" cut to the visual hull" if refine.get("input_carve", {}).get("kept") else "")
        passes = sum(p["kept"] == "refined" for p in refine.get("passes", []))
        errors.append(f'<p>Refine stage (re-rendered at {width} px wide, weighted over the views): the {surface} '
                      f'<b>{before:.4f}</b>, the refined one <b>{after:.4f}</b>; kept: the '
                      f'{"refined mesh" if refine.get("kept") == "refined" else surface}'
                      f'{f" (refined in {passes} passes)" if passes > 1 else ""}.</p>')
    series = [("visual hull", HULL), ("result", MESH)] if any(v.error_hull is not None for v in data.views) \
        else [("result", MESH)]
    rows = [(f"view {v.index:02d}", ([v.error_hull] if len(series) == 2 else []) + [v.error]) for v in data.views]
    errors.append(f'<p>Re-rendered as glass by the path tracer at {data.rerender_width} px wide, compared with the '
                  'photos (both exposed to a mean of 0.5): mean absolute difference per channel over the mask and the '
                  'silhouette.</p>' + bar_chart(rows, series, width=460, digits=3))
    parts.append('<div class="card"><h3>Render errors</h3>' + "".join(errors) + "</div>")
    if data.metrics:
        parts.append(f'<div class="card"><h3>Against the ground truth</h3>{metrics_table(data.metrics)}</div>')
    warnings = r.get("warnings", [])
    parts.append('<div class="card" id="warnings"><h3>Warnings</h3>' + (
        '<ul class="warnings">' + "".join(f"<li>{escape(w)}</li>" for w in warnings) + "</ul>" if warnings
        else '<p class="muted">none</p>') + ("".join(f'<p class="muted">{escape(n)}.</p>' for n in data.notes)) + "</div>")
    return "\n".join(parts)


def config_section(report: dict) -> str:
    config = json.dumps(report.get("config", {}), indent=2)
    rest = {k: v for k, v in report.items() if k != "config"}
    return ('<div class="card"><p>The resolved config of this run (report.json\'s <code>config</code>); '
            '<code>lookingglass reconstruct SCENE --config OUT/report.json</code> runs it again.</p>'
            f'<pre>{escape(config)}</pre><details><summary>the whole report.json</summary>'
            f'<pre>{escape(json.dumps(rest, indent=1))}</pre></details></div>')


def scene_name(report: dict) -> str:
    """The capture's folder name (its parent's for a folder named "scene", as demo and
    generate-validation make them; a folder still being written, `fileio.staged_dir`'s
    ".NAME.partial-XXXX" as demo's scene is while it runs, by the NAME it will have)."""
    scene = Path(report.get("scene", "scene"))
    name = (scene.parent.name if scene.name == "scene" and scene.parent.name else scene.name) or "?"
    staged = re.fullmatch(r"\.(.+)\.partial-[^.]+", name)
    return staged.group(1) if staged else name


def render_page(data: ReportData) -> str:
    r = data.report
    name = scene_name(r)
    gt = " · with ground truth" if data.metrics else ""
    fields = {
        "version": escape(__version__),
        "title": escape(f"lookingglass · {name}"),
        "heading": escape(f"lookingglass · {name}"),
        "subtitle": escape(f"{r.get('num_views')} views · {time.strftime('%Y-%m-%d %H:%M')}{gt}"),
        "side": side_panel(data),
        "views_intro": escape("Per view, cropped around the object: the photo with the mask's outline, the result "
                              "re-rendered as glass under the capture's environment map (the mask outlined), then the "
                              "first-surface normals (camera frame, RGB = (n + 1) / 2) of the visual hull, the network "
                              "(at its resolution, after latent optimization), the result"
                              + (" and the ground truth." if data.metrics else ".")),
        "views": views_section(data),
        "numbers": numbers_section(data),
        "config": config_section(r),
        "footer": (f"Made by lookingglass {escape(__version__)}. The 3D view uses three.js (MIT licence, "
                   "lookingglass/report/static/LICENSE-three.txt), embedded in this file: it loads nothing."),
        "data": json.dumps(data.scene3d, separators=(",", ":")).replace("</", "<\\/"),
        "three": _script_safe(_asset("static/three-bundle.min.js"), "the three.js bundle"),
        "viewer": _script_safe(_asset("viewer.js"), "viewer.js"),
    }
    template = _asset("template.html")
    missing = set(re.findall(r"\{\{(\w+)\}\}", template)) ^ set(fields)
    if missing:
        raise KeyError(f"template.html and the page's fields differ in {sorted(missing)}")
    # one pass over the template: the values (scripts, data) are never scanned for placeholders
    return re.sub(r"\{\{(\w+)\}\}", lambda m: fields[m.group(1)], template)
