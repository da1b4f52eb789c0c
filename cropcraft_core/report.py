"""Self-contained reports: the per-scene HTML page and the season summary (CSV and PNG plot).

Pure functions from small records and arrays to text or bytes; every image is inlined as a
base64 ``data:`` URI, so a report is one file that opens anywhere. Nothing here reads or writes
the scene store (the ``report`` task does), and nothing imports Prefect.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from cropcraft_core.config.params import is_range
from cropcraft_core.errors import InputError

#: Traits shown in the report's metric table and the season summary, in this order.
REPORT_METRICS = (
    "lai",
    "lai_gap_fraction",
    "leaf_angle_mean_deg",
    "leaf_angle_std_deg",
    "leaf_angle_class",
    "node_count",
    "internode_mean_m",
    "plant_height_m",
    "leaf_count",
    "n_plants",
    "leaf_area_m2",
    "ground_area_m2",
)

#: Season summary columns: (metrics key, CSV header with unit).
SEASON_COLUMNS = (
    ("lai", "lai_m2_m2"),
    ("lai_gap_fraction", "lai_gap_fraction_m2_m2"),
    ("leaf_angle_mean_deg", "leaf_angle_mean_deg"),
    ("leaf_angle_std_deg", "leaf_angle_sd_deg"),
    ("plant_height_m", "plant_height_m"),
    ("node_count", "node_count"),
    ("internode_mean_m", "internode_mean_m"),
    # not a trait: the parameters the date's fit was given (field notes, ``--param``), e.g.
    # ``num_nodes=9``; empty when it searched the whole box
    ("parameters_given", "parameters_given"),
    # not a trait: where the date's metric scale came from (the row fit's ``scale_source``:
    # metric_poses, camera_height, camera_distance, gps, row_spacing, user_hint or
    # assumed_metric, the last measured by nothing; session 96's capture audit found it in
    # the report only)
    ("scale_source", "scale_source"),
    # not a trait: the share of the row camera's view the reconstruction left empty (a flag on
    # the date's LAI; ``observe.coverage_warning``)
    ("no_surface_fraction", "row_view_no_surface_fraction"),
    # the surfaces' cover against the photos' (consistency stage): extra − unreconstructed
    ("photo_net_cover", "photo_net_cover_fraction"),
    # where the date was also fitted over its neighbour rows (``rows.neighbours``): how many
    # rows, and the lowest and highest of their LAI answers (the date's LAI is row 0's, or the
    # rows' combined answer's under rows.answer)
    ("n_rows_fitted", "rows_fitted"),
    ("lai_rows_min", "lai_rows_min_m2_m2"),
    ("lai_rows_max", "lai_rows_max_m2_m2"),
    # the lowest and highest LAI of the date's optimiser seeds' answers (metrics.json's seeds:
    # how firmly its observation pins LAI down)
    ("lai_seeds_min", "lai_seeds_min_m2_m2"),
    ("lai_seeds_max", "lai_seeds_max_m2_m2"),
    # done, or failed (its last run; the values, where any, are the run's before); the note:
    # the run's warnings (too few photos, coverage, ...), or where and why it failed
    ("status", "status"),
    ("note", "note"),
)


def png_bytes(rgb: np.ndarray) -> bytes:
    """(H, W, 3) or (H, W) uint8 image → PNG bytes."""
    from PIL import Image

    a = np.asarray(rgb)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise InputError(f"image must be (H, W[, 3]) uint8, got {a.dtype} {a.shape}")
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def data_uri(png: bytes, mime: str = "image/png") -> str:
    """``data:`` URI of encoded image bytes."""
    return f"data:{mime};base64,{base64.b64encode(png).decode('ascii')}"


def thumbnail(rgb: np.ndarray, max_side: int = 192) -> np.ndarray:
    """Downscale (H, W, 3) uint8 so that its longer side is at most ``max_side`` pixels."""
    from PIL import Image

    im = Image.fromarray(np.asarray(rgb, np.uint8))
    im.thumbnail((max_side, max_side), Image.Resampling.LANCZOS)
    return np.asarray(im)


def _fmt(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            return "–"
        return f"{value:.4g}"
    return html.escape(str(value))


def _depth_pair(observed: np.ndarray, predicted: np.ndarray | None) -> tuple[str, str | None]:
    """Both depth maps on one colour scale (the observed finite range)."""
    from cropcraft_core.render.preview import depth_to_rgb

    obs = np.asarray(observed, np.float64)
    fin = np.isfinite(obs)
    lo, hi = (float(obs[fin].min()), float(obs[fin].max())) if fin.any() else (0.0, 1.0)
    a = data_uri(png_bytes(depth_to_rgb(obs, lo, hi)))
    b = None
    if predicted is not None:
        b = data_uri(png_bytes(depth_to_rgb(np.asarray(predicted, np.float64), lo, hi)))
    return a, b


def _depth_key(width: int = 256, height: int = 12) -> str:
    """The depth maps' colour key, near (left) to far (right), as a data URI (the caption
    named the colour map alone; session 93's report audit)."""
    from cropcraft_core.render.preview import depth_to_rgb

    ramp = np.tile(np.linspace(0.0, 1.0, width), (height, 1))
    return data_uri(png_bytes(depth_to_rgb(ramp, 0.0, 1.0)))


