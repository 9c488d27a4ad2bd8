"""The development archive (the ``archive`` preset): every labelled photo set of ../shared/data and
rendered landmarks shuffled into one flat folder under opaque names, its runs, and what is read from
their models: each label's photos per model, the models that mix labels.

A label is a place: photos of one label may end in one model, photos of two labels never. Sets that
show one place under two names are one label (``SAME_PLACE``); a WxBS pair is a label of its own
(its two photos show one scene), as is each rendered landmark.
"""

from __future__ import annotations

import json
import os
import random
import re
import shutil
import sys
import time
from collections import Counter
from collections.abc import Callable
from fnmatch import fnmatch
from pathlib import Path, PurePosixPath

from colmap_guided.features import list_images
from colmap_guided.paths import shared_data_dir
from recon_scripts.evaluation.registration import method_slug
from recon_scripts.evaluation.tables import write_json
from recon_scripts.scale.measure import run_measured
from recon_scripts.scale.photos import render_landmarks
from recon_scripts.scale.stage import CHECKOUT

# the landmark sets of ../shared/data, each a label (its folder's name) unless merged below
LANDMARK_SETS = (
    "sacre_coeur_hloc",
    "sceaux_castle",
    "opensfm_lund",
    "lund_door_gtsfm",
    "opensfm_berlin",
    "gtsfm_1dsfm_sample",
)
# labels of one place: each merged into the place's label (a model joining them is right)
SAME_PLACE = {
    "sacre_coeur_hloc": "sacre_coeur",
    "train:dfsfm_sacre_coeur": "sacre_coeur",
    "lightglue:sacre_coeur": "sacre_coeur",
    "opensfm_berlin": "berliner_dom",
    "wxbs:berlin": "berliner_dom",  # the Dom by day and lit at night
    "train:strecha_entry_P10": "train:strecha_castle",  # the courtyard's entry, seen in the castle
    "train:cut3r_kitchen": "train:cut3r_flat",  # two rooms of one flat
    "train:cut3r_livingroom": "train:cut3r_flat",
    "gtsfm_1dsfm_sample": "alamo",  # four photos of 1DSfM's Alamo set
}
# ALIKED's 1,024 best keypoints on photos sized to 1,024 px (default 2,048 at 1,600 px)
ALIKED_1024 = ["--aliked_max_num_keypoints", "1024", "--aliked_max_image_size", "1024"]
# reconstruct's flags of a named run of the archive (``runs``): the default, the default with one
# decision undone or changed, to print what it changes
RUNS = {
    "default": [],
    "orphans_kept": ["--orphan_after", "none"],
    "aliked_1024": ALIKED_1024,
    # aliked_1024, pairs with fewer than 10 cheap matches in the window left to escalation, and
    # global mapping once (auto runs both mappers where the largest model fails the check)
    "hour_other_models": [*ALIKED_1024, "--cheap_matches", "10", "--mapper", "global"],
    # and escalation for the photos in no model only (the join links models)
    "hour": [*ALIKED_1024, "--cheap_matches", "10", "--mapper", "global", "--no_other_models"],
}
# a label run on its own (the reference its archive model is compared with) from this many photos
MIN_ALONE = 3
# the share of a label's photos of its own run that one archive model must hold
GOAL = 0.95


def _files(folder: Path) -> list[Path]:
    return [folder / name for name in list_images(folder)]


def real_sources(root: Path | None = None) -> list[tuple[str, Path]]:
    """(label, photo) of every labelled photo of ``root`` (../shared/data), in a fixed order."""
    root = Path(root or shared_data_dir()).absolute()
    out = [(s, f) for s in LANDMARK_SETS for f in _files(root / s / "images")]
    for card in sorted((root / "postcards_cmahnke").glob("*/images")):
        out += [(f"postcards:{card.parent.name}", f) for f in _files(card)]
    for scene in sorted((root / "train").glob("*/images")):
        out += [(f"train:{scene.parent.name}", f) for f in _files(scene)]
    for f in _files(root / "phototourism_superglue" / "images"):
        # <landmark>_<id>_<id>.jpg
        out.append((f"phototourism:{re.sub(r'(_[0-9]+){2}$', '', f.stem)}", f))
    for f in _files(root / "lightglue_assets" / "images"):
        out.append((f"lightglue:{re.sub(r'_?[0-9]+$', '', f.stem)}", f))
    for pair in sorted(p for p in (root / "wxbs_v1.1").glob("*/*") if p.is_dir()):
        # a pair's second version (kettle2, submarine2) and a category's other pair of one view
        # (kyiv) are the same scene: the pair's name without its number
        out += [(f"wxbs:{re.sub(r'[0-9]+$', '', pair.name)}", f) for f in _files(pair)]
    return [(SAME_PLACE.get(label, label), f) for label, f in out]


