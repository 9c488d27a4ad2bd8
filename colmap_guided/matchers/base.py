"""The matcher interface: everything the pipeline (match.py, executor.py) and recon_scripts ask of a
matcher.

A new matcher subclasses ``Matcher``, sets ``name`` and ``default_conf`` (one comment line per
option; ``feature_defaults`` where some features need other values), implements ``match`` and adds
itself to ``matchers.MATCHERS``; the other hooks have defaults that fit a matcher needing no
per-image work, no own verification options and no separate guidance step. Coordinates follow
COLMAP (see ``colmap_guided.image_data``).
"""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from colmap_guided.conf import merge_conf
from colmap_guided.image_data import ImageData

_steps_lock = threading.Lock()


class Matcher:
    """Base class: ``match(a, b)`` returns (M, 2) uint32 indices into a.keypoints and
    b.keypoints."""

    name = "base"
    default_conf: dict = {}
    # torch device it runs on (subclasses resolve it); retrieval's backbone runs there too
    device = "auto"
    pair_workers: int = (
        1  # pairs that match_database may match at once in threads (``match`` must be thread-safe)
    )
    torch_threads: int | None = (
        None  # torch CPU threads while match_database runs (set, then restored); None: as is
    )
    flow_options: tuple[
        str, ...
    ] = ()  # options ``match_flows`` takes as overrides (applied after ``coarse_flows``)
    feature_types: tuple[str, ...] | None = (
        None  # the features (``features.FEATURE_TYPES`` keys) it can match; None: any
    )
    # Its options on some features (``features.FEATURE_TYPES`` key -> options over default_conf),
    # which ``matchers.resolve_auto`` gives the matcher's own preset where the user sets none
    feature_defaults: dict[str, dict] = {}

    def __init__(self, conf: dict | None = None):
        self.conf = merge_conf(self.default_conf, conf, f"{self.name} matcher")

    def match(self, a: ImageData, b: ImageData) -> np.ndarray:
        raise NotImplementedError

    def match_verified(self, a: ImageData, b: ImageData, verification: dict) -> tuple:
        """What the pipeline's pair workers call: ``match`` and, for a matcher whose matching
        already verified them, the matches' two-view geometry under ``verify.two_view_options(
        verification)`` (the pipeline writes it and does not verify the pair again); None: the
        verification stage verifies the pair. (None, None): the matcher left the pair unmatched (a
        cheap decision, e.g. a pair gate): nothing is written, as for a deferred pair."""
        return self.match(a, b), None

    @property
    def verification_conf(self) -> dict:
        """Options of ``verify.two_view_options`` for this matcher's pairs (e.g. min_num_inliers);
        {}: COLMAP's."""
        return {}

    def prepare(self, image: ImageData) -> None:
        """Per-image work done once, before the image's first pair, by the process that reads the
        database. What it stores in ``image.extra`` travels with the image to pair workers (the
        guided matcher's backbone features); ``prepares_images`` says whether there is any."""

    @property
    def prepares_images(self) -> bool:
        return type(self).prepare is not Matcher.prepare

    def release(self, name: str) -> None:
        """Called when the pipeline will not pass image ``name`` again: drop what is cached for
        it."""

    def coarse_flows(self, a: ImageData, b: ImageData) -> object | None:
        """The pair's guidance (guided matchers: the coarse match at both images' keypoints),
        computed once for variants that differ only in ``flow_options``; None for a matcher without
        that step."""
        return None

    def match_flows(
        self, a: ImageData, b: ImageData, flows: object | None, **overrides
    ) -> np.ndarray:
        """``match`` given ``coarse_flows``' result, with ``overrides`` of the options in
        ``flow_options``."""
        self.flow_conf(overrides)
        return self.match(a, b)

    def flow_conf(self, overrides: dict) -> dict:
        """``conf`` with ``overrides`` of ``match_flows``; an option outside ``flow_options`` is a
        ValueError."""
        unknown = sorted(set(overrides) - set(self.flow_options))
        if unknown:
            raise ValueError(
                f"The {self.name} matcher takes no option {unknown} "
                f"after its guidance; known: {list(self.flow_options)}"
            )
        return {**self.conf, **overrides}

    def retrieval_backbone(self):
        """The ``coarse.CoarseMatcher`` whose backbone features give retrieval descriptors
        (pairs.py); None: an ImageNet backbone on this matcher's ``device``."""
        return None

    @contextlib.contextmanager
    def timed(self, step: str):
        """Seconds spent in ``step``, summed over the pairs this process matched (``steps``)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            with _steps_lock:
                steps = self.__dict__.setdefault("_steps", {})
                steps[step] = steps.get(step, 0.0) + time.perf_counter() - start

    @property
    def steps(self) -> dict[str, float]:
        return dict(self.__dict__.get("_steps", {}))

    def match_guided(self, a: ImageData, b: ImageData, fine=None):
        """``match`` of a guided matcher: the coarse guidance, then the matching it restricts
        (``fine(a, b, flows)``, default ``match_flows``), each timed."""
        with self.timed("coarse"):
            flows = self.coarse_flows(a, b)
        with self.timed("fine"):
            return (fine or self.match_flows)(a, b, flows)

    def describe(self) -> dict:
        """What the report records about this matcher."""
        return {"name": self.name, "conf": self.conf}


@contextlib.contextmanager
def scoped_torch_threads(threads: int | None):
    """torch's (process-wide) CPU thread count set to ``threads`` inside the block, restored after
    it. A library call must not leave global state changed; None leaves it as it is."""
    if threads is None:
        yield
        return
    import torch

    saved = torch.get_num_threads()
    if saved != threads:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != saved:
            torch.set_num_threads(saved)
