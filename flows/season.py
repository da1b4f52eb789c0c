"""The season flow: every dated scene of a site that has photos and no results, each as a
subflow, then a season summary (LAI, leaf angle, height by date: CSV and a PNG plot)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from prefect import flow, get_run_logger
from prefect.states import Failed

from cropcraft_core.errors import CropCraftError, InputError
from cropcraft_core.store import (
    SEASON_FOLDER,
    DiscoveredScene,
    SceneKey,
    SceneStore,
    manifest_key,
)
from flows.runners import DEFAULT_RUNNER
from flows.scene import SurfacesBackend


def pending_dates(store: SceneStore, site: str, crop: str) -> list[str]:
    """Dates of ``site``/``crop`` with photos in their inbox whose report stage is not done, or
    whose inbox changed since the run that finished it (photos uploaded late or replaced,
    new poses): that night's run saw a part of them."""
    return [
        d.scene.date
        for d in store.discover(site, crop)
        if d.stages.get("report") != "done" or _inbox_changed(store, d)
    ]


def _inbox_changed(store: SceneStore, found: DiscoveredScene) -> bool:
    """Whether the scene's inbox (photos, ``transforms.json``, ``known.json``) differs from the
    inputs its manifest recorded; False for a scene last run from photos kept elsewhere
    (``cropcraft run --images URI``), whose inbox that run did not read."""
    from flows.scene import manifest_inputs, scene_inputs

    if found.sources.get("images") is not None:
        return False
    try:
        _, _, now, _ = scene_inputs(store, found.scene)
    except CropCraftError:  # no photos now, or bad notes: the run will say so
        return True
    return manifest_inputs(now) != found.inputs


def stale_dates(
    store: SceneStore,
    site: str,
    crop: str,
    overrides: dict[str, Any] | None,
    skip: list[str] | tuple[str, ...] = (),
) -> list[str]:
    """Finished dates (not in ``skip``) whose stored results this release would not serve
    under ``overrides``: run with other settings (the deployment's changed), or by a release
    whose stages have changed since. The season runs only new or changed inboxes, so their
    answers stay in its summary beside the others; the run names them. A date whose photos
    cannot be read where its last run read them is left out (``cropcraft status`` says so)."""
    from flows.scene import cache_walk, prepare

    out = []
    for d in store.discover(site, crop, with_runs=True):
        if d.scene.date in skip or d.stages.get("report") != "done":
            continue
        images, poses = d.sources.get("images"), d.sources.get("poses")
        try:
            req = prepare(site, crop, d.scene.date, images, poses, overrides, store.root)
        except CropCraftError:
            continue
        if cache_walk(req)[1] is not None:
            out.append(d.scene.date)
    return out


def _no_surface(store: SceneStore, folder: str) -> float | None:
    """The share of the date's row-camera view without a fully supported reconstructed surface
    (the observe stage's figure, kept in the observation's meta; None if no observation is
    stored)."""
    import io

    from cropcraft_core.observe import Observation, no_surface_fraction

    key = folder + "observation.npz"
    if not store.isfile(key):
        return None
    obs = Observation.load(io.BytesIO(store.get_bytes(key)))
    seen = obs.meta.get("no_surface_fraction")  # older observations: from the rendered depth
    return float(seen) if seen is not None else no_surface_fraction(obs.depth)


def _stored_json(store: SceneStore, key: str) -> dict[str, Any]:
    """The JSON a stage stored at ``key``; {} where it stored none (not run, an older store)."""
    return store.get_json(key) if store.isfile(key) else {}


def _rows(store: SceneStore, scene: SceneKey) -> dict[str, Any]:
    """The date's LAI over the rows it was fitted on (``rows/rows.json``): ``n_rows_fitted``,
    ``lai_rows_min``, ``lai_rows_max``; {} when it has none, or when the answer it records is
    not the date's current canopy (``generate/canopy.json``: a later run answered otherwise).

    The canopy is the table's when its parameters are the table's answer and, where the
    manifest keeps the generate stage's inputs, the canopy was built from the answer the
    table names: the rows' combined answer (``rows/fit.json``, as stored by the rows stage)
    for ``rows.answer`` other than ``best``, the best row's own (not ``rows/fit.json``) for
    ``best``. So a later best-only run whose answer equals the rows' mean to the last digit
    no longer reads as the rows' table (the parameters alone cannot tell them apart)."""
    prefix = scene.prefix
    key, recipe = f"{prefix}/rows/rows.json", f"{prefix}/generate/canopy.json"
    if not (store.isfile(key) and store.isfile(recipe)):
        return {}
    table = store.get_json(key)
    answer, params = table.get("answer_params") or {}, store.get_json(recipe)["params"]
    if set(answer) != set(params) or any(
        not math.isclose(float(answer[k]), float(params[k]), rel_tol=1e-9) for k in answer
    ):
        return {}
    stages = store.load_manifest(scene).stages if store.isfile(manifest_key(scene)) else {}
    built = stages.get("generate")
    if built is not None and built.inputs:  # older manifests: the parameters decide alone
        combined = f"{prefix}/rows/fit.json"
        if table.get("answer", "best") == "best":
            if combined in built.inputs:
                return {}
        else:
            stored = stages["rows"].artefacts.get(combined) if "rows" in stages else None
            if stored is None or built.inputs.get(combined) != stored:
                return {}
    spread = table["spread"]["lai"]
    return {
        "n_rows_fitted": table["n_rows"],
        "lai_rows_min": spread["min"],
        "lai_rows_max": spread["max"],
    }