def plan_archive(sources: list[tuple[str, Path]], seed: int) -> dict[str, tuple[str, Path]]:
    """{opaque name: (label, photo)}: the photos shuffled (seeded), named p0001.jpg ... in that
    order, each with its own suffix."""
    order = list(sources)
    random.Random(seed).shuffle(order)
    width = max(4, len(str(len(order))))
    return {
        f"p{i:0{width}d}{f.suffix.lower()}": (label, f) for i, (label, f) in enumerate(order, 1)
    }


def build_archive(out: Path, photos: int, labels: list[str], seed: int) -> Path:
    """OUT/archive: ``images/`` (symlinks to the photos under opaque names, nothing else),
    ``labels.json`` {name: label}, ``sources.json`` {name: photo} and ``manifest.json`` (postcards
    historical). The real photos of the labels matching a pattern of ``labels`` come first (the
    first ``photos`` of them), rendered landmarks (under OUT/synthetic) fill up to ``photos``.
    Built once: labels.json is written last."""
    archive = out / "archive"
    if (archive / "labels.json").exists():
        return archive
    real = [(lb, f) for lb, f in real_sources() if any(fnmatch(lb, p) for p in labels)][:photos]
    rendered = render_landmarks(out, photos - len(real))
    sources = real + [(f"rendered:{s['name']}", Path(f)) for s in rendered for f in s["files"]]
    if len(sources) < photos:
        raise ValueError(
            f"{len(sources)} photos for an archive of {photos}: choose more labels or fewer photos"
        )
    plan = plan_archive(sources, seed)
    images = archive / "images"
    tmp = archive / "images.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name, (_, f) in plan.items():
        (tmp / name).symlink_to(f)
    shutil.rmtree(images, ignore_errors=True)
    tmp.rename(images)
    write_json(archive / "sources.json", {name: str(f) for name, (_, f) in plan.items()})
    era = {True: "historical", False: "modern"}
    eras = [{"name": n, "era": era[lb.startswith("postcards:")]} for n, (lb, _) in plan.items()]
    write_json(archive / "manifest.json", {"images": eras})
    write_json(archive / "labels.json", {name: label for name, (label, _) in plan.items()})
    return archive


def sample_archive(archive: Path, out: Path, take: int) -> Path:
    """OUT: the first ``take`` names of ``archive`` (``build_archive``'s), the same photos under
    the same names and labels. Built once: labels.json is written last."""
    if (out / "labels.json").exists():
        return out
    labels = json.loads((archive / "labels.json").read_text())
    names = sorted(labels)[:take]
    shutil.rmtree(out / "images", ignore_errors=True)
    (out / "images").mkdir(parents=True)
    for name in names:
        (out / "images" / name).symlink_to(os.readlink(archive / "images" / name))
    sources = json.loads((archive / "sources.json").read_text())
    write_json(out / "sources.json", {name: sources[name] for name in names})
    eras = json.loads((archive / "manifest.json").read_text())["images"]
    write_json(out / "manifest.json", {"images": [e for e in eras if e["name"] in set(names)]})
    write_json(out / "labels.json", {name: labels[name] for name in names})
    return out


def reconstruct_run(scene: Path, out: Path, timeout: float, flags=()) -> dict:
    """``python -m colmap_guided reconstruct SCENE [flags]`` as a user runs it (from scratch, the
    machine's threads) into ``out``, measured (run_measured) with report.json's timings; kept in
    OUT.json, so a run that succeeded is not run again. {'failed': why} otherwise."""
    saved = out.with_suffix(".json")
    if saved.exists():
        return json.loads(saved.read_text())
    cmd = ["nice", "-n", "5", sys.executable, "-m", "colmap_guided", "reconstruct", str(scene)]
    cmd += ["--output", str(out), "--overwrite", *flags]
    path = os.pathsep.join(filter(None, [str(CHECKOUT), os.environ.get("PYTHONPATH")]))
    now = time.strftime("%H:%M:%S", time.gmtime())
    n = len(list_images(scene / "images"))
    print(f"[{now}] reconstruct {scene.name} ({n} photos)", flush=True)
    r = run_measured(cmd, {**os.environ, "PYTHONPATH": path}, timeout, out.with_suffix(".log"))
    if r["returncode"] != 0:
        why = "timed out" if r["returncode"] is None else f"exit {r['returncode']}"
        print(f"  failed ({why}; {out.with_suffix('.log')})", flush=True)
        return {"failed": why, **r}
    report = json.loads((out / "report.json").read_text())
    r.update(timings=report["timings"], num_images=n)
    print(
        f"  {r['wall']:.0f} s wall, {r['cpu']:.0f} s CPU, peak RSS {r['peak_rss_mb']} MB "
        f"(tree {r['peak_tree_rss_mb']} MB)",
        flush=True,
    )
    write_json(saved, r)
    return r


