"""Each mapper on a finished archive run's database: its models, their model check and labels.

    python -m recon_scripts.scale.archive_mappers WORKSPACE LABELS.json [--out DIR]
        [--mappers incremental global]

The run's database (with every pair its first pass, check, escalation and join matched) is copied
to DIR (default WORKSPACE/../mappers) and mapped there by each mapper with the default options;
printed per model: photos, whether it passes the model check, its labels; per mapper: photos
placed, those in models that pass the check, seconds. The run itself is left as it is.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from collections import Counter
from pathlib import Path, PurePosixPath


def main() -> None:
    from colmap_guided import model_check
    from colmap_guided.mapping import run_mapping
    from recon_scripts.scale.archive import photo_of

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspace", type=Path, help="a reconstruct run's workspace")
    parser.add_argument("labels", type=Path, help="the archive's labels.json")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--mappers", nargs="+", default=["incremental", "global"])
    args = parser.parse_args()
    report = json.loads((args.workspace / "report.json").read_text())
    labels = json.loads(args.labels.read_text())
    stems = {PurePosixPath(n).stem: n for n in labels}
    out = args.out or args.workspace.parent / "mappers"
    out.mkdir(parents=True, exist_ok=True)
    database = out / "database.db"
    shutil.copyfile(report["database_path"], database)
    for mapper in args.mappers:
        start = time.perf_counter()
        models = run_mapping(database, Path(report["image_path"]), out / mapper, {"mapper": mapper})
        seconds = time.perf_counter() - start
        placed = passed = 0
        print(f"| {mapper}: model | photos | model check | labels (photos) |\n|---|---|---|---|")
        for key, rec in models.items():
            names = [rec.images[i].name for i in rec.reg_image_ids()]
            ok = not model_check.check_model(rec)
            placed, passed = placed + len(names), passed + ok * len(names)
            count = Counter(labels.get(photo_of(name, stems), "?") for name in names)
            shown = ", ".join(f"{lb} {n}" for lb, n in count.most_common(4))
            more = f" and {len(count) - 4} more" if len(count) > 4 else ""
            print(f"| {key} | {len(names)} | {'ok' if ok else 'failed'} | {shown}{more} |")
        print(
            f"\n{mapper}: {placed} photos placed, {passed} in models that pass the check, "
            f"{seconds:.0f} s\n",
            flush=True,
        )


if __name__ == "__main__":
    main()