_CSS = """
body{font-family:system-ui,sans-serif;margin:2em;color:#222;max-width:1100px}
h1{font-size:1.5em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ddd;padding:.25em .6em;
text-align:left;vertical-align:top}th{background:#f4f4f4}td.num{text-align:right;
font-variant-numeric:tabular-nums}.thumbs img{margin:2px;border:1px solid #ccc}
figure{display:inline-block;margin:.3em 1em .3em 0}figcaption{font-size:.85em;color:#555}
.small{font-size:.85em;color:#555}
"""


def _seeds_html(metrics: Mapping[str, Any], defs: Mapping[str, Any]) -> str:
    """The table of the traits of each optimiser seed's answer beside the scene's answer
    (``metrics.json``'s ``seeds``: :func:`cropcraft_core.metrics.seeds.seed_traits`)."""
    from cropcraft_core.metrics.seeds import SEED_TRAITS

    block = metrics["seeds"]
    stored = block.get("traits") or {}
    # the store sorts a JSON object's keys: back to the traits' own order
    traits = {k: stored[k] for k in (*SEED_TRAITS, *sorted(stored)) if k in stored}
    out = [
        f"<h2>Traits over the {int(block.get('n_seeds', 0))} seeds' answers</h2>",
        "<p class='small'>Each optimiser seed's best parameters build a canopy (the answer's "
        "layout and plants); its traits are measured as above. How far equally good searches "
        "of the same observation land apart: a wide range says the observation pins the trait "
        "down loosely. Not a confidence interval.</p>",
        "<table><tr><th>trait</th><th>answer</th><th>median</th><th>min</th><th>max</th>"
        "<th>SD (÷n)</th><th>unit</th></tr>",
    ]
    for name, t in traits.items():
        unit = (defs.get(name) or {}).get("unit", "")
        cells = "".join(
            f"<td class='num'>{_fmt(t.get(k))}</td>" for k in ("median", "min", "max", "sd")
        )
        out.append(
            f"<tr><td>{html.escape(name)}</td><td class='num'>{_fmt(metrics.get(name))}</td>"
            f"{cells}<td>{html.escape(str(unit))}</td></tr>"
        )
    out.append("</table>")
    return "".join(out)


def _rows_html(rows: Mapping[str, Any]) -> str:
    """The table of the answers fitted over each observed row, and their spread."""
    from cropcraft_core.metrics.rows import ROW_TRAITS

    how = rows.get("answer", "best")
    answer = (
        "the scene's answer above"
        if how == "best"
        else f"and the scene's answer above is the {html.escape(str(how))} of the rows' answers"
    )
    out = [
        f"<h2>The answer over {len(rows['rows'])} rows</h2>",
        f"<p class='small'>Each row observed and fitted alone. Row 0 is the row fit's best row, "
        f"{answer}; +k / −k the k-th row to its right / left. The spread is how "
        "much the answer depends on the row observed.</p><table><tr><th>row</th>"
        "<th>offset (m)</th>",
    ]
    out += [f"<th>{html.escape(t)}</th>" for t in ROW_TRAITS]
    out.append("</tr>")
    for r in rows["rows"]:
        out.append(f"<tr><td>{int(r['index']):+d}</td><td class='num'>{_fmt(r['offset_m'])}</td>")
        out += [f"<td class='num'>{_fmt(r['traits'].get(t))}</td>" for t in ROW_TRAITS]
        out.append("</tr>")
    spread = rows.get("spread") or {}
    for stat in ("mean", "sd", "min", "max"):
        out.append(f"<tr><th>{stat}</th><td></td>")
        out += [f"<td class='num'>{_fmt((spread.get(t) or {}).get(stat))}</td>" for t in ROW_TRAITS]
        out.append("</tr>")
    out.append("</table>")
    return "".join(out)


