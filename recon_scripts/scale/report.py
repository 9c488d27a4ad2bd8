"""The scale benchmark's Markdown tables (per N, projected exhaustive matching, mappers, executors),
read from the stage JSONs, and its plot."""

from __future__ import annotations

import json
from pathlib import Path

from recon_scripts.scale.measure import verified_pairs
from recon_scripts.scale.photos import composition
from recon_scripts.scale.plot import plot

MODES = ("retrieval", "exhaustive")
MAPPERS = ("incremental", "global", "hierarchical")


def _json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.exists() else None


def _loads(r: dict) -> str:
    """The 1-minute load before and after a run: 'before–after'."""
    return f"{r['load_before'].split('/')[0]}–{r['load_after'].split('/')[0]}"


def report(out: Path, ns: list[int], k: int) -> str:
    """Markdown tables (returned and OUT/report.md) and OUT/scale.png from the stage JSONs."""
    lines, rows, per_pair = _stage_table(out, ns, k)
    lines += _projection_table(per_pair, ns) + _mapping_table(out, ns)
    executors = [
        row
        for path in sorted(out.glob("n*/executors/result.json"))
        for row in json.loads(path.read_text())["rows"]
    ]
    if executors:
        lines += ["", *executors_table(executors)]
    text = "\n".join(lines)
    (out / "report.md").write_text(text + "\n")
    if rows or executors:  # (the pool alone: nothing to plot)
        plot(out / "scale.png", rows, executors, per_pair)
    return text


