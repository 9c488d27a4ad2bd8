"""A small rendered multi-view scene with exact ground truth, for the demo and the pipeline tests.

A textured "landmark" (a gabled hall, a tower with a pyramid roof, a low annex and a few stone
blocks) stands on a paved plaza in a grass field, with a distant tree line and a sky gradient. Every
surface is a planar polygon with a procedural texture drawn from the seed: stone blocks, bricks or
plaster, windows, doors, posters and stains, roof tiles, pebbles. With ``repeated=True`` all facades
show one identical window, tiled on an exact grid over plain plaster: repeated structure that fools
descriptor matching.

Modules: ``textures`` (procedural textures), ``render`` (exact rendering of textured polygons),
``scene`` (layout, cameras, ``render_scene``, ``load_scene``, ``transfer_points``). Pose errors of a
reconstruction against the ground truth: ``recon_scripts.evaluation.ground_truth.pose_errors``.

Output of :func:`render_scene`::

    OUT/images/view_000.jpg ...   JPEG photos (EXIF: one camera make/model, focal length in 35 mm)
    OUT/ground_truth/             COLMAP text model: one PINHOLE camera, every image with
                                  cam_from_world
    OUT/depth/view_000.npy ...    float32 depth along the optical axis, 0 = sky or an occlusion edge
"""

from .render import Polygon, Texture, make_texture, render_image, render_view
from .scene import (
    SceneInfo,
    build_scene,
    default_conf,
    load_ground_truth,
    load_scene,
    main,
    render_scene,
    transfer_points,
)

__all__ = [
    "Polygon",
    "SceneInfo",
    "Texture",
    "build_scene",
    "default_conf",
    "load_ground_truth",
    "load_scene",
    "main",
    "make_texture",
    "render_image",
    "render_scene",
    "render_view",
    "transfer_points",
]