#: Why a run left photos out, by the key of its ``photos_left_out`` record
#: (:func:`tasks.common.photos_left_out`).
LEFT_OUT_WHY = {
    "unposed": "have no pose in the imported poses",
    "unregistered": "were not registered by structure from motion",
    "outside_box": "do not see the scene box",
    "duplicates": "are copies of another photo",
    "in_subfolders": "are in subfolders, which are not read (move them into the folder)",
}


def few_photos_warning(n_photos: int | None) -> str | None:
    """The warning a run of fewer photos than ``surfaces.FEW_PHOTOS`` gets (a season date of 3
    photos read LAI -81 % and was published as any other date: session 91's season audit),
    else None."""
    from cropcraft_core.surfaces.base import FEW_PHOTOS

    if n_photos is None or n_photos >= FEW_PHOTOS:
        return None
    return (
        f"only {n_photos} photos: a plot's capture takes ~50 (a walk around it) to ~500 (a "
        "drone), so its reconstruction, and the answer, rest on few views"
    )


def left_out_lines(left: Mapping[str, Sequence[str]] | None) -> list[str]:
    """One line per reason a run left photos out, naming the first eight: without a pose in
    the imported poses (a photo added after the capture was posed), not registered by SfM (a
    part of the walk it could not join: the far side of a plot), not seeing the scene box, or
    copies of another photo. The run's summary and its report print the same lines."""
    out = []
    for key, why in LEFT_OUT_WHY.items():
        names = list((left or {}).get(key) or [])
        if names:
            more = f" (+{len(names) - 8} more)" if len(names) > 8 else ""
            out.append(f"{len(names)} photo(s) {why}, left out: {', '.join(names[:8])}{more}")
    return out