def date_warnings(store: SceneStore, scene: SceneKey) -> list[str]:
    """The warnings of a date's last finished run, as its report lists them (too few photos,
    the row view's coverage, an answer on the box's edge, photos left out...); [] where the
    report predates the list, but for the row view's coverage, which its observation keeps
    (session 92's upgrade audit: a date of an older release showing 79 % of its row view
    without surface read with an empty note, the cleanest of the season)."""
    key = f"{scene.prefix}/report/warnings.json"
    try:
        if store.isfile(key):
            return [str(w) for w in store.get_json(key)]
        from cropcraft_core.observe import coverage_warning

        seen = _no_surface(store, f"{scene.prefix}/observe/")
        said = None if seen is None else coverage_warning(seen, scene.crop)
        return [said] if said else []
    except CropCraftError:
        return []


def _failure(store: SceneStore, scene: SceneKey, failed: list[str], earlier: bool) -> str:
    """A failed date's note: where its last run failed and why, and whether the values beside
    it are an earlier run's."""
    from tasks.common import STAGES

    stage = min(failed, key=lambda s: STAGES.index(s) if s in STAGES else len(STAGES))
    try:
        error = store.load_manifest(scene).stages[stage].error or "?"
    except (CropCraftError, KeyError):
        error = "?"
    kept = "; the values are its run's before" if earlier else ""
    return f"the last run failed at {stage}: {error}{kept}"


