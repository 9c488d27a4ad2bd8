"""What the coarse network and the cheap pass knew of the pairs LightGlue matched in a finished run:
which pairs a decision from them would have spared LightGlue, and what it would have lost.

    python -m recon_scripts.scale.pair_signals WORKSPACE [--labels LABELS.json]

For every pair of the run's database that the full matcher matched (written, not kept by a cheap
decision), the coarse pair score and the cheap pass's matches inside eq. 1's window are computed
again (the run's features and options), beside the inliers the run verified. Per rule "leave the
pair where the cheap pass finds fewer than C matches or the coarse score is below S": LightGlue
calls spared, verified and strong (100+ inliers) pairs lost, photos placed in the run whose every
verified pair is lost, and with the archive's labels (``recon_scripts archive``) lost pairs within
one label and across two. With the labels also the verified pairs' inlier share (inliers over
matches) within one label and across two, rendered landmarks apart from real photos.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from recon_scripts.scale.archive import label_of

CHEAP = (None, 10, 20, 40, 80)
SCORE = (None, 0.1, 0.15, 0.2)


def signals(workspace: Path) -> list[dict]:
    """Per full-matcher pair: names, coarse pair score, the cheap pass's matches and verified
    inliers, the run's inliers."""
    from colmap_guided import database as dbio
    from colmap_guided import escalate
    from colmap_guided.matchers import MATCHERS

    report = json.loads((workspace / "report.json").read_text())
    matcher = MATCHERS[report["matcher"]["name"]](report["matcher"]["conf"])
    verification = report["options"]["verification"]
    kept = escalate.read_kept(workspace / "kept_pairs.jsonl")
    with dbio.open_database(Path(report["database_path"])) as db:
        names = dbio.image_names(db)
        inliers = dbio.pair_inlier_counts(db)
        written = dbio.written_pairs(Path(report["database_path"]))
        pairs = [p for p in written if frozenset(names[i] for i in p) not in kept]
        images = {
            i: dbio.read_image_data(db, dbio.read_image(db, names[i]), report["image_path"])
            for i in sorted({i for p in pairs for i in p})
        }
    for image in images.values():
        matcher.prepare(image)
    window = matcher.conf["window_cells"]
    rows = []
    for k, (i, j) in enumerate(pairs):
        a, b = images[i], images[j]
        flows = matcher.coarse_flows(a, b)
        m, geometry = matcher.cheap(a, b, flows, window, verification)
        rows.append(
            {
                "pair": (names[i], names[j]),
                "score": float(flows.pair_score),
                "cheap": len(m),
                "cheap_inliers": len(geometry.inlier_matches),
                "inliers": inliers.get((i, j), 0),
            }
        )
        if k % 500 == 0:
            print(f"{k}/{len(pairs)} pairs", flush=True)
    return rows


def rule_table(rows: list[dict], placed: set[str], verified_by_photo: dict, labels=None) -> list:
    """Markdown rows: per rule, what it spares and loses (``module docstring``)."""
    label = label_of(labels)
    out = [
        "| cheap matches below | coarse score below | LightGlue pairs spared | verified pairs lost "
        "(strong) | placed photos left without a verified pair | lost within one label / across |",
        "|---|---|---|---|---|---|",
    ]
    for c in CHEAP:
        for s in SCORE:
            if c is None and s is None:
                continue
            left = [
                r
                for r in rows
                if (c is not None and r["cheap"] < c) or (s is not None and r["score"] < s)
            ]
            lost = [r for r in left if r["inliers"] > 0]
            strong = sum(r["inliers"] >= 100 for r in lost)
            gone = {frozenset(r["pair"]) for r in lost}
            cut = sum(
                1 for p in placed if verified_by_photo.get(p) and verified_by_photo[p] <= gone
            )
            same = [label(r["pair"][0]) == label(r["pair"][1]) for r in lost]
            split = f"{sum(same)} / {len(same) - sum(same)}" if labels else "–"
            out.append(
                f"| {c or '–'} | {s or '–'} | {len(left)} of {len(rows)} | {len(lost)} ({strong}) "
                f"| {cut} | {split} |"
            )
    return out


def share_table(names: dict, matched: dict, inliers: dict, labels: dict) -> list[str]:
    """Markdown rows: the inlier share of the verified pairs (``inliers`` over ``matched`` by pair
    of image ids; ``names``: id -> name) per kind (within one label or across two; both photos
    rendered landmarks or not), its percentiles."""
    label = label_of(labels)
    kinds: dict[str, list[float]] = {}
    for (i, j), n in inliers.items():
        a, b = label(names[i]), label(names[j])
        if n == 0 or a is None or b is None:
            continue
        rendered = "rendered" if a.startswith("rendered:") and b.startswith("rendered:") else "real"
        kind = f"{'within one label' if a == b else 'across two'}, {rendered}"
        kinds.setdefault(kind, []).append(n / max(matched.get((i, j), n), 1))
    out = [
        "| verified pairs | number | inlier share 1 / 5 / 25 / 50 % | below 0.8 / 0.9 |",
        "|---|---|---|---|",
    ]
    for kind, shares in sorted(kinds.items()):
        q = " / ".join(f"{x:.2f}" for x in np.percentile(shares, [1, 5, 25, 50]))
        below = " / ".join(str(sum(x < t for x in shares)) for t in (0.8, 0.9))
        out.append(f"| {kind} | {len(shares)} | {q} | {below} |")
    return out


def main() -> None:
    from colmap_guided import database as dbio
    from colmap_guided.mapping import load_models, registered

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path, help="a reconstruct run's workspace")
    parser.add_argument("--labels", type=Path, help="the archive's labels.json")
    args = parser.parse_args()
    cache = args.workspace / "pair_signals.json"
    if cache.is_file():
        rows = json.loads(cache.read_text())
    else:
        rows = signals(args.workspace)
        cache.write_text(json.dumps(rows))
    report = json.loads((args.workspace / "report.json").read_text())
    with dbio.open_database(Path(report["database_path"])) as db:
        names = dbio.image_names(db)
        matched, verified = dbio.pair_match_counts(db), dbio.pair_inlier_counts(db)
    by_photo: dict[str, set] = {}
    for i, j in verified:
        for name in (names[i], names[j]):
            by_photo.setdefault(name, set()).add(frozenset((names[i], names[j])))
    placed = set().union(*map(registered, load_models(args.workspace / "sparse").values()))
    labels = json.loads(args.labels.read_text()) if args.labels else None
    ok = np.array([r["inliers"] > 0 for r in rows])
    for key in ("cheap", "cheap_inliers", "score"):
        v = np.array([r[key] for r in rows])
        q = [f"{x:.3g}" for x in np.percentile(v[ok], [5, 25, 50])] if ok.any() else []
        print(f"{key}: verified pairs 5/25/50 % {q}; not verified median {np.median(v[~ok]):.3g}")
    print("\n".join(rule_table(rows, placed, by_photo, labels)))
    if labels:
        print("\n".join(share_table(names, matched, verified, labels)))


if __name__ == "__main__":
    main()