def scene_report_html(
    scene: str,
    *,
    thumbnails: Sequence[np.ndarray] = (),
    observed_depth: np.ndarray | None = None,
    predicted_depth: np.ndarray | None = None,
    preview_png: bytes | None = None,
    metrics: Mapping[str, Any] | None = None,
    fit: Mapping[str, Any] | None = None,
    timings: Mapping[str, float] | None = None,
    info: Mapping[str, Any] | None = None,
    rows: Mapping[str, Any] | None = None,
    warnings: Sequence[str] = (),
) -> str:
    """The HTML page of one scene.

    scene: ``site/crop/date``. thumbnails: (h, w, 3) uint8 input photos (already small).
    observed_depth / predicted_depth: (H, W) z-depth in metres from the row camera, NaN where
    empty (shown on the observed map's colour scale). preview_png: the mesh preview.
    metrics: ``metrics.json`` (values plus ``definitions`` {name: {unit, method}}).
    fit: ``fit.json`` (``params``, ``params_std``, ``seed_params``, ``seed_losses``, ``method``).
    timings: seconds per stage. info: other key facts (shown as a table). rows: ``rows.json``
    (``cropcraft_core.metrics.rows.compare_rows``: the answer fitted over each observed row).
    warnings: the run's warnings (the rows against a camera-height hint, an answer on the
    parameter box's edge, the row view's coverage, photos left out), first on the page: the
    console printed them and the page, read the next morning, did not.
    """
    metrics = dict(metrics or {})
    defs = metrics.get("definitions") or {}
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>CropCraft report {html.escape(scene)}</title><style>{_CSS}</style></head><body>",
        f"<h1>CropCraft scene report: {html.escape(scene)}</h1>",
    ]
    if warnings:
        parts.append("<h2>Warnings</h2><ul class='warnings'>")
        parts += [f"<li>{html.escape(str(w))}</li>" for w in warnings]
        parts.append("</ul>")
    if info:
        parts.append("<table>")
        for k, v in info.items():
            parts.append(f"<tr><th>{html.escape(str(k))}</th><td>{_fmt(v)}</td></tr>")
        parts.append("</table>")

    parts.append("<h2>Input photos</h2>")
    if thumbnails:
        parts.append("<div class='thumbs'>")
        for im in thumbnails:
            parts.append(f"<img alt='input photo' src='{data_uri(png_bytes(im))}'>")
        parts.append(f"</div><p class='small'>{len(thumbnails)} of the ingested photos.</p>")
    else:
        parts.append("<p class='small'>none recorded</p>")

    parts.append("<h2>Row-camera depth: observed vs predicted</h2>")
    if observed_depth is not None:
        a, b = _depth_pair(observed_depth, predicted_depth)
        parts.append(
            f"<figure><img alt='observed depth' src='{a}'><figcaption>observed "
            "(surfaces rendered from the row camera)</figcaption></figure>"
        )
        if b is not None:
            parts.append(
                f"<figure><img alt='predicted depth' src='{b}'><figcaption>predicted "
                "(fitted procedural canopy)</figcaption></figure>"
            )
        fin = np.isfinite(np.asarray(observed_depth, float))
        if fin.any():
            d = np.asarray(observed_depth, float)[fin]
            parts.append(
                f"<p class='small'>z-depth below the row camera: {d.min():.3f} m (blue, near) "
                f"<img alt='colour key' src='{_depth_key()}'> {d.max():.3f} m (red, far); "
                "grey = no canopy there (the soil, or no surface seen).</p>"
            )
    else:
        parts.append("<p class='small'>no observation</p>")

    parts.append("<h2>Canopy mesh</h2>")
    if preview_png:
        parts.append(
            f"<img alt='mesh preview' src='{data_uri(preview_png)}' style='max-width:100%'>"
        )
    else:
        parts.append("<p class='small'>no preview</p>")

    parts.append(
        "<h2>Metrics</h2><table><tr><th>trait</th><th>value</th><th>unit</th><th>method</th></tr>"
    )
    for k in REPORT_METRICS:
        if k not in metrics:
            continue
        d = defs.get(k) or {}
        parts.append(
            f"<tr><td>{html.escape(k)}</td><td class='num'>{_fmt(metrics[k])}</td>"
            f"<td>{html.escape(str(d.get('unit', '')))}</td>"
            f"<td class='small'>{html.escape(str(d.get('method', '')))}</td></tr>"
        )
    parts.append("</table>")
    if isinstance(metrics.get("seeds"), Mapping):
        parts.append(_seeds_html(metrics, defs))

    if fit:
        params = fit.get("params") or {}
        std = fit.get("params_std") or {}
        seeds = fit.get("seed_params") or []
        losses = fit.get("seed_losses") or []
        box = (fit.get("config") or {}).get("box") or {}
        over = "rows" if (fit.get("extra") or {}).get("answer") == "mean" else "seeds"
        count = "" if over == "rows" else f", {len(seeds)} seeds"
        parts.append(
            f"<h2>Fitted parameters ({html.escape(str(fit.get('method', '')))}{count})</h2>"
            "<table><tr><th>parameter</th><th>answer</th>"
            f"<th>SD over {over} ({'÷n' if over == 'rows' else '÷n−1'})</th><th>min</th>"
            "<th>max</th></tr>"
        )
        for name, value in params.items():
            col = [float(s[name]) for s in seeds if name in s]
            lo = min(col) if col else None
            hi = max(col) if col else None
            given = box.get(name)
            label = name
            if is_range(given):
                label = f"{name} (searched {_fmt(given[0])} to {_fmt(given[1])})"
            elif given is not None:
                label = f"{name} (given, not fitted)"
            parts.append(
                f"<tr><td>{html.escape(label)}</td><td class='num'>{_fmt(value)}</td>"
                f"<td class='num'>{_fmt(std.get(name))}</td><td class='num'>{_fmt(lo)}</td>"
                f"<td class='num'>{_fmt(hi)}</td></tr>"
            )
        parts.append("</table>")
        if losses:
            cells = " ".join(_fmt(float(v)) for v in losses)
            parts.append(f"<p class='small'>best loss per seed: {cells}</p>")

    if rows and rows.get("rows"):
        parts.append(_rows_html(rows))

    if timings:
        total = sum(float(v) for v in timings.values())
        parts.append("<h2>Stage timings</h2><table><tr><th>stage</th><th>seconds</th></tr>")
        for k, v in timings.items():
            parts.append(f"<tr><td>{html.escape(k)}</td><td class='num'>{float(v):.2f}</td></tr>")
        parts.append(f"<tr><th>total</th><th class='num'>{total:.2f}</th></tr></table>")
        parts.append(
            "<p class='small'>wall-clock seconds of the run that computed each "
            "stage (a cached stage keeps the time of its original run); fit_seed "
            "is summed over seeds.</p>"
        )
    parts.append("</body></html>\n")
    return "".join(parts)


