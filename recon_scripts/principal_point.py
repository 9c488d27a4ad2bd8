"""Principal points of cropped prints: the databases of finished runs mapped again with each
camera's principal point fixed at the image centre (COLMAP's default) and refined by bundle
adjustment (mapping's ``refine_principal_point``), one mapping thread, seed 0.

    python -m recon_scripts.principal_point --eval outputs/eval_dev [--method guided_lightglue]
    python -m recon_scripts.principal_point --workspaces WORKSPACE [...]

``--eval``: eval_registration output folders; each scene's run of ``--method`` (seed 0) is scored
against the scene's reference (photos on the reference pose / off it). ``--workspaces``: reconstruct
workspaces without a reference: photos registered and the model check. Repeated prints are left
out of mapping as ``reconstruct`` leaves them out.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import pycolmap

from colmap_guided import cards, mapping, model_check
from colmap_guided import database as dbio
from recon_scripts import script_parser
from recon_scripts.evaluation.registration import method_slug, score_registration


def map_again(database: Path, image_path: Path, refine: bool) -> pycolmap.Reconstruction | None:
    """The largest model of ``database`` (copied) mapped with the principal point fixed/refined."""
    prints = cards.repeated_prints(database, cards.check_conf(None))
    with dbio.open_database(database) as db:
        names = [n for n in sorted(dbio.images_by_name(db)) if n not in prints] if prints else None
    conf = {"num_threads": 1, "random_seed": 0, "refine_principal_point": refine}
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copy(database, Path(tmp) / "database.db")
        models = mapping.run_mapping(
            Path(tmp) / "database.db",
            image_path,
            Path(tmp) / "sparse",
            {**conf, "image_names": names},
        )
    return models.get(0)


def cell(score: dict) -> str:
    if not score["registered"]:
        return "no model"
    ok = "model check ok" if score["check_ok"] else "model check fails"
    pose = f"{score['correct']} ✓ {score['wrong']} ✗ · " if score["correct"] is not None else ""
    return f"{pose}{score['registered']} registered · {ok}"


def score(rec, images: list[dict] | None, reference) -> dict:
    out = {"registered": rec.num_reg_images() if rec else 0, "correct": None, "wrong": None}
    out["check_ok"] = bool(rec) and not model_check.check_model(rec)
    if images is not None:
        scored = score_registration(rec, images, reference)
        out["registered"], out["correct"] = scored["num_registered"], scored["correct"]
        out["wrong"] = len(scored["wrong"] or [])
    return out


def runs(args) -> list[tuple]:
    """(label, database, photos, manifest images or None, reference or None) of every run."""
    found = []
    for folder in args.eval:
        for scene in json.loads((folder / "results.json").read_text())["scenes"]:
            scene_dir = Path(scene["scene_dir"])
            run = scene_dir / "runs" / "seed0" / method_slug(args.method)
            images = json.loads((scene_dir / "manifest.json").read_text())["images"]
            ref = pycolmap.Reconstruction(scene["reference"]) if scene.get("reference") else None
            label = f"{scene['scene']} ({scene['subset']})"
            found.append((label, run / "database.db", scene_dir / "images", images, ref))
    for ws in args.workspaces:
        report = json.loads((ws / "report.json").read_text())
        found.append((report["scene"], ws / "database.db", Path(report["image_path"]), None, None))
    return found


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("--eval", type=Path, nargs="*", default=[])
    parser.add_argument("--method", default="guided_lightglue")
    parser.add_argument("--workspaces", type=Path, nargs="*", default=[])
    parser.add_argument("--output", type=Path, default=Path("outputs/principal_point.json"))
    args = parser.parse_args()
    rows = []
    print("| set | principal point fixed | refined |\n|---|---|---|")
    for label, database, image_path, images, ref in runs(args):
        fixed, refined = (
            score(map_again(database, image_path, r), images, ref) for r in (False, True)
        )
        rows.append({"set": label, "fixed": fixed, "refined": refined})
        print(f"| {label} | {cell(fixed)} | {cell(refined)} |", flush=True)
    totals = {
        side: {k: sum(r[side][k] or 0 for r in rows) for k in ("registered", "correct", "wrong")}
        for side in ("fixed", "refined")
    }
    print(f"\nsummed: {totals}")
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({"rows": rows, "totals": totals}, indent=1))


if __name__ == "__main__":
    main()
