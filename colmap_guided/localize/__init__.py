"""After stage 5: localize new photos in an existing model, without rebuilding it.

    python -m colmap_guided localize WORKSPACE PHOTOS... [--add] [--num_images 10] [--model N]

"Where was this old photo taken?" For each new photo: retrieval of the model's most similar images
(GeM descriptors of the matcher's backbone, as ``--pairs retrieval``), the workspace's matcher
between the photo and those images (guided, as ``reconstruct`` picks it for the database's
features), COLMAP's two-view verification, 2D-3D correspondences through the model's tracks, then
absolute pose estimation with an unknown focal length (LO-RANSAC + refinement, pycolmap) and a pose
check (inliers, reprojection error, the model check's focal length rule).

The model (WORKSPACE/sparse/0, the largest; ``--model N``: sparse/N), database.db and the photos
are only read. What localize writes in
the workspace, recorded in its marker (so ``reconstruct --overwrite`` removes it):

- ``localize.db``: a COLMAP database with the new photos' keypoints and matches and a copy of the
  keypoints of the model's images they were matched with; image names are absolute paths without the
  leading '/'. A killed run continues from it; photos already in ``localized.json`` are not redone.
- ``localized.json``: one entry per photo: pose, focal length, inliers, matched model images, a
  verdict; in a georeferenced workspace (``georeference``) also latitude, longitude and heading.
- ``localize_pairs.txt``, ``localize_retrieval.npz``: the pairs matched, the model's retrieval
  descriptors.
- ``sparse_localized/0`` with ``--add``: a new model version, the model with the placed photos
  registered, their points triangulated and bundle adjustment run; sparse/N is left as it was.
- ``report.html`` is written again with a section on the localized photos.

Modules: ``results`` (the workspace's files, localized.json), ``pose`` (retrieval, matches, pose,
verdict), ``add`` (``--add``), ``run`` (the steps), ``command`` (the command line).
"""

from __future__ import annotations

from pathlib import Path

from .. import model_check
from ..conf import merge_conf
from ..matchers import AUTO
from ..workspace import model_digest
from .add import add_to_model
from .results import WRITES, db_name, open_workspace
from .run import localize_one, localize_photos, summary_text

__all__ = [
    "WRITES",
    "add_to_model",
    "db_name",
    "default_conf",
    "localize",
    "localize_one",
    "model_digest",
    "open_workspace",
    "summary_text",
]

# here, where the command line reads the options' comments as its help
default_conf = {
    "num_images": 10,  # model images matched with each photo (the retrieval's top k)
    # fewer pose inliers: not placed (the project's mapper registers a photo from 15)
    "min_inliers": 15,
    "placed_inliers": 30,  # fewer: uncertain (COLMAP's mapper registers a photo from 30)
    "max_error": 12.0,  # RANSAC threshold in pixels (COLMAP mapper's abs_pose_max_error)
    # mean over inliers, px
    "max_reprojection_error": model_check.default_conf["max_reprojection_error"],
    "random_seed": 0,  # a rerun gives the same poses
    # Triangulation of new points with --add (COLMAP's triangulator: 1.5° and 4 px).
    "min_tri_angle_deg": 1.5,
    "max_tri_error": 4.0,
}


def localize(
    workspace: Path,
    photos: list[Path],
    matcher: str = AUTO,
    matcher_conf: dict | None = None,
    conf: dict | None = None,
    add: bool = False,
    model: int = 0,
) -> dict:
    """Localize ``photos`` (files or folders) in a model of a ``reconstruct`` workspace
    (sparse/``model``; 0: the largest); returns localized.json's content ({"photos": [...], ...})
    and, with ``add``, the new model's folder."""
    conf = merge_conf(default_conf, conf, "localize")
    return localize_photos(workspace, photos, matcher, matcher_conf, conf, add, model)