def photo_finder(photos) -> Callable[[str], str | None]:
    """image -> its archive photo of ``photos`` (names): itself, or the collage card of a panel
    (../WORKSPACE/panels/<card>_p<k>.jpg); None where it is neither."""
    stems = {PurePosixPath(n).stem: n for n in photos}

    def photo_of(image: str) -> str | None:
        base = PurePosixPath(image)
        card = re.fullmatch(r"(.+)_p[0-9]+", base.stem)
        return stems.get(base.stem) or (stems.get(card[1]) if card else None)

    return photo_of


def label_of(labels: dict[str, str] | None) -> Callable[[str], str | None]:
    """image -> the archive label of its photo (``photo_finder``; None: no labels or no photo)."""
    photo_of = photo_finder(labels or {})
    return lambda image: labels.get(photo_of(image)) if labels else None


def read_models(sparse: Path, photos) -> dict[str, set[str]]:
    """{model folder: the photos registered in it} of every model in SPARSE/*/ (pycolmap)."""
    import pycolmap

    photo_of = photo_finder(photos)
    models = {}
    for folder in sorted(p for p in Path(sparse).glob("*") if (p / "images.bin").exists()):
        rec = pycolmap.Reconstruction(folder)
        registered = {photo_of(rec.images[i].name) for i in rec.reg_image_ids()}
        models[folder.name] = registered - {None}
    return models


def compare(
    labels: dict[str, str], archive: dict[str, set[str]], alone: dict[str, dict[str, set[str]]]
) -> dict:
    """Per label: its photos in the archive's models and, for a label run alone (``alone``: its
    models), how many of its own run's largest model one archive model holds; and the archive's
    models that hold photos of two labels or more."""
    by_label: dict[str, set[str]] = {}
    for name, label in labels.items():
        by_label.setdefault(label, set()).add(name)
    rows = {}
    for label, names in sorted(by_label.items()):
        row = {
            "photos": len(names),
            "registered_archive": len(names & set().union(*archive.values())),
            "archive_models": sorted(m for m, reg in archive.items() if reg & names),
        }
        if label in alone:
            own = max(alone[label].values(), key=len, default=set())
            best = max(archive, key=lambda m: len(own & archive[m]), default=None)
            held = len(own & archive[best]) if best is not None else 0
            row.update(
                registered_alone=len(own),
                registered_alone_all=len(set().union(*alone[label].values())),
                best_model=best if held else None,
                in_best_model=held,
                ratio=held / len(own) if own else None,
                ok=held >= GOAL * len(own) if own else None,
            )
        rows[label] = row
    mixing = []
    for model, reg in archive.items():
        counts = {lb: len(reg & names) for lb, names in sorted(by_label.items()) if reg & names}
        if len(counts) > 1:
            mixing.append({"model": model, "photos": len(reg), "labels": counts})
    checked = [r for r in rows.values() if r.get("ok") is not None]
    return {
        "labels": rows,
        "mixing": mixing,
        "labels_checked": len(checked),
        "labels_ok": sum(r["ok"] for r in checked),
        "archive_models": len(archive),
    }


def run_archive(archive: Path, out: Path, alone, timeout: float, flags=()) -> dict:
    """The archive reconstructed in one run (OUT/run, with reconstruct's ``flags``), then each
    label of at least MIN_ALONE photos that matches a pattern of ``alone`` (fnmatch; empty: none)
    alone with the same flags (ARCHIVE/../alone/<label>/run, or run_<OUT's name> with flags; its
    photos under their archive names): what sorting the photos by hand would have given the same
    settings; and their comparison."""
    labels = json.loads((archive / "labels.json").read_text())
    result = {"archive": reconstruct_run(archive, out / "run", timeout, flags), "alone": {}}
    by_label: dict[str, list[str]] = {}
    for name, label in labels.items():
        by_label.setdefault(label, []).append(name)
    own_models = {}
    for label, names in sorted(by_label.items()):
        if len(names) < MIN_ALONE or not any(fnmatch(label, p) for p in alone or ()):
            continue
        scene = archive.parent / "alone" / method_slug(label)
        if not (scene / "images").is_dir():
            tmp = scene / "images.partial"
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            for name in names:
                (tmp / name).symlink_to(os.path.relpath(archive / "images" / name, tmp))
            tmp.rename(scene / "images")
        own = scene / (f"run_{out.name}" if flags else "run")
        r = result["alone"][label] = reconstruct_run(scene, own, timeout, flags)
        own_models[label] = {} if "failed" in r else read_models(own / "sparse", names)
    if "failed" not in result["archive"]:
        models = read_models(out / "run" / "sparse", labels)
        result["comparison"] = compare(labels, models, own_models)
        result["costs"] = photo_costs(out / "run")
        result["pairs"] = label_pairs(out / "run", labels)
        result["cuts"] = label_cuts(out / "run", labels)
    return result


