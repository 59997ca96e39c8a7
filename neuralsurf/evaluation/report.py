"""Writing the results: results.csv, results.json, a Markdown table, PNG plots, report.html.

Every file is replaced whole (a temporary file, then a rename): a reader, or a job rebuilding the
report beside another, never sees half of one."""

from __future__ import annotations

import base64
import csv
import html
import json
import math
from pathlib import Path
from typing import Any

from neuralsurf.evaluation.distances import PERCENTILE, write_error_views
from neuralsurf.evaluation.filenames import read_stored
from neuralsurf.evaluation.per_class import class_table
from neuralsurf.evaluation.render import bar_chart, css_gradient, scatter_plot
from neuralsurf.locks import replaced, write_atomic
from neuralsurf.metrics import json_ready

TABLE_COLUMNS = [("method", "method"), ("scene", "scene"), ("status", "status"),
                 ("chamfer_l1", "Chamfer-L1"), ("chamfer_l1_exact", "Chamfer-L1 exact"),
                 ("fscore_1%", "F@1%"), ("normal_consistency", "NC"), ("normal_consistency_exact", "NC exact"), ("iou", "IoU"),
                 ("hausdorff", "Hausdorff"), ("depth_error_mean", "held-out depth err m"),
                 ("depth_error_common", "held-out err common px m"), ("depth_completeness", "held-out compl."),
                 ("depth_fscore_1cm", "held-out F@1cm"), ("depth_fscore_5cm", "held-out F@5cm"),
                 ("tracking_ate", "tracking ATE m"), ("normal_error_mean_deg", "normal err mean deg"),
                 ("normal_error_median_deg", "normal err median deg"),
                 ("integration_depth_error", "integrated depth err"),
                 ("integration_depth_error_pieces", "integrated depth err per piece"), ("seconds", "time s"), ("peak_rss_mb", "peak RSS MiB"),
                 ("cuda_peak_mb", "CUDA peak MiB"), ("n_faces", "faces"), ("watertight", "watertight")]


def _cell(value: Any) -> str:
    if value is None or value == "":
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "—" if math.isnan(value) else f"{value:.4g}"
    return str(value)


def markdown(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table: the `header` line, its rule, then one line per row of cells (text)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(cells) + " |" for cells in rows])


