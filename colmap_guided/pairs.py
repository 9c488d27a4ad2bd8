"""Which image pairs to match: exhaustive, by image retrieval, sequential, or a pairs file.

- ``exhaustive``: all N(N-1)/2 pairs (COLMAP's exhaustive_matcher).
- ``retrieval``: each image with its ``num_neighbors`` most similar images by a global descriptor
  (VLAD of its ALIKED descriptors over a trained codebook; GeM pooling of the coarse network's
  backbone features for other features), symmetric union — the visibility graph that hloc /
  COLMAP's vocabulary tree build; the coarse matches alone cannot (the paper's §Limitations: they
  look consistent even between different places).
- ``sequential``: each image with the ``num_neighbors`` next ones in name order
  (video, a scanned film).
- ``auto`` (default): exhaustive up to ``AUTO_EXHAUSTIVE_MAX`` images, retrieval above.
- a pairs file: one pair per line, ``name_a name_b`` (hloc / COLMAP matches_importer format);
  names that contain spaces are separated by a tab instead, or resolved against the known names.
"""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np

# k-means words of ALIKED descriptors (python -m colmap_guided.train.codebook; MODEL_CARD.md)
CODEBOOK = Path(__file__).resolve().parent / "weights" / "retrieval_codebook.safetensors"

PAIR_MODES = ("auto", "exhaustive", "retrieval", "sequential")
# Above this many images ``auto`` picks retrieval (README "Large archives": measured recall vs k).
AUTO_EXHAUSTIVE_MAX = 40
DEFAULT_NUM_NEIGHBORS = 10


def exhaustive_pairs(names: list[str]) -> list[tuple[str, str]]:
    return list(combinations(sorted(names), 2))


def sequential_pairs(names: list[str], num_neighbors: int) -> list[tuple[str, str]]:
    """Each image with the ``num_neighbors`` images after it in name order."""
    names = sorted(names)
    return [
        (a, names[j])
        for i, a in enumerate(names)
        for j in range(i + 1, min(i + 1 + num_neighbors, len(names)))
    ]


def gem(features: np.ndarray, p: float = 3.0) -> np.ndarray:
    """Generalised-mean pooling (Radenović et al. 2018) of (C, h, w) features → L2-normalised (C,).

    The backbone's last block is linear (signed output): GeM pools the positive part."""
    x = np.clip(features.reshape(features.shape[0], -1).astype(np.float64), 1e-6, None)
    d = np.power(np.power(x, p).mean(1), 1.0 / p)
    return (d / max(np.linalg.norm(d), 1e-12)).astype(np.float32)


def load_codebook(path: Path = CODEBOOK) -> np.ndarray:
    """The (K, D) unit visual words of a codebook file."""
    from safetensors.numpy import load_file

    return load_file(str(path))["words"]


def vlad(descriptors: np.ndarray, words: np.ndarray) -> np.ndarray:
    """VLAD (Jégou et al. 2010) of one image's local descriptors (N, D) over ``words`` (K, D):
    per word the summed residuals of the descriptors nearest it, each word's sum L2-normalised
    (Arandjelović & Zisserman 2013), square-rooted with its sign, L2-normalised → (K * D,)."""
    d = np.asarray(descriptors, np.float32)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    nearest = np.argmax(d @ words.T, axis=1)
    v = np.zeros_like(words)
    np.add.at(v, nearest, d - words[nearest])
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    v = (np.sign(v) * np.sqrt(np.abs(v))).ravel()
    return (v / max(np.linalg.norm(v), 1e-12)).astype(np.float32)


def retrieval_pairs(
    names: list[str], descriptors: np.ndarray, num_neighbors: int
) -> list[tuple[str, str]]:
    """Top-``num_neighbors`` neighbours of each image by cosine similarity of ``descriptors``
    (N, D), symmetric union, in name order (deterministic: a resumed run selects the same pairs)."""
    order = np.argsort(names, kind="stable")
    names, descriptors = [names[i] for i in order], np.asarray(descriptors, np.float32)[order]
    sim = descriptors @ descriptors.T
    np.fill_diagonal(sim, -np.inf)
    k = min(num_neighbors, len(names) - 1)
    top = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    keys = {(min(i, int(j)), max(i, int(j))) for i in range(len(names)) for j in top[i]}
    return [(names[i], names[j]) for i, j in sorted(keys)]


