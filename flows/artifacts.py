"""What a person watching the Prefect UI sees of a run besides its logs: Prefect artifacts.

A finished scene run publishes a markdown artifact (its traits with units and the seeds'
range, its warnings, which stages ran, where its report and files are) under the key
``{site}-{crop}-scene``, and a season run a table artifact of its summary (one row a date)
under ``{site}-{crop}-season``. One key per plot and crop, so the UI's *Artifacts* page shows
the latest and, under the key, every earlier version: a season's nights one after another,
each linked to its flow run.

Keys hold lowercase letters, digits and dashes only (Prefect's rule); a site name that the
rule changes (``PlotA``, ``plot_a``) gets a short digest of its own spelling, so two plots
never share a key. Publishing is housekeeping: a failure to publish is logged, never fails
the run.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

#: Longest key written (Prefect stores longer ones, but the UI's list cuts them).
MAX_KEY = 60


def artifact_key(site: str, crop: str, kind: str) -> str:
    """``{site}-{crop}-{kind}`` in Prefect's key alphabet (``[a-z0-9-]``), distinct per site
    spelling."""
    slug = re.sub(r"[^a-z0-9]+", "-", site.lower()).strip("-") or "site"
    if slug != site:
        slug += "-" + hashlib.sha1(site.encode()).hexdigest()[:6]
    tail = f"-{crop}-{kind}"
    if len(slug) + len(tail) > MAX_KEY:
        digest = hashlib.sha1(site.encode()).hexdigest()[:6]
        slug = f"{slug[: MAX_KEY - len(tail) - 7].rstrip('-')}-{digest}"
    return slug + tail


def _cell(value: Any, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if math.isfinite(value) else "–"
    return str(value)


def _md(text: str) -> str:
    """A warning or path inside a markdown table or list: its pipes and newlines escaped."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def scene_markdown(out: Mapping[str, Any], warnings: Sequence[str]) -> str:
    """The scene run's record (``flows.scene.summarize``'s, with its ``seconds``) as markdown:
    the traits with their units, the warnings the report opens with, the stages that ran and
    those answered from the cache, and where the report and the files are."""
    from cropcraft_core.metrics.traits import HEADLINE_UNITS

    metrics = dict(out.get("metrics") or {})
    lo, hi = metrics.pop("lai_seeds_min", None), metrics.pop("lai_seeds_max", None)
    lines = [f"# {out['scene']}", ""]
    lines += ["| trait | value | unit |", "|---|---:|---|"]
    for name, value in metrics.items():
        lines.append(f"| {name} | {_cell(value)} | {_md(HEADLINE_UNITS.get(name, ''))} |")
    if lo is not None and hi is not None:
        lines += [
            "",
            f"The optimiser seeds' answers read LAI {_cell(lo, 3)} to {_cell(hi, 3)}: "
            "how firmly the photos pin it down (the search's spread, not a confidence "
            "interval).",
        ]
    params = out.get("params") or {}
    if params:
        sd = out.get("params_std") or {}
        lines += ["", "| parameter | answer | SD over the seeds |", "|---|---:|---:|"]
        lines += [f"| {k} | {_cell(v)} | {_cell(sd.get(k))} |" for k, v in params.items()]
    rows = out.get("rows")
    if rows and (rows.get("lai_spread") or {}).get("mean") is not None:
        s = rows["lai_spread"]
        lines += [
            "",
            f"LAI over {rows['n_rows']} fitted rows: mean {_cell(s['mean'], 3)}, "
            f"range {_cell(s['min'], 3)} to {_cell(s['max'], 3)}.",
        ]
    lines += ["", "## Warnings", ""]
    lines += [f"- {_md(w)}" for w in warnings] or ["none"]
    states = out.get("states") or {}
    seconds = out.get("seconds") or {}

    def listed(cached: bool) -> str:
        names = [k for k, v in states.items() if (v == "Cached") == cached]
        seeds = sum(k.startswith("fit_seed-") for k in names)
        cells = [
            f"{k} ({seconds[k]:.0f} s)" if isinstance(seconds.get(k), (int, float)) else k
            for k in names
            if not k.startswith("fit_seed-")
        ]
        return ", ".join(cells + ([f"{seeds} fit seeds"] if seeds else [])) or "–"

    lines += [
        "",
        "## Stages",
        "",
        f"- ran: {listed(False)}",
        f"- answered from the cache: {listed(True)}",
        "",
        "## Files",
        "",
        f"- report: `{_md(out.get('report', '?'))}`",
        f"- bundle (meshes, Helios XML, metrics): `{_md(out.get('bundle', '?'))}`",
    ]
    return "\n".join(lines) + "\n"


def season_table(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The season summary's rows (``report.season_rows``) as a table artifact's: the same
    columns as ``summary.csv``, a NaN or infinity (not JSON) as an empty cell."""
    out = []
    for r in rows:
        clean = {}
        for k, v in r.items():
            if isinstance(v, float) and not math.isfinite(v):
                v = None
            clean[k] = round(v, 6) if isinstance(v, float) else v
        out.append(clean)
    return out


def _publish(make: Any, log: Any, what: str, **kwargs: Any) -> str | None:
    """Create one artifact; its id, or None after logging why it could not be (never raises)."""
    try:
        return str(make(**kwargs))
    except Exception as exc:  # housekeeping must not fail the run
        log.warning("could not publish the %s to the Prefect UI: %s", what, exc)
        return None


def publish_scene(out: Mapping[str, Any], site: str, crop: str, warnings: Sequence[str], log: Any):
    """The scene run's markdown artifact (inside its flow run); its id or None."""
    from prefect.artifacts import create_markdown_artifact

    return _publish(
        create_markdown_artifact,
        log,
        "scene's results",
        key=artifact_key(site, crop, "scene"),
        markdown=scene_markdown(out, warnings),
        description=f"{out['scene']}: traits, warnings, stages and files",
    )


def publish_season(
    rows: Sequence[Mapping[str, Any]], site: str, crop: str, description: str, log: Any
):
    """The season summary's table artifact (inside the season's flow run); its id or None."""
    from prefect.artifacts import create_table_artifact

    return _publish(
        create_table_artifact,
        log,
        "season summary",
        key=artifact_key(site, crop, "season"),
        table=season_table(rows),
        description=description,
    )