def shown_columns(rows: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """The TABLE_COLUMNS that some ok row has a value for (method, scene and status always)."""
    ok = [row for row in rows if row["status"] == "ok"]
    return [(key, header) for key, header in TABLE_COLUMNS
            if key in ("method", "scene", "status") or any(row.get(key) not in (None, "") for row in ok)]


def _general(reason: str, scene: str) -> str:
    """A skip reason with its scene's name taken out, so that rows skipped for one cause read alike."""
    for name in (f"scene {scene!r}", f"scene {scene}", repr(scene), scene):
        reason = reason.replace(name, "the scene")
    return reason.replace("the scene's", "its").replace("\n", " ")


def skipped_lines(rows: list[dict[str, Any]]) -> list[tuple[str, str]]:
    """The skipped rows folded into one (reason, "method on scene, scene; method on scene") per reason."""
    causes: dict[str, dict[str, list[str]]] = {}
    for row in rows:
        if row["status"] == "skipped":
            reason = _general(row.get("reason", ""), row["scene"])
            causes.setdefault(reason, {}).setdefault(row["method"], []).append(row["scene"])
    return [(reason, "; ".join(f"{method} on {', '.join(scenes)}" for method, scenes in by_method.items()))
            for reason, by_method in causes.items()]


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """One line per computed row: the metrics any row has; failed rows show their reason. Skipped rows
    follow the table, one line per reason (`skipped_lines`)."""
    columns, lines = shown_columns(rows), []
    for row in rows:
        if row["status"] == "ok":
            lines.append([_cell(row.get(key)) for key, _ in columns])
        elif row["status"] != "skipped":
            reason = row.get("reason", "").replace("|", "/").replace("\n", " ")[:120]
            lines.append([row["method"], row["scene"], f"{row['status']}: {reason}"] + [""] * (len(columns) - 3))
    skipped = [f"skipped ({reason}): {pairs}" for reason, pairs in skipped_lines(rows)]
    return "\n".join([markdown([h for _, h in columns], lines), *(["", *skipped] if skipped else [])])


def per_class_markdown(rows: list[dict[str, Any]]) -> str:
    """The per-class comparison of scene sets' methods with the baselines of the same input
    (`per_class.class_table`) as Markdown, under a line that says how to read it; "" without scene sets."""
    header, lines = class_table(rows)
    if not lines:
        return ""
    return ("Per class of each scene set: the mean exact Chamfer-L1 and F@1% of each method, and against each "
            "baseline of the same input its mean Chamfer over the method's (above 1: the method is better) with "
            "the shapes where the method's Chamfer is lower (k/n), and the baseline's F@1%.\n\n"
            + markdown(header, lines))


def metrics_table(metrics: dict[str, Any]) -> str:
    """A two-column Markdown table of metric names and values (floats to 6 significant digits)."""
    return markdown(["metric", "value"], [[name, f"{value:.6g}" if isinstance(value, float) else str(value)]
                                          for name, value in metrics.items()])


def write_tables(rows: list[dict[str, Any]], run_dir: Path, extra: dict[str, Any] | None = None) -> None:
    """results.csv (one line per row, union of the columns) and results.json ({"rows", ...extra})."""
    run_dir.mkdir(parents=True, exist_ok=True)
    columns: list[str] = []
    for row in rows:  # lists (a scene set's per-shape values) go to results.json only
        columns += [key for key in row if key not in columns and not isinstance(row[key], list)]
    with replaced(run_dir / "results.csv") as temporary, open(temporary, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    clean = [json_ready(row) for row in rows]  # NaN as null, with the reason under "undefined"
    write_atomic(run_dir / "results.json", json.dumps({"rows": clean, **(extra or {})}, indent=2, default=str))


CHARTS = [
    ("chamfer_l1_exact", "exact Chamfer-L1, fraction of the gt box (log; lower is better)", True),
    ("fscore_1%", "F-score at 1% of the gt box (higher is better)", False),
    ("normal_consistency_exact", "normal consistency, exact (higher is better)", False),
    ("iou", "volumetric IoU (higher is better)", False),
    ("hausdorff", "Hausdorff distance, fraction of the gt box (log; lower is better)", True),
    ("depth_error_mean", "held-out depth error, mean in metres (log; lower is better)", True),
    ("depth_error_common", "held-out depth error over the pixels every method shows, metres (log; lower is better)",
     True),
    ("depth_completeness", "held-out depth completeness (higher is better)", False),
    ("depth_fscore_1cm", "held-out depth F-score at 1 cm (higher is better)", False),
    ("depth_fscore_5cm", "held-out depth F-score at 5 cm (higher is better)", False),
    ("tracking_ate", "tracking ATE in metres, poses hidden (log; lower is better)", True),
    ("normal_error_mean_deg", "normal angular error, mean in degrees (log; lower is better)", True),
    ("integration_depth_error", "depth error of the integrated normals (log; lower is better)", True),
    ("seconds", "wall time in seconds (log)", True),
]
"""One bar chart per metric family (key, title, log scale): drawn when some row has a value for it."""


def write_plots(rows: list[dict[str, Any]], run_dir: Path) -> list[str]:
    """A bar chart per metric of CHARTS that some ok row has (only the scenes and methods with a value),
    and a time vs. exact Chamfer scatter; returns their paths in `run_dir`."""
    ok = [r for r in rows if r["status"] == "ok"]
    plots = {}
    for key, title, log in CHARTS:
        values = {(r["scene"], r["method"]): float(r[key]) for r in ok
                  if isinstance(r.get(key), (int, float)) and math.isfinite(r[key]) and (r[key] > 0 or not log)}
        if values:
            scenes = list(dict.fromkeys(scene for scene, _ in values))
            methods = list(dict.fromkeys(method for _, method in values))
            plots[f"{'fscore' if key == 'fscore_1%' else key}.png"] = bar_chart(title, scenes, methods, values, log=log)
    points = [(r["seconds"], r["chamfer_l1_exact"], r["method"], r["scene"]) for r in ok
              if isinstance(r.get("chamfer_l1_exact"), (int, float)) and isinstance(r.get("seconds"), (int, float))]
    if points:
        plots["time_vs_chamfer.png"] = scatter_plot("time vs. accuracy (lower left is better)", "seconds (log)",
                                                    "exact Chamfer-L1 (log)", points)
    folder = run_dir / "plots"
    folder.mkdir(parents=True, exist_ok=True)
    for name, image in plots.items():
        with replaced(folder / name) as temporary:
            image.save(temporary)
    return [f"plots/{name}" for name in plots]


def _img(run_dir: Path, path: str, alt: str) -> str:
    """An embedded PNG: only a PNG file inside `run_dir` (`read_stored`), else "" with a warning."""
    image = read_stored(run_dir, path, "image")
    if image is None:
        return ""
    data = base64.b64encode(image).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}">'


def _error_view(run_dir: Path, row: dict[str, Any], view: dict[str, Any]) -> str:
    """The error-coloured render of a row (`distances.write_error_views`; none with render=false), its
    colour bar in the scene's units and links to its coloured GLBs."""
    top, name = view["top"], f"{row['method']} on {row['scene']}"
    ticks = "".join(f"<span>{value:.3g}</span>" for value in (0.0, top / 2, top))
    links = " ".join(f"<a href='{html.escape(path)}'>{html.escape(what)} (GLB)</a>"
                     for what, path in view["meshes"].items())
    share = f", {100 * top / view['extent']:.3g}% of the ground truth's longest side" if view["extent"] > 0 else ""
    image = _img(run_dir, view["render"], f"{name}: distance to ground truth") if view["render"] else ""
    return (f"<figure class='error-view'>{image}"
            f"<figcaption><div class='colour-bar' data-top='{top!r}' style='background:{css_gradient()}'></div>"
            f"<div class='ticks'>{ticks}</div>distance in scene units, 0 to {top:.3g}{share} (the {PERCENTILE:g}th "
            f"percentile of every method's distances on {html.escape(row['scene'])}; beyond it: yellow)"
            f"{'<br>' + links if links else ''}</figcaption></figure>")


def write_html(rows: list[dict[str, Any]], run_dir: Path, plots: list[str], title: str = "neuralsurf evaluation",
               extra: dict[str, Any] | None = None,
               error_views: dict[tuple[str, str], dict[str, Any]] | None = None) -> Path:
    """One self-contained report.html: the table, the plots and every render (base64 PNGs), each beside
    its error-coloured render with a colour bar (`error_views`, from `distances.write_error_views`)."""
    error_views = error_views or {}
    columns = shown_columns(rows)
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h in columns)
    body = []
    for row in rows:
        if row["status"] == "ok":
            cells = "".join(f"<td>{html.escape(_cell(row.get(k)))}</td>" for k, _ in columns)
        elif row["status"] == "skipped":
            continue
        else:
            cells = (f"<td>{html.escape(row['method'])}</td><td>{html.escape(row['scene'])}</td>"
                     f"<td class='{row['status']}' colspan='{len(columns) - 2}'>"
                     f"{html.escape(row['status'])}: {html.escape(row.get('reason', ''))}</td>")
        body.append(f"<tr>{cells}</tr>")
    skipped = "".join(f"<li class='skipped'><b>{html.escape(pairs)}</b>: {html.escape(reason)}</li>"
                      for reason, pairs in skipped_lines(rows))
    scenes = {r["scene"]: r.get("scene_description", "") for r in rows}
    class_header, class_lines = class_table(rows)
    per_class = ("<h2>Per class</h2><p>Each method against the baselines of the same input: the baseline's mean "
                 "exact Chamfer-L1 over the method's (above 1: the method is better) and the shapes the method wins "
                 "(k/n)</p><table><tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in class_header) + "</tr>"
                 + "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>"
                           for cells in class_lines) + "</table>") if class_lines else ""
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title><style>",
        "body{font-family:sans-serif;margin:2em} table{border-collapse:collapse;font-size:13px}",
        "td,th{border:1px solid #ccc;padding:3px 6px;text-align:right} td:nth-child(-n+3){text-align:left}",
        ".failed{color:#b00;text-align:left} .skipped{color:#777;text-align:left} img{max-width:100%;margin:4px}",
        (".views{display:flex;align-items:flex-start} .views>*{min-width:0} figure{margin:0} figcaption{font-size:12px;"
         "max-width:40em} .colour-bar{height:14px;width:100%;min-width:200px;border:1px solid #888}"
         " .ticks{display:flex;justify-content:space-between}"),
        "</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        "<p>Distances are fractions of the ground truth's longest side (its normalised frame).</p>",
        "<ul>" + "".join(f"<li><b>{html.escape(s)}</b>: {html.escape(d)}</li>" for s, d in scenes.items()) + "</ul>",
        f"<h2>Results</h2><table><tr>{head}</tr>{''.join(body)}</table>",
        f"<p>Skipped, one line per reason:</p><ul class='skips'>{skipped}</ul>" if skipped else "",
        per_class,
        "<h2>Plots</h2>", *[_img(run_dir, p, p) for p in plots],
        ("<h2>Renders</h2><p>ground truth | reconstruction | distance to ground truth (blue 0, red &ge; 1%); "
         "beside them, in viridis on one scale per scene: the reconstruction coloured by each vertex's distance to "
         "the ground truth, and the ground truth by each vertex's distance to the reconstruction (what was "
         "missed)</p>"),
    ]
    for row in rows:
        view = error_views.get((row["scene"], row["method"]))
        error = _error_view(run_dir, row, view) if view and (view["render"] or view["meshes"]) else ""
        if row.get("render") or error:
            parts.append(f"<h3>{html.escape(row['method'])} on {html.escape(row['scene'])}</h3>")
            grey = _img(run_dir, row["render"], f"{row['method']} on {row['scene']}") if row.get("render") else ""
            parts.append(f"<div class='views'>{grey}{error}</div>")
        if row.get("class_render"):
            name = f"{row['method']} on {row['scene']}"
            parts.append(f"<h3>{html.escape(name)}: one shape of each class</h3><figure>"
                         f"{_img(run_dir, row['class_render'], name + ': input, completion, ground truth')}"
                         "<figcaption>the input (points, darker nearer) | the method's mesh | the ground truth, "
                         "from the same side</figcaption></figure>")
        if row.get("held_out_render"):
            name = f"{row['method']} on {row['scene']}"
            parts.append(f"<h3>{html.escape(name)}: held-out views</h3><figure>"
                         f"{_img(run_dir, row['held_out_render'], name + ': held-out depth error')}<figcaption>"
                         "each held-out view: measured depth | the mesh's depth | rendered - measured (green 0, red: "
                         "the mesh lies behind the reading, blue: in front, saturated at 20 cm; black: nothing "
                         "rendered; grey: no reading)</figcaption></figure>")
    if extra:
        parts.append("<h2>Environment and config</h2><pre>" + html.escape(json.dumps(extra, indent=2, default=str))
                     + "</pre>")
    parts.append("</body></html>")
    return write_atomic(run_dir / "report.html", "\n".join(parts))


def write_report(rows: list[dict[str, Any]], run_dir: str | Path, extra: dict[str, Any] | None = None) -> str:
    """Everything above; returns the Markdown table."""
    run_dir = Path(run_dir)
    write_tables(rows, run_dir, extra)
    plots = write_plots(rows, run_dir)
    write_html(rows, run_dir, plots, extra=extra, error_views=write_error_views(rows, run_dir))
    table = markdown_table(rows)
    per_class = per_class_markdown(rows)
    write_atomic(run_dir / "results.md", table + "\n" + (f"\n{per_class}\n" if per_class else ""))
    return table
