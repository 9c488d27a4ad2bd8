"""Multi-scene manifests (datasets/ltll_manifest.json schema): load, scan a local copy, lay scenes
out.

Schema (JSON)::

    {
      "name": "LTLL", "description": "...", "citation": "...", "source": "...",
      "root": "/abs/path" | "relative/to/this/file" | "$COLMAP_GUIDED_DATA[/...]" | null,
      "scenes": [
        {"name": "scene", "path": "relative/to/root",  # the scene's folder
         "image_dir": "images",                         # photos below path (default: path itself)
         "reference": {"type": "colmap", "path": "..."}
                      | null,                           # model to check registrations against
         "images": [{"name": "historical/a.jpg", "era": "historical" | "modern" | "distractor",
                     "ref_name": "name in the reference model (optional)"}]}
      ]
    }

``root: null`` means the data is not shipped (LTLL): pass the registration preset's ``root``.
``$COLMAP_GUIDED_DATA`` expands to ``colmap_guided.paths.shared_data_dir()``. Eras: ``historical``
and ``modern`` as in LTLL; ``distractor`` marks images of another scene that must not register
(the historical proxy).

A laid-out scene is SCENE/images (symlinks to the photos, or copies) + SCENE/manifest.json (the
one-scene schema ``colmap_guided.report.read_manifest`` reads); the source is never modified.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from colmap_guided.features import IMAGE_EXTENSIONS
from colmap_guided.log import logger
from colmap_guided.paths import shared_data_dir
from colmap_guided.workspace import Workspace

ERAS = ("historical", "modern", "distractor")
# A subset of a scene: the eras it keeps. Distractors stay in every subset: they must never
# register.
SUBSETS = {
    "historical": ("historical", "distractor"),
    "modern": ("modern", "distractor"),
    "all": None,
}
HISTORICAL_ALIASES = (
    "historical",
    "historic",
    "history",
    "hist",
    "old",
    "past",
    "archive",
    "archival",
    "then",
)
MODERN_ALIASES = ("modern", "new", "recent", "present", "today", "current", "now", "contemporary")


def expand(text: str | None, base: Path | None = None) -> Path | None:
    """A manifest path: $COLMAP_GUIDED_DATA prefix, absolute, or relative to ``base``."""
    if text is None:
        return None
    text = str(text)
    if text.startswith("$COLMAP_GUIDED_DATA"):
        rest = text[len("$COLMAP_GUIDED_DATA") :].lstrip("/")
        return shared_data_dir() / rest if rest else shared_data_dir()
    path = Path(os.path.expanduser(text))
    if not path.is_absolute() and base is not None:
        path = Path(base) / path
    return path


def load_manifest(path: Path, root: Path | None = None) -> dict:
    """Read a manifest; ``root`` (the preset's ``root``) overrides its root. Adds '_root' (Path or
    None)."""
    path = Path(path)
    data = json.loads(path.read_text(encoding="utf-8"))
    data["_root"] = Path(root) if root else expand(data.get("root"), path.parent.resolve())
    data["_path"] = str(path)
    return data


def save_manifest(path: Path, data: dict) -> None:
    clean = {k: v for k, v in data.items() if not k.startswith("_")}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(clean, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")


def scene_image_dir(manifest: dict, scene: dict) -> Path:
    root = manifest.get("_root")
    if root is None:
        raise ValueError(
            f"Manifest {manifest.get('name')} has no root: "
            "pass root=FOLDER (the folder of your local copy)."
        )
    base = Path(root) / scene.get("path", scene["name"])
    return base / scene["image_dir"] if scene.get("image_dir") else base


def scene_reference(manifest: dict, scene: dict) -> Path | None:
    ref = scene.get("reference")
    if not ref:
        return None
    root = manifest.get("_root")
    base = Path(root) / scene.get("path", scene["name"]) if root else None
    return expand(ref["path"], base)


def _images_below(folder: Path) -> list[str]:
    return sorted(
        p.relative_to(folder).as_posix()
        for p in folder.rglob("*")
        if p.is_file()
        and p.suffix.lower() in IMAGE_EXTENSIONS
        and not any(part.startswith(".") for part in p.relative_to(folder).parts)
    )


def era_of_folder(name: str) -> str | None:
    low = name.lower().replace("-", "_").replace(" ", "_")
    for era, aliases in (("historical", HISTORICAL_ALIASES), ("modern", MODERN_ALIASES)):
        if low in aliases or any(low.startswith(a + "_") or low.endswith("_" + a) for a in aliases):
            return era
    return None


def scan_root(root: Path) -> list[dict]:
    """Scenes of a local copy laid out as ROOT/SCENE/{historical,modern}/... (or old/new, ...) or as
    ROOT/{historical,modern}/SCENE/... . Images without an era folder get era 'unknown'
    (with a warning); they are kept in the 'all' subset only."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a folder")
    top = [d for d in sorted(root.iterdir()) if d.is_dir() and not d.name.startswith(".")]
    era_top = {d.name: era_of_folder(d.name) for d in top}
    scenes: dict[str, dict] = {}
    if top and all(era_top.values()):  # ROOT/ERA/SCENE/...
        for era_dir in top:
            for scene_dir in sorted(
                d for d in era_dir.iterdir() if d.is_dir() and not d.name.startswith(".")
            ):
                scene = scenes.setdefault(
                    scene_dir.name, {"name": scene_dir.name, "path": ".", "images": []}
                )
                scene["images"] += [
                    {"name": f"{era_dir.name}/{scene_dir.name}/{n}", "era": era_top[era_dir.name]}
                    for n in _images_below(scene_dir)
                ]
    else:  # ROOT/SCENE/ERA/...
        for scene_dir in top:
            images = []
            for name in _images_below(scene_dir):
                parts = name.split("/")
                era = next((e for e in (era_of_folder(p) for p in parts[:-1]) if e), None)
                images.append({"name": name, "era": era or "unknown"})
            unknown = sum(im["era"] == "unknown" for im in images)
            if unknown:
                logger.warning(
                    "%s: %d/%d images are in no historical/modern (old/new) folder: era 'unknown'.",
                    scene_dir.name,
                    unknown,
                    len(images),
                )
            if images:
                scenes[scene_dir.name] = {
                    "name": scene_dir.name,
                    "path": scene_dir.name,
                    "images": images,
                }
    out = [s for s in scenes.values() if s["images"]]
    for s in out:
        counts = {
            e: sum(im["era"] == e for im in s["images"])
            for e in sorted({im["era"] for im in s["images"]})
        }
        logger.info("Scanned %s: %s", s["name"], ", ".join(f"{v} {k}" for k, v in counts.items()))
    return out