def _stage_table(out: Path, ns: list[int], k: int) -> tuple[list[str], dict, dict]:
    """The table per N and pair selection; the plot's {(n, mode): times and memory}; exhaustive
    matching's {n: (wall s, CPU s) per pair}."""
    pool = json.loads((out / "pool.json").read_text())
    lines = [
        "| N (photos) | pairs | pairs matched (of exhaustive) | "
        "verified (exhaustive's kept) | extract s | select s | match s | verify s | "
        "map (global) s | total s (CPU s) | peak RSS: run / match stage (start) MB | "
        "images held max / reads | registered (train + rendered) | models | load 1-min |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    per_pair, rows = {}, {}
    for n in ns:
        ex = _json(out / f"n{n}" / "extract.json")
        for mode in MODES:
            m = _json(out / f"n{n}" / mode / "match.json")
            g = _json(out / f"n{n}" / mode / "map_global.json")
            if ex is None or m is None:
                continue
            if mode == "exhaustive":
                pure_match = m["match_time"] + m["verify_time"]
                per_pair[n] = (pure_match / m["num_pairs"], m["cpu"] / m["num_pairs"])
            rows[(n, mode)] = _plot_row(ex, m, g)
            label = mode + (f" k={k}" if mode == "retrieval" else "")
            kept = _kept(out / f"n{n}", mode)
            photos = composition(pool, n)
            lines.append(_stage_row(n, photos, label, kept, (ex, m, g), rows[(n, mode)]))
    return lines, rows, per_pair


def _plot_row(ex: dict, m: dict, g: dict | None) -> dict:
    """Times (s) and memory of one N and pair selection, its stages summed."""
    stages = [r for r in (ex, m, g) if r]
    return {
        "extract": ex["wall"],
        "select": m["select_time"],
        "match": m["match_time"],
        "verify": m["verify_time"],
        "map": g["wall"] if g else None,
        "total": sum(r["wall"] for r in stages),
        "cpu": sum(r["cpu"] for r in stages),
        "rss_match": m["peak_rss_mb"],
        "rss_run": max(r["peak_rss_mb"] for r in stages),
        "held": (m.get("memory") or {}).get("images_held_max"),
    }


def _kept(set_dir: Path, mode: str) -> str:
    """'<kept>/<all>' of exhaustive's verified pairs that ``mode`` verified; '–' without
    exhaustive."""
    exhaustive = set_dir / "exhaustive"
    if not (exhaustive / "match.json").exists():
        return "–"
    truth = verified_pairs(exhaustive / "database.db")
    return f"{len(verified_pairs(set_dir / mode / 'database.db') & truth)}/{len(truth)}"


def _stage_row(n: int, photos: str, label: str, kept: str, runs: tuple, row: dict) -> str:
    """One row of the table per N; ``runs``: the extract, match and global map JSONs (None: not
    mapped)."""
    ex, m, g = runs
    stages = [r for r in runs if r]
    mem = m.get("memory") or {}
    reg = (
        f"{g['registered']}/{n} ({g['registered_train']} + {g['registered_synthetic']})"
        if g
        else "–"
    )
    loads = [float(r[key].split("/")[0]) for r in stages for key in ("load_before", "load_after")]
    mapped = f"{g['wall']:.0f}" if g else "–"
    head = (
        f"| {n} ({photos}) | {label} | {m['num_pairs']} ({m['num_pairs'] / (n * (n - 1) / 2):.1%}) "
        f"| {m['num_verified_pairs']} ({kept}) | {ex['wall']:.0f} | {m['select_time']:.0f} "
        f"| {m['match_time']:.0f} | {m['verify_time']:.0f} | {mapped} | "
    )
    return head + (
        f"{row['total']:.0f} ({row['cpu']:.0f}) | {row['rss_run']} / "
        f"{m['peak_rss_mb']} ({m['rss_start_mb']}) | "
        f"{mem.get('images_held_max', '–')} / {mem.get('image_reads', '–')} | {reg} | "
        f"{g['num_models'] if g else '–'} | {min(loads):.1f}–{max(loads):.1f} |"
    )


def _projection_table(per_pair: dict, ns: list[int]) -> list[str]:
    """Exhaustive matching per N projected from its time per pair at the smallest N measured."""
    if not per_pair:
        return []
    n0 = min(per_pair)
    wall_pp, cpu_pp = per_pair[n0]
    lines = [
        "",
        f"Exhaustive matching projected from its measured time per pair at N={n0} "
        f"({wall_pp:.2f} s wall match + verify per pair, {cpu_pp:.2f} s CPU with "
        "selection): a projection, not a measurement:",
        "",
        "| N | exhaustive pairs | projected match + verify h (wall, this load) | projected CPU h |",
        "|---|---|---|---|",
    ]
    for n in ns:
        pairs = n * (n - 1) // 2
        lines.append(
            f"| {n} | {pairs} | {pairs * wall_pp / 3600:.1f} | {pairs * cpu_pp / 3600:.1f} |"
        )
    return lines


def _mapping_table(out: Path, ns: list[int]) -> list[str]:
    """Every mapper run per N and pair selection."""
    mapping = [
        (n, mode, r)
        for n in ns
        for mode in MODES
        for mapper in MAPPERS
        if (r := _json(out / f"n{n}" / mode / f"map_{mapper}.json"))
    ]
    if not mapping:
        return []
    lines = [
        "",
        "| N | pairs | mapper | wall s (CPU s) | models | registered (train + rendered) | "
        "largest model | photos in a verified pair | peak RSS MB | load 1-min |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n, mode, r in mapping:
        lines.append(
            f"| {n} | {mode} | {r['mapper']} | {r['wall']:.0f} ({r['cpu']:.0f}) | "
            f"{r['num_models']} | {r['registered']} ({r['registered_train']} + "
            f"{r['registered_synthetic']}) | {r['largest']} | "
            f"{r['images_in_verified_pairs']} | {r['peak_rss_mb']} | {_loads(r)} |"
        )
    return lines


def _kind_round(r: dict) -> tuple[str, str]:
    """An executor row's kind (local or ray) and round."""
    return "local" if r["executor"] == "local" else "ray", r["config"].split("_r")[-1]


def executors_table(executors: list[dict]) -> list[str]:
    """Pairs/s per configuration and per worker against the same kind's 1-worker run."""
    base = {}
    for r in executors:
        if r["workers"] == 1:
            base.setdefault(_kind_round(r), r)
    lines = [
        "| configuration | workers | pairs | match s | pairs/s | "
        "per worker vs 1 worker | same matches | load 1-min |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in executors:
        b = base.get(_kind_round(r))
        ratio = r["pairs_per_s"] / (r["workers"] * b["pairs_per_s"]) if b else float("nan")
        lines.append(
            f"| {r['config']} | {r['workers']} | {r['pairs']} | {r['match_time']:.0f} | "
            f"{r['pairs_per_s']:.2f} | {ratio:.2f} | {r['same_matches_as_local_1']} | "
            f"{_loads(r)} |"
        )
    return lines


def default_table(work: Path, ns: list[int]) -> list[str]:
    """One row per N of ``reconstruct`` end to end (the ``scale_default`` preset)."""
    lines = [
        "| N (photos) | pairs: selected / matched / verified | extract s | match s | verify s "
        "| map s | escalation s | total s (CPU s) | peak RSS MB | registered: largest (train + "
        "rendered) / all models | models | load 1-min |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for n in ns:
        path = Path(work) / f"n{n}" / "default" / "reconstruct.json"
        if not path.exists():
            continue
        r = json.loads(path.read_text())
        t = r["timings"]
        escalation = t.get("escalate_match", 0) + t.get("escalate_map", 0)
        loads = [float(r[k].split("/")[0]) for k in ("load_before", "load_after")]
        lines.append(
            f"| {n} | {r['num_pairs']} / {r['num_pairs_matched']} / {r['num_verified_pairs']} "
            f"| {t['extract']:.0f} | {t['match']:.0f} | {t['verify']:.0f} | {t['map']:.0f} "
            f"| {escalation:.0f} | {r['wall']:.0f} ({r['cpu']:.0f}) | {r['peak_rss_mb']} "
            f"| {r['largest']} ({r['registered_largest_train']} + "
            f"{r['registered_largest_synthetic']}) / {r['registered']} | {r['num_models']} "
            f"| {min(loads):.1f}–{max(loads):.1f} |"
        )
    return lines