def write_summary(
    store: SceneStore, site: str, crop: str, refused: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """Season summary of every date whose metrics are done or whose last run failed:
    ``{site}/{crop}/season/summary.csv`` and ``summary.png``, with each date's share of the row
    view without a reconstructed surface, its surfaces' net cover against its photos, the
    parameters its fit was given and (where fitted over several rows) its LAI's range over the
    rows beside its traits; its ``status`` (done, failed) and a ``note``: the run's warnings,
    or where and why it failed (a failed rerun keeps the date's earlier answer, said so).
    Returns the keys and the rows."""
    from cropcraft_core.report import given_text, season_csv, season_plot_png, season_rows

    per_date = {}
    refused = dict(refused or {})
    for d in store.discover(site, crop, with_runs=True):  # ad hoc runs' dates too
        key = f"{d.scene.prefix}/metrics/metrics.json"
        failed = [s for s, status in d.stages.items() if status == "failed"]
        done = d.stages.get("metrics") == "done" and store.isfile(key)
        if not done and not failed and d.scene.date not in refused:  # not run yet, running
            continue
        bad = failed or d.scene.date in refused
        entry: dict[str, Any] = {"status": "failed" if bad else "done"}
        if store.isfile(key):  # a failed rerun keeps the last answer, flagged
            prefix = d.scene.prefix
            fit = _stored_json(store, f"{prefix}/fit/fit.json")
            consistency = _stored_json(store, f"{prefix}/consistency/consistency.json")
            rowfit = _stored_json(store, f"{prefix}/rowfit/rowfit.json")
            entry.update(
                store.get_json(key),
                parameters_given=given_text((fit.get("config") or {}).get("box")),
                no_surface_fraction=_no_surface(store, f"{prefix}/observe/"),
                # the surfaces' net cover against the photos (extra − unreconstructed)
                photo_net_cover=consistency.get("net"),
                # where the date's metric scale came from (the row fit's)
                scale_source=rowfit.get("scale_source"),
                **_rows(store, d.scene),
            )
        if d.scene.date in refused:  # refused tonight before any work (its field notes...)
            kept = "; the values are its run's before" if store.isfile(key) else ""
            entry["note"] = f"not run: {refused[d.scene.date]}{kept}"
        elif failed:
            entry["note"] = _failure(store, d.scene, failed, store.isfile(key))
        else:
            entry["note"] = "; ".join(date_warnings(store, d.scene))
        per_date[d.scene.date] = entry
    rows = season_rows(per_date)
    csv_key = f"{site}/{crop}/season/summary.csv"
    png_key = f"{site}/{crop}/season/summary.png"
    store.put_bytes(csv_key, season_csv(rows).encode("utf-8"))
    plotted = any(r.get("lai_m2_m2") is not None for r in rows)
    if plotted:
        store.put_bytes(png_key, season_plot_png(rows, f"{site} {crop}"))
    elif store.exists(png_key):  # no date has results now: an older plot would show them still
        store.delete(png_key)
    return {
        "csv": store.url(csv_key),
        "png": store.url(png_key) if plotted else None,
        "rows": rows,
    }


@flow(name="process-season", flow_run_name="{site}/{crop} season", persist_result=False)
def process_season(
    site: str,
    crop: str,
    store: str | None = None,
    overrides: dict[str, Any] | None = None,
    runner: str = DEFAULT_RUNNER,
    surfaces_backend: SurfacesBackend | None = None,
) -> Any:
    """Run :func:`flows.scene.reconstruct_scene` as a subflow for every date of ``site``/``crop``
    that has photos in the store (``{site}/{crop}/{date}/images/``, with an optional
    ``transforms.json`` beside them) and no finished report, or an inbox changed since its
    report (:func:`pending_dates`), one after another, on ``runner``;
    a failed date does not stop the others. Then write the season summary. surfaces_backend:
    as :func:`flows.scene.reconstruct_scene`'s (a GPU deployment's nerfacto).

    Returns ``{"scenes": {date: final state, with the reason where not Completed}, "failed":
    [dates], "misnamed": [folders], "csv": URL, "png": URL or None}``; where a date failed, or
    the summary could not be written, as the data of a Failed state, so the run reads Failed in
    the UI and its alerts fire (:func:`run_season` returns the record either way).
    """
    from cropcraft_core.lease import refuse_if_busy
    from cropcraft_core.store import SceneBusyError
    from flows.runners import make_task_runner
    from flows.scene import (
        default_images_uri,
        notes_overridden,
        prepare,
        read_known,
        reconstruct_scene,
        with_backend,
    )

    log = get_run_logger()
    overrides = with_backend(overrides, surfaces_backend)
    st = SceneStore.connect(store)
    misnamed = st.misnamed_dates(site, crop)
    for name in misnamed:
        log.warning(
            "%s/%s/%s has photos but is not a date (YYYY-MM-DD, a real day): not processed; "
            "rename the folder",
            site,
            crop,
            name,
        )
    for name in (astray := st.photos_out_of_place(site, crop)):
        log.warning(
            "%s/%s/%s holds photos, but its date has no images/ inbox: not processed; move "
            "them into %s/%s/%s/images/",
            site, crop, name, site, crop, name.partition("/")[0],
        )  # fmt: skip
    dates = pending_dates(st, site, crop)
    unchanged = [
        d.scene.date
        for d in st.discover(site, crop, with_runs=True)
        if d.scene.date not in dates and d.stages.get("report") == "done"
    ]
    log.info("%s/%s: %d date(s) to process: %s", site, crop, len(dates), ", ".join(dates))
    warnings = []
    # a scene run from photos kept elsewhere (cropcraft run --images URI) is one too: its date
    # is in the summary written below, so the warning would contradict it
    empty = (
        not dates and not misnamed and not astray and not st.list_dates(site, crop, with_runs=True)
    )
    if empty:
        # a worker without CROPCRAFT_STORE reads its own ./cropcraft-data: nothing, every night
        like = st.sites_like(site)  # or the site typed in another case (plota for PlotA)
        warnings.append(
            f"{site}/{crop} has no dated scene in the store {st.url('')}: "
            + (
                f"the store holds {' and '.join(like)}, spelled otherwise (site names are "
                "case-sensitive)"
                if like
                else "is it the store the photos are uploaded to (CROPCRAFT_STORE on the "
                "worker, or the flow's store parameter)?"
            )
        )
        log.warning("%s", warnings[-1])
    stale = stale_dates(st, site, crop, overrides, dates)
    if stale:
        warnings.append(
            f"{len(stale)} finished date(s) hold results that these settings (or this release) "
            f"would not give: {', '.join(stale)}; the season runs only new or changed photos, "
            f"so their answers stand in the summary as they were: `cropcraft run {site}/{crop}/"
            "DATE` with the same settings recomputes one (what did not change stays cached)"
        )
        log.warning("%s", warnings[-1])
    scenes: dict[str, str] = {}
    refused: dict[str, str] = {}  # dates refused before any work, and why
    notes: dict[str, list[str]] = {}
    failed = []
    busy: list[str] = []  # dates another run holds tonight: that run answers them
    sub = reconstruct_scene.with_options(task_runner=make_task_runner(runner))
    for date in dates:
        try:
            refuse_if_busy(st, SceneKey(site, crop, date))
        except SceneBusyError as exc:
            # not a failure: two overlapping seasons each ended Failed, their alerts firing,
            # for the date the other was running, which both then listed done (session 93's
            # overlap audit)
            scenes[date] = f"busy: {exc}"
            busy.append(date)
            log.warning("%s/%s/%s not run: %s", site, crop, date, exc)
            continue
        try:
            prepare(site, crop, date, None, None, overrides, store)
        except CropCraftError as exc:
            refused[date] = str(exc)
            scenes[date] = f"invalid: {exc}"
            failed.append(date)
            log.error("%s/%s/%s not run: %s", site, crop, date, exc)
            continue
        state = sub(
            site=site,
            crop=crop,
            date=date,
            overrides=dict(overrides or {}),
            store=store,
            return_state=True,
        )
        # what the UI and the CLI print: the final state, with the reason where it failed
        scenes[date] = state.name if state.is_completed() else f"{state.name}: {state.message}"
        if not state.is_completed() and "SceneBusyError" in (state.message or ""):
            busy.append(date)  # taken by another run between the check above and its start
            log.warning("%s/%s/%s not run: %s", site, crop, date, state.message)
        elif not state.is_completed():
            failed.append(date)
            log.error("%s/%s/%s failed: %s", site, crop, date, state.message)
        else:  # its warnings, with its line: a 3-photo date read "Completed" like any other
            notes[date] = date_warnings(st, SceneKey(site, crop, date))
        # the season's --param over a date's field notes: said (the breeder's count went quietly)
        over = notes_overridden(
            read_known(default_images_uri(st, SceneKey(site, crop, date)), crop), overrides
        )
        for line in over:
            log.warning("%s/%s/%s: %s", site, crop, date, line)
        notes[date] = over + notes.get(date, [])
    out: dict[str, Any] = {
        "scenes": scenes,
        "notes": {d: w for d, w in notes.items() if w},
        "unchanged": unchanged,
        "failed": failed,
        "busy": busy,
        "misnamed": misnamed,
        "astray": astray,
        "warnings": warnings,
    }
    if empty and not st.exists(f"{site}/{crop}/{SEASON_FOLDER}"):
        # nothing to summarise: a mistyped site's run wrote an empty summary, making a folder
        # for a site that is not there (session 94's folders audit)
        out.update(csv=None, png=None, summary_note=f"no dated scene of {site}/{crop}")
    else:
        try:
            summary = write_summary(st, site, crop, refused)
            out.update(csv=summary["csv"], png=summary["png"])
            from flows.artifacts import publish_season

            ran = ", ".join(f"{d} {s.partition(':')[0]}" for d, s in scenes.items())
            publish_season(
                summary["rows"],
                site,
                crop,
                f"{site}/{crop} season, {len(summary['rows'])} date(s); this run: {ran or 'none'}",
                log,
            )
        except CropCraftError as exc:  # the dates' own results stand; the cause is named
            log.error("%s/%s: the season summary was not written: %s", site, crop, exc)
            out.update(csv=None, png=None, summary_error=str(exc))
    problems = []
    if failed:
        # each with its reason: the run's state message is what the UI's run list, `prefect
        # flow-run inspect` and an automation's alert show; it named the dates only (session
        # 92's deployment audit), and the result that held the reasons is not persisted
        why = "; ".join(f"{d} ({scenes[d]})" for d in failed)
        problems.append(f"{len(failed)} of {len(dates)} date(s) failed: {why}")
    if "summary_error" in out:
        problems.append("the season summary was not written")
    return Failed(message="; ".join(problems), data=out) if problems else out


def run_season(
    site: str,
    crop: str,
    store: str | None = None,
    overrides: dict[str, Any] | None = None,
    runner: str = DEFAULT_RUNNER,
    surfaces_backend: SurfacesBackend | None = None,
) -> dict[str, Any]:
    """Validate (names, store, settings), then run :func:`process_season`."""
    from cropcraft_core.store import SceneKey
    from flows.runners import parse_runner
    from flows.scene import resolve_config, with_backend

    SceneKey(site, crop, "2000-01-01")
    resolve_config(crop, with_backend(overrides, surfaces_backend))
    parse_runner(runner)
    unopened = SceneStore(store)
    if unopened._local and not unopened.fs.isdir(unopened._root_path):
        # the photos are uploaded into the store: a folder not there is a mistyped --store,
        # which made itself and reported an empty season, exit 0, every night
        raise InputError(f"no store at {unopened.root}: check --store (or CROPCRAFT_STORE)")
    SceneStore.connect(store)
    state = process_season(
        site, crop, store, dict(overrides or {}), runner, surfaces_backend, return_state=True
    )
    out = state.result(raise_on_failure=False)
    if isinstance(out, BaseException):  # the flow itself broke (not a date): its own error
        raise out
    return {**out, "state": state.name, "message": state.message}