def subset_images(scene: dict, subset: str) -> list[dict]:
    if subset not in SUBSETS:
        raise ValueError(f"subset must be one of {sorted(SUBSETS)}, got {subset!r}")
    eras = SUBSETS[subset]
    return [im for im in scene["images"] if eras is None or im["era"] in eras]


def layout_scene(
    manifest: dict, scene: dict, subset: str, out_dir: Path, copy: bool = False
) -> Path | None:
    """OUT_DIR/<scene>__<subset>/images (links or copies) + manifest.json; None when the subset has
    fewer than 2 images that are not distractors. Only files this function made are ever
    replaced."""
    images = subset_images(scene, subset)
    if sum(im["era"] != "distractor" for im in images) < 2:
        return None
    src_dir = scene_image_dir(manifest, scene).resolve()
    workspace = Workspace.claim(out_dir, "evaluation", keep=(src_dir,))
    scene_dir = workspace.take(f"{scene['name']}__{subset}")
    image_dir = scene_dir / "images"
    if image_dir.exists():
        shutil.rmtree(image_dir)  # our own links/copies from an earlier layout
    image_dir.mkdir(parents=True)
    kept = []
    for im in images:
        src = src_dir / im["name"]
        if not src.is_file():
            logger.warning("%s: %s is missing, skipped.", scene["name"], src)
            continue
        dst = image_dir / im["name"]
        dst.parent.mkdir(parents=True, exist_ok=True)
        if copy:
            shutil.copyfile(src, dst)
        else:
            dst.symlink_to(src)
        kept.append(im)
    one = {"scene": scene["name"], "subset": subset, "source": str(src_dir), "images": kept}
    ref = scene_reference(manifest, scene)
    if ref is not None:
        one["reference"] = {"type": scene["reference"].get("type", "colmap"), "path": str(ref)}
    (scene_dir / "manifest.json").write_text(json.dumps(one, indent=1) + "\n", encoding="utf-8")
    return scene_dir


def select_scenes(manifest: dict, names=None, max_scenes: int | None = None) -> list[dict]:
    scenes = [s for s in manifest.get("scenes", []) if s.get("images")]
    if names:
        unknown = set(names) - {s["name"] for s in scenes}
        if unknown:
            raise ValueError(
                f"Unknown scene(s) {sorted(unknown)}; the "
                f"manifest has {[s['name'] for s in scenes]}"
            )
        scenes = [s for s in scenes if s["name"] in names]
    return scenes[:max_scenes] if max_scenes else scenes
