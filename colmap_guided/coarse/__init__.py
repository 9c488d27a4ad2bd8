"""Coarse matching network (paper §4.1, §4.3): backbone features → 4D correlation → symmetric
neighbourhood-consensus filter → coarse matches and pixel flow. See ``matcher.CoarseMatcher``."""

from colmap_guided.coarse.backbone import BACKBONES, DEFAULT_BACKBONE, build_backbone
from colmap_guided.coarse.flow import CoarseResult
from colmap_guided.coarse.geometry import ImageGeometry, resize_geometry
from colmap_guided.coarse.matcher import CoarseFeatures, CoarseMatcher
from colmap_guided.coarse.model import CoarseNet, GridMatches, NeighConsensus
from colmap_guided.coarse.weights import (
    DEFAULT_WEIGHTS,
    load_filter_weights,
    read_filter_weights,
    save_filter_weights,
)

__all__ = [
    "BACKBONES",
    "DEFAULT_BACKBONE",
    "DEFAULT_WEIGHTS",
    "CoarseFeatures",
    "CoarseMatcher",
    "CoarseNet",
    "CoarseResult",
    "GridMatches",
    "ImageGeometry",
    "NeighConsensus",
    "build_backbone",
    "load_filter_weights",
    "read_filter_weights",
    "resize_geometry",
    "save_filter_weights",
]