# --------------------------------------------------------------------------- season summary


def given_text(box: Mapping[str, Any] | None) -> str:
    """A fit's given parameters (``FitConfig.box``) as one cell: ``num_nodes=9 leaf_length=
    0.8:1.2``; empty for the whole box."""
    parts = []
    for name, v in (box or {}).items():
        value = ":".join(f"{float(x):g}" for x in v) if is_range(v) else f"{v:g}"
        parts.append(f"{name}={value}")
    return " ".join(parts)


def season_rows(per_date: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """``{date: metrics}`` → rows sorted by date, one column per :data:`SEASON_COLUMNS`."""
    rows = []
    for date in sorted(per_date):
        m = per_date[date]
        rows.append({"date": date, **{col: m.get(key) for key, col in SEASON_COLUMNS}})
    return rows


def season_csv(rows: Sequence[Mapping[str, Any]]) -> str:
    """The season summary as CSV text (units in the column names, empty cell = unknown)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["date", *(col for _, col in SEASON_COLUMNS)])
    for r in rows:
        cells = []
        for _, col in SEASON_COLUMNS:
            v = r.get(col)
            if isinstance(v, str):
                cells.append(v)
            else:  # a NaN or inf (JSON reads them from a metrics.json) is not a value either
                x = math.nan if v is None else float(v)
                cells.append(f"{x:.6g}" if math.isfinite(x) else "")
        writer.writerow([r["date"], *cells])
    return buf.getvalue()


#: Days either side of a season's dates on its plot's axis, at least (one date spanned 4 years,
#: its own date unlabelled: session 93's report audit).
SEASON_PLOT_MARGIN_DAYS = 7


def season_plot_png(rows: Sequence[Mapping[str, Any]], title: str = "") -> bytes:
    """PNG of LAI, mean leaf angle (± SD) and plant height against date (three panels):
    :func:`season_figure`'s."""
    fig = season_figure(rows, title)  # selects the Agg backend first
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    return buf.getvalue()


#: The year a season plot of several years draws every date in (a leap year: 29 February has a
#: place), so that each year's dates lie over one axis of days in the year.
_PLOT_YEAR = 2000


def season_figure(rows: Sequence[Mapping[str, Any]], title: str = "") -> Any:
    """The season plot's matplotlib figure (Agg). A failed date (``status``) is marked on
    every panel: a red cross at the foot where it has no values, its values drawn hollow in red
    where they are an earlier run's (a failed date was left off and a failed rerun's old values
    drawn as a fresh answer: session 93's report audit).

    Dates of more than one year (a plot photographed again the next season, under the same
    site and crop) are drawn a series per year over the days of the year (``Jul 01``), each
    year in its own colour, rather than along one time axis on which each season shrank to a
    strip beside a year's empty gap."""
    import datetime as dt

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    all_dates = [dt.date.fromisoformat(r["date"]) for r in rows]
    years = sorted({d.year for d in all_dates})
    several = len(years) > 1
    fig, axes = plt.subplots(3, 1, figsize=(9.5, 7.5), sharex=True)
    for n, year in enumerate(years):
        part = [r for r, d in zip(rows, all_dates, strict=True) if d.year == year]
        dates = [d.replace(year=_PLOT_YEAR) if several else d for d in all_dates if d.year == year]
        colour = f"C{n % 10}" if several else None
        _season_series(axes, part, dates, colour, f" {year}" if several else "")
    axes[0].set_ylabel("LAI (m² m⁻²)")
    # beside the panels, not over a date's points (it hid the gap-fraction LAI of a first night);
    # each kind of mark once, whichever years drew it
    handles, labels = axes[0].get_legend_handles_labels()
    once = dict(zip(labels, handles, strict=True))
    axes[0].legend(
        once.values(), once.keys(), fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0),
        borderaxespad=0,
    )  # fmt: skip
    axes[1].set_ylabel("leaf angle (°), mean ± SD")
    axes[2].set_ylabel("plant height (m)")
    axes[2].set_xlabel("day of the year" if several else "date")
    drawn = [d.replace(year=_PLOT_YEAR) if several else d for d in all_dates]
    margin = dt.timedelta(days=SEASON_PLOT_MARGIN_DAYS)
    axes[2].set_xlim(min(drawn) - margin, max(drawn) + margin)
    locator = mdates.AutoDateLocator(minticks=3, maxticks=9)
    axes[2].xaxis.set_major_locator(locator)
    axes[2].xaxis.set_major_formatter(mdates.DateFormatter("%b %d" if several else "%Y-%m-%d"))
    if title:
        axes[0].set_title(title)
    fig.autofmt_xdate()
    fig.tight_layout()
    return fig