def label_cuts(workspace: Path, labels: dict[str, str]) -> list[dict]:
    """The models the run of ``workspace`` cut in two: the labels of each side's photos (counts),
    and the cut's conflicts and agreements."""
    report = json.loads((workspace / "report.json").read_text())
    label = label_of(labels)
    return [
        {
            "sides": [dict(Counter(label(n) or "?" for n in side)) for side in cut["photos"]],
            "conflicts": cut["conflicts"],
            "agreements": cut["agreements"],
        }
        for cut in report["database"].get("splits", [])
    ]


def label_pairs(workspace: Path, labels: dict[str, str]) -> dict:
    """The pairs verified in the run of ``workspace`` across two labels and within one: how many,
    their inliers (median, largest). A pair across labels is two places that look alike."""
    from colmap_guided import database as dbio

    label = label_of(labels)
    with dbio.open_database(workspace / "database.db") as db:
        names = dbio.image_names(db)
        inliers = dbio.pair_inlier_counts(db)
    found = {"across": [], "within": []}
    for pair, n in inliers.items():
        a, b = (label(names[i]) for i in pair)
        if a is not None and b is not None:
            found["across" if a != b else "within"].append(n)
    return {
        k: {"pairs": len(v), "median": sorted(v)[len(v) // 2] if v else 0, "max": max(v, default=0)}
        for k, v in found.items()
    }


def photo_costs(workspace: Path) -> dict:
    """What a photo in no model and a placed photo cost in the run of ``workspace``: photos, pairs
    the matcher ran on per photo (a pair counts for each of its photos; first pass, escalation and
    join), those of them the full matcher (LightGlue) matched, not a cheap decision, and the
    seconds of matching (first pass and escalation) that their pairs took, shared evenly by the
    pairs; and the photos that matching took for orphans."""
    from colmap_guided import database as dbio
    from colmap_guided import escalate
    from colmap_guided.mapping import load_models, registered

    report = json.loads((workspace / "report.json").read_text())
    with dbio.open_database(workspace / "database.db") as db:
        names = dbio.image_names(db)
    pairs = [[names[i] for i in pair] for pair in dbio.written_pairs(workspace / "database.db")]
    kept = escalate.read_kept(workspace / escalate.KEPT_PAIRS)
    placed = set().union(*map(registered, load_models(workspace / "sparse").values()))
    per_photo = Counter(name for pair in pairs for name in pair)
    full = Counter(name for pair in pairs if frozenset(pair) not in kept for name in pair)
    t = report["timings"]
    per_pair = (t.get("match", 0) + t.get("escalate_match", 0)) / max(len(pairs), 1)
    costs = {}
    for what, photos in (("placed", placed), ("in no model", set(names.values()) - placed)):
        n = sum(per_photo[name] for name in photos)
        costs[what] = {
            "photos": len(photos),
            "pairs_per_photo": n / max(len(photos), 1),
            "lightglue_per_photo": sum(full[name] for name in photos) / max(len(photos), 1),
            "seconds_per_photo": n * per_pair / max(len(photos), 1),
        }
    costs["orphans"] = len(report["database"].get("orphans", []))
    costs["seconds_per_pair"] = per_pair
    return costs


def _s(timings: dict, *keys: str) -> str:
    return f"{sum(timings.get(k, 0) for k in keys):.0f}"


def _run_row(what: str, runs: list[dict], registered: str) -> str:
    """A table row of one run or several summed: photos, stage times, memory."""
    t: dict[str, float] = {}
    for r in runs:
        for k, v in r["timings"].items():
            t[k] = t.get(k, 0) + v
    wall, cpu = sum(r["wall"] for r in runs), sum(r["cpu"] for r in runs)
    return (
        f"| {what} | {sum(r['num_images'] for r in runs)} | {wall:.0f} ({cpu:.0f}) "
        f"| {_s(t, 'extract')} | {_s(t, 'match')} | {_s(t, 'verify')} | {_s(t, 'map')} "
        f"| {_s(t, 'escalate_match', 'escalate_map')} | {_s(t, 'join')} "
        f"| {max(r['peak_rss_mb'] for r in runs)} / {max(r['peak_tree_rss_mb'] for r in runs)} "
        f"| {registered} |"
    )


def archive_report(n: int, result: dict) -> list[str]:
    """Markdown: per label its photos in the archive's models against its own run, the models
    that mix labels, time per stage and peak memory."""
    run = result["archive"]
    if "failed" in run:
        return [f"N={n}: the archive run failed ({run['failed']})"]
    c = result["comparison"]
    lines = [
        f"**Archive of {run.get('num_images', n)} photos, {len(c['labels'])} labels**: "
        f"{c['labels_ok']} of "
        f"{c['labels_checked']} labels run alone have ≥ {GOAL:.0%} of their model's photos in "
        f"one archive model; {len(c['mixing'])} of {c['archive_models']} models mix labels.",
        "",
        "| label | photos | alone: registered (largest model / all) | archive: of those in one "
        f"model (model) | ratio | ≥ {GOAL:.0%} | archive: registered (models) |",
        "|---|---|---|---|---|---|---|",
    ]
    for label, r in c["labels"].items():
        archive = f"{r['registered_archive']} ({', '.join(r['archive_models']) or '–'})"
        if "registered_alone" not in r:
            failed = "failed" if label in result["alone"] else "not run"
            lines.append(f"| {label} | {r['photos']} | {failed} | – | – | – | {archive} |")
            continue
        ratio = "–" if r["ratio"] is None else f"{r['ratio']:.0%}"
        ok = {True: "yes", False: "**no**", None: "–"}[r["ok"]]
        lines.append(
            f"| {label} | {r['photos']} | {r['registered_alone']} / {r['registered_alone_all']} "
            f"| {r['in_best_model']} ({r['best_model'] or '–'}) | {ratio} | {ok} | {archive} |"
        )
    pairs = result.get("pairs")
    if pairs:
        a, w = pairs["across"], pairs["within"]
        lines += [
            "",
            f"Pairs verified across two labels: {a['pairs']} (inliers: median {a['median']}, "
            f"largest {a['max']}); within one label: {w['pairs']} (median {w['median']}).",
        ]
    cuts = result.get("cuts") or []
    lines += ["", "Models cut in two (labels of each side; conflicts / agreements):", ""]
    lines += [
        "- "
        + " | ".join(
            ", ".join(f"{lb} {k}" for lb, k in sorted(side.items())) for side in c["sides"]
        )
        + f" ({c['conflicts']} / {c['agreements']})"
        for c in cuts
    ] or ["- none"]
    lines += ["", "Models that mix labels:", ""]
    lines += [
        f"- model {m['model']} ({m['photos']} photos): "
        + ", ".join(f"{lb} {k}" for lb, k in m["labels"].items())
        for m in c["mixing"]
    ] or ["- none"]
    own = [r for r in result["alone"].values() if "failed" not in r]
    lines += [
        "",
        "| run | photos | wall s (CPU s) | extract s | match s | verify s | map s | escalation s "
        "| join s | peak RSS MB: largest process / tree | registered (models) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        _run_row(
            "archive, one run",
            [run],
            f"{sum(r['registered_archive'] for r in c['labels'].values())} ({c['archive_models']})",
        ),
    ]
    if own:
        registered = sum(r.get("registered_alone_all", 0) for r in c["labels"].values())
        lines.append(_run_row(f"each label alone ({len(own)} runs, summed)", own, f"{registered}"))
    return lines


def costs_report(results: dict) -> list[str]:
    """Markdown: per named run of the archive (``RUNS``), what a photo in no model and a placed
    photo cost (``photo_costs``)."""
    lines = [
        "| run | photos placed / in no model (orphans) | pairs per photo: placed / in no model "
        "| of them LightGlue's | matching s per photo: placed / in no model | s per pair "
        "| wall s |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, result in results.items():
        c = result.get("costs")
        if c is None:
            lines.append(f"| {name} | failed | – | – | – | – | – |")
            continue
        p, o = c["placed"], c["in no model"]
        lines.append(
            f"| {name} | {p['photos']} / {o['photos']} ({c['orphans']}) "
            f"| {p['pairs_per_photo']:.1f} / {o['pairs_per_photo']:.1f} "
            f"| {p['lightglue_per_photo']:.1f} / {o['lightglue_per_photo']:.1f} "
            f"| {p['seconds_per_photo']:.1f} / {o['seconds_per_photo']:.1f} "
            f"| {c['seconds_per_pair']:.2f} | {result['archive']['wall']:.0f} |"
        )
    return lines