def pair_mode(pairs: str | Path | None, num_images: int, num_neighbors: int) -> str:
    """The mode of ``pairs`` (a mode of ``PAIR_MODES``, None = auto, or a pairs file: 'file'), auto
    decided by the number of images; a missing file or a count below 1 is a one-line error."""
    mode = "auto" if pairs is None else str(pairs)
    if mode not in PAIR_MODES:
        if not Path(mode).is_file():
            raise FileNotFoundError(
                f"--pairs {mode}: no such pairs file; pass "
                f"a file or one of {', '.join(PAIR_MODES)}."
            )
        return "file"
    if num_neighbors < 1:
        raise ValueError(f"--num_neighbors must be at least 1, got {num_neighbors}.")
    if mode == "auto":
        mode = "exhaustive" if num_images <= AUTO_EXHAUSTIVE_MAX else "retrieval"
    return mode


def retrieves(mode: str, num_images: int, num_neighbors: int) -> bool:
    """Whether ``mode``'s pairs need retrieval descriptors (not when every image is a neighbour)."""
    return mode == "retrieval" and num_neighbors < num_images - 1


def select_pairs(
    pairs: str | Path | None,
    names: list[str],
    num_neighbors: int = DEFAULT_NUM_NEIGHBORS,
    descriptors: np.ndarray | None = None,
) -> tuple[list[tuple[str, str]], str]:
    """The pairs to match and the mode used (``pair_mode``). ``descriptors``: the global
    descriptors (N, D) of ``names`` that retrieval needs (``retrieves``)."""
    mode = pair_mode(pairs, len(names), num_neighbors)
    if mode == "file":
        return read_pairs(Path(pairs), names), mode
    if mode == "sequential":
        return sequential_pairs(names, num_neighbors), mode
    if not retrieves(mode, len(names), num_neighbors):
        return exhaustive_pairs(names), mode
    if descriptors is None:
        raise ValueError("Retrieval pairs need global image descriptors.")
    return retrieval_pairs(names, descriptors, num_neighbors), mode


def _split_line(line: str, known: set[str]) -> tuple[str, str] | None:
    if "\t" in line:
        parts = [p.strip() for p in line.split("\t") if p.strip()]
        return (parts[0], parts[1]) if len(parts) >= 2 else None
    tokens = line.split(" ")
    for cut in range(1, len(tokens)):
        a, b = " ".join(tokens[:cut]), " ".join(tokens[cut:])
        if a in known and b in known:
            return a, b
    return (tokens[0], tokens[1]) if len(tokens) >= 2 else None


def read_pairs(path: Path, names: list[str]) -> list[tuple[str, str]]:
    """Pairs from a file, deduplicated (a-b and b-a are one pair), self-pairs dropped, in file
    order."""
    known = set(names)
    pairs, seen = [], set()
    for lineno, raw in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        pair = _split_line(line, known)
        if pair is None:
            raise ValueError(f"{path}:{lineno}: expected two image names per line, got {raw!r}.")
        for name in pair:
            if name not in known:
                raise ValueError(
                    f"{path}:{lineno}: image {name!r} is not in the "
                    "database/image folder; fix the pairs file."
                )
        key = tuple(sorted(pair))
        if pair[0] != pair[1] and key not in seen:
            seen.add(key)
            pairs.append(pair)
    return pairs


def write_pairs(path: Path, pairs: list[tuple[str, str]]) -> None:
    sep = lambda a, b: "\t" if (" " in a or " " in b) else " "  # noqa: E731
    Path(path).write_text("".join(f"{a}{sep(a, b)}{b}\n" for a, b in pairs), encoding="utf-8")


def global_descriptors(coarse, paths: dict[str, Path], desc: str = "retrieval") -> np.ndarray:
    """GeM descriptor (N, C) of each image of ``paths`` (name → file), in its order, from the
    backbone of a ``colmap_guided.coarse.CoarseMatcher``; each image's features are released at once
    (memory flat in N)."""
    from .log import progress

    out = []
    for name, path in progress(paths.items(), desc, "img"):
        out.append(gem(coarse.extract_path(path, name).features.float().cpu().numpy()))
        coarse.release(name)
    return np.stack(out) if out else np.zeros((0, 0), np.float32)