def _season_series(
    axes: Any, rows: Sequence[Mapping[str, Any]], dates: list, colour: str | None, year: str
) -> None:
    """One year's dates on the season plot's three panels (``year``: "" or " 2025", added to
    its LAI lines' legend labels)."""
    failed = np.array([r.get("status") == "failed" for r in rows], bool)

    def col(name: str) -> np.ndarray:
        return np.array([np.nan if r.get(name) is None else float(r[name]) for r in rows])

    def mark_failed(ax: Any, values: np.ndarray, legend: bool = False) -> None:
        kept = failed & np.isfinite(values)
        if kept.any():
            ax.plot(
                [d for d, k in zip(dates, kept, strict=True) if k], values[kept], "o",
                mfc="none", mec="tab:red", ms=11, mew=1.5,
                label="failed: an earlier run's values" if legend else None,
            )  # fmt: skip
        gone = failed & ~np.isfinite(values)
        if gone.any():
            ax.plot(
                [d for d, g in zip(dates, gone, strict=True) if g], [0.03] * int(gone.sum()),
                "x", color="tab:red", ms=9, mew=2, transform=ax.get_xaxis_transform(),
                label="failed: no values (summary.csv says why)" if legend else None,
            )  # fmt: skip

    axes[0].plot(
        dates, col("lai_m2_m2"), "o-", color=colour, label=f"LAI (leaf area / ground area){year}"
    )
    lo, hi = col("lai_rows_min_m2_m2"), col("lai_rows_max_m2_m2")
    if np.isfinite(lo).any():
        has = np.isfinite(lo) & np.isfinite(hi)
        axes[0].vlines(
            [d for d, h in zip(dates, has, strict=True) if h],
            lo[has],
            hi[has],
            colors="grey",
            linewidth=4,
            alpha=0.5,
            label="LAI over the rows fitted",
        )
    lo, hi = col("lai_seeds_min_m2_m2"), col("lai_seeds_max_m2_m2")
    if np.isfinite(lo).any():
        has = np.isfinite(lo) & np.isfinite(hi)
        axes[0].errorbar(
            [d for d, h in zip(dates, has, strict=True) if h],
            (lo[has] + hi[has]) / 2,
            yerr=(hi[has] - lo[has]) / 2,
            fmt="none",
            ecolor=colour or "tab:blue",
            capsize=4,
            alpha=0.6,
            label="LAI over the seeds' answers (not always the answer's)",
        )
    if np.isfinite(col("lai_gap_fraction_m2_m2")).any():
        axes[0].plot(
            dates, col("lai_gap_fraction_m2_m2"), "s--", color=colour,
            label=f"LAI (gap fraction){year}",
        )  # fmt: skip
    mark_failed(axes[0], col("lai_m2_m2"), legend=True)
    mean, sd = col("leaf_angle_mean_deg"), col("leaf_angle_sd_deg")
    axes[1].errorbar(dates, mean, yerr=np.nan_to_num(sd), fmt="o-", capsize=3, color=colour)
    mark_failed(axes[1], mean)
    axes[2].plot(dates, col("plant_height_m"), "o-", color=colour)
    mark_failed(axes[2], col("plant_height_m"))
