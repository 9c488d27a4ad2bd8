"""Each mapper on a finished archive run's database: its models, their model check and labels.

    python -m recon_scripts.scale.archive_mappers WORKSPACE LABELS.json [--out DIR]
        [--mappers incremental global] [--extend]

The run's database (with every pair its first pass, check, escalation and join matched) is copied
to DIR (default WORKSPACE/../mappers) and mapped there by each mapper with the default options;
printed per model: photos, whether it passes the model check, its labels; per mapper: photos
placed, those in models that pass the check, those in two models, seconds. ``--extend``: each
mapper's models then extended as escalation extends them (model 0 continued incrementally with the
photos it lacks, ``run_mapping(extend=True)``). The run itself is left as it is.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from collections import Counter
from pathlib import Path


def main() -> None:
    from colmap_guided import model_check
    from colmap_guided.mapping import registered, run_mapping
    from recon_scripts.scale.archive import label_of

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path, help="a reconstruct run's workspace")
    parser.add_argument("labels", type=Path, help="the archive's labels.json")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--mappers", nargs="+", default=["incremental", "global"])
    parser.add_argument("--extend", action="store_true", help="then extend them as escalation")
    args = parser.parse_args()
    report = json.loads((args.workspace / "report.json").read_text())
    labels = json.loads(args.labels.read_text())
    label = label_of(labels)
    out = args.out or args.workspace.parent / "mappers"
    out.mkdir(parents=True, exist_ok=True)
    database = out / "database.db"
    shutil.copyfile(report["database_path"], database)
    runs = [(m, m, False) for m in args.mappers]
    runs += [(f"{m}, extended", m, True) for m in args.mappers if args.extend]
    for what, mapper, extend in runs:
        start = time.perf_counter()
        conf = {"mapper": mapper}
        models = run_mapping(database, Path(report["image_path"]), out / mapper, conf, extend)
        seconds = time.perf_counter() - start
        placed, passed, seen = 0, 0, Counter()
        print(f"| {what}: model | photos | model check | labels (photos) |\n|---|---|---|---|")
        for key, rec in models.items():
            names = registered(rec)
            seen.update(names)
            ok = not model_check.check_model(rec)
            placed, passed = placed + len(names), passed + ok * len(names)
            count = Counter(label(name) or "?" for name in names)
            shown = ", ".join(f"{lb} {n}" for lb, n in count.most_common(4))
            more = f" and {len(count) - 4} more" if len(count) > 4 else ""
            print(f"| {key} | {len(names)} | {'ok' if ok else 'failed'} | {shown}{more} |")
        twice = sum(n > 1 for n in seen.values())
        print(
            f"\n{what}: {placed} photos placed, {passed} in models that pass the check, "
            f"{twice} in two models, {seconds:.0f} s\n",
            flush=True,
        )


if __name__ == "__main__":
    main()
