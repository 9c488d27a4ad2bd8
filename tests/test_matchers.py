"""Raw, guided (eq. 1) and classical guided matching against brute-force references and known
geometry."""

import logging
import warnings
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch

from colmap_guided.coarse import DEFAULT_WEIGHTS
from colmap_guided.log import logger
from colmap_guided.matchers import MATCHERS, get_matcher
from colmap_guided.matchers.base import ImageData
from colmap_guided.matchers.geometric import (
    apply_homography,
    epipolar_distances,
    keypoint_scales,
    top_scale_indices,
)
from colmap_guided.matchers.guided import guided_match
from colmap_guided.matchers.raw import mutual_nn_match, normalize_descriptors
from colmap_guided.paths import shared_data_dir


def _unit(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _reference_mutual(dist: np.ndarray, ratio):
    """Brute force on a full (N, M) distance matrix, inf = not a candidate: mutual NN + ratio both
    ways."""
    matches = []
    for i in range(dist.shape[0]):
        row = dist[i]
        if not np.isfinite(row).any():
            continue
        j = int(np.argmin(row))
        col = dist[:, j]
        if int(np.argmin(col)) != i:
            continue
        if ratio is not None:
            r2 = np.sort(row)[1] if len(row) > 1 else np.inf
            c2 = np.sort(col)[1] if len(col) > 1 else np.inf
            if not (row[j] < ratio * r2 and col[i] < ratio * c2):
                continue
        matches.append((i, j))
    return np.array(matches, dtype=np.int64).reshape(-1, 2)


def _pairwise(da, db):
    return np.sqrt(np.maximum(((da[:, None, :] - db[None]) ** 2).sum(-1), 0))


@pytest.mark.parametrize("ratio", [None, 0.8, 0.95])
def test_raw_equals_bruteforce_numpy(ratio):
    rng = np.random.default_rng(1)
    da = _unit(rng.normal(size=(300, 32))).astype(np.float32)
    db = np.concatenate(
        [da[:120] + 0.05 * rng.normal(size=(120, 32)), rng.normal(size=(140, 32))]
    ).astype(np.float32)
    db = _unit(db)
    expected = _reference_mutual(_pairwise(da.astype(np.float64), db.astype(np.float64)), ratio)
    for chunk in (7, 1024):
        got = mutual_nn_match(
            torch.from_numpy(da), torch.from_numpy(db), ratio, chunk_size=chunk
        ).numpy()
        np.testing.assert_array_equal(got, expected)
    assert 50 < len(expected) <= 300


def test_raw_matcher_on_uint8_descriptors_normalises_them():
    rng = np.random.default_rng(2)
    desc_a = rng.integers(0, 120, size=(200, 128), dtype=np.uint8)
    desc_b = (
        np.clip(desc_a.astype(int) + rng.integers(-4, 5, size=desc_a.shape), 0, 255)
        .astype(np.uint8)[::-1]
        .copy()
    )
    kp = np.zeros((200, 4), np.float32)
    for array in (desc_a, desc_b):
        array.setflags(write=False)  # as pycolmap's database arrays can be
    a = ImageData("a", 1, None, kp, desc_a, 10, 10)
    b = ImageData("b", 2, None, kp, desc_b, 10, 10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = get_matcher("raw", {"device": "cpu"}).match(a, b)
    assert got.dtype == np.uint32
    expected = _reference_mutual(
        _pairwise(_unit(desc_a.astype(np.float64)), _unit(desc_b.astype(np.float64))), 0.8
    )
    np.testing.assert_array_equal(got, expected)
    # desc_b is desc_a reversed, perturbed
    np.testing.assert_array_equal(got[:, 1], 199 - got[:, 0])


def _random_guided_problem(seed, n=900, m=800, clustered=False):
    """Random eq. 1 problem; ``clustered`` puts half the keypoints in a few small blobs, as on
    textured facades, so that many queries share a window (more than one unit of queries per
    cell)."""
    g = torch.Generator().manual_seed(seed)
    ka = torch.rand(n, 2, generator=g) * torch.tensor([640.0, 480.0])
    kb = torch.rand(m, 2, generator=g) * torch.tensor([600.0, 500.0])
    if clustered:
        centres = torch.tensor([[100.0, 100.0], [400.0, 300.0], [250.0, 420.0]])
        ka[::2] = centres[torch.arange(0, n, 2) % 3] + 15 * torch.rand(len(ka[::2]), 2, generator=g)
        kb[::2] = ka[:m:2] * 0.9 + 12 + torch.randn(len(kb[::2]), 2, generator=g)
    da = torch.nn.functional.normalize(torch.randn(n, 24, generator=g), dim=1)
    db = torch.nn.functional.normalize(torch.randn(m, 24, generator=g), dim=1)
    db[:300] = torch.nn.functional.normalize(
        da[:300] + 0.3 * torch.randn(300, 24, generator=g), dim=1
    )
    kb[:300] = ka[:300] * 0.9 + 12 + torch.randn(300, 2, generator=g)
    flow_ab = ka * 0.9 + 12 + 6 * torch.randn(n, 2, generator=g)
    flow_ba = (kb - 12) / 0.9 + 6 * torch.randn(m, 2, generator=g)
    flow_ab[:5] = float("nan")  # a coarse match may be missing
    return ka, da, kb, db, flow_ab, flow_ba


@pytest.mark.parametrize("ratio", [None, 0.9])
@pytest.mark.parametrize("clustered", [False, True])
def test_guided_equals_bruteforce_eq1(ratio, clustered):
    ka, da, kb, db, fab, fba = _random_guided_problem(0, clustered=clustered)
    wa, wb = 20.0, 18.0
    dist = _pairwise(da.double().numpy(), db.double().numpy())
    cand_ab = np.linalg.norm(fab.numpy()[:, None] - kb.numpy()[None], axis=-1) < wb  # nan -> False
    cand_ba = np.linalg.norm(ka.numpy()[:, None] - fba.numpy()[None], axis=-1) < wa
    if clustered:
        # windows far larger than one unit of queries or one block
        assert cand_ab.sum(1).max() > 100
    expected = _reference_guided(dist, cand_ab, cand_ba, ratio)
    for max_pairs in (1, 5000, 1 << 20):
        np.testing.assert_array_equal(
            guided_match(ka, da, kb, db, fab, fba, wa, wb, ratio, max_pairs=max_pairs).numpy(),
            expected,
        )
    assert len(expected) > 100


def _reference_guided(dist, cand_ab, cand_ba, ratio):
    """Eq. 1 in both directions by brute force: per-direction candidate sets, mutual, ratio among
    candidates."""

    def one_way(d, cand):
        best, ok = np.zeros(len(d), np.int64), np.zeros(len(d), bool)
        for i in range(len(d)):
            c = np.flatnonzero(cand[i])
            if len(c) == 0:
                continue
            order = np.argsort(d[i, c], kind="stable")
            best[i] = c[order[0]]
            ok[i] = ratio is None or len(c) == 1 or d[i, c[order[0]]] < ratio * d[i, c[order[1]]]
        return best, ok

    best_ab, ok_ab = one_way(dist, cand_ab)
    best_ba, ok_ba = one_way(dist.T, cand_ba.T)
    return np.array(
        [
            (i, best_ab[i])
            for i in range(len(dist))
            if ok_ab[i] and ok_ba[best_ab[i]] and best_ba[best_ab[i]] == i
        ],
        dtype=np.int64,
    ).reshape(-1, 2)


def test_guided_chunked_equals_unchunked_window_and_mutual():
    ka, da, kb, db, fab, fba = _random_guided_problem(3)
    wa, wb = 25.0, 22.0
    full = guided_match(ka, da, kb, db, fab, fba, wa, wb, 0.95, max_pairs=1 << 30)
    for max_pairs in (1, 97, 5000):
        assert torch.equal(
            guided_match(ka, da, kb, db, fab, fba, wa, wb, 0.95, max_pairs=max_pairs), full
        )
    i, j = full[:, 0], full[:, 1]
    assert len(full) > 100
    # within W of its coarse match in B
    assert torch.all(torch.linalg.norm(fab[i] - kb[j], dim=1) < wb)
    assert torch.all(torch.linalg.norm(fba[j] - ka[i], dim=1) < wa)  # and in A
    assert len(torch.unique(i)) == len(i) and len(torch.unique(j)) == len(j)
    reverse = guided_match(kb, db, ka, da, fba, fab, wb, wa, 0.95)  # the mutual test is symmetric
    assert torch.equal(torch.sort(reverse.flip(1)[:, 0]).values, i)
    assert set(map(tuple, reverse.flip(1).tolist())) == set(map(tuple, full.tolist()))


def test_guided_valid_mask_drops_keypoints():
    ka, da, kb, db, fab, fba = _random_guided_problem(4)
    valid = torch.arange(len(ka)) % 2 == 0
    got = guided_match(ka, da, kb, db, fab, fba, 20.0, 20.0, None, valid_ab=valid)
    assert len(got) > 50 and torch.all(got[:, 0] % 2 == 0)


def _sift(gray: np.ndarray):
    keypoints, descriptors = pycolmap.Sift().extract(np.ascontiguousarray(gray))
    return keypoints, descriptors


def _facade(h=480, w=640, period=(48, 40)):
    """A periodic facade: identical windows with mullions on a smooth wall, no distinctive
    detail."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = 150 + 0.05 * x
    wy, wx = period
    window = ((y % wy) > 10) & ((y % wy) < 36) & ((x % wx) > 8) & ((x % wx) < 30)
    img[window] = 60
    img[window & ((np.abs((x % wx) - 19) < 1.5) | (np.abs((y % wy) - 23) < 1.5))] = 200
    return np.clip(img, 0, 255).astype(np.uint8)


def _warp(img: np.ndarray, H: np.ndarray):
    """Warp by H given in COLMAP pixel coordinates; returns the warped image."""
    shift = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])
    H_index = np.linalg.inv(shift) @ H @ shift  # OpenCV works on pixel indices (centre = integer)
    return cv2.warpPerspective(
        img, H_index, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR, borderValue=128
    )


H_TRUE = np.array([[0.9, 0.08, 30.0], [-0.05, 0.95, 20.0], [1e-4, 5e-5, 1.0]])


@pytest.fixture(scope="module")
def facade_pair():
    a = _facade()
    b = _warp(a, H_TRUE)
    (ka, da), (kb, db) = _sift(a), _sift(b)
    return ka, da, kb, db


def _share_correct(matches, ka, kb, H):
    pred = apply_homography(
        torch.tensor(H, dtype=torch.float32), torch.from_numpy(ka[matches[:, 0], :2])
    )
    return (
        float((np.linalg.norm(pred.numpy() - kb[matches[:, 1], :2], axis=1) < 3).mean())
        if len(matches)
        else 0.0
    )


def test_repeated_structure_confuses_raw_but_not_guided(facade_pair):
    ka, da, kb, db = facade_pair
    ta, tb = torch.from_numpy(ka[:, :2]), torch.from_numpy(kb[:, :2])
    na, nb = normalize_descriptors(da, "cpu"), normalize_descriptors(db, "cpu")
    raw = mutual_nn_match(na, nb, 0.8).numpy()
    raw_off = mutual_nn_match(na, nb, None).numpy()
    H = torch.tensor(H_TRUE, dtype=torch.float32)
    flow_ab, flow_ba = apply_homography(H, ta), apply_homography(torch.linalg.inv(H), tb)
    guided = guided_match(ta, na, tb, nb, flow_ab, flow_ba, 16.0, 16.0, 0.8).numpy()
    raw_correct = len(raw) * _share_correct(raw, ka, kb, H_TRUE)
    # the period fools nearest neighbours
    assert raw_correct < 20 and _share_correct(raw_off, ka, kb, H_TRUE) < 0.3
    assert len(guided) > 500 and _share_correct(guided, ka, kb, H_TRUE) > 0.9
    assert np.all(
        np.linalg.norm(flow_ab.numpy()[guided[:, 0]] - kb[guided[:, 1], :2], axis=1) < 16.0
    )


@pytest.fixture(scope="module")
def photo_pair(tmp_path_factory):
    """A real photo and its warp by a known homography, written as files (SIFT at 640 px to stay
    fast)."""
    path = shared_data_dir() / "lightglue_assets" / "images" / "sacre_coeur1.jpg"
    if not path.exists():
        pytest.skip(f"{path} not available")
    gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    gray = cv2.resize(
        gray, (640, round(640 * gray.shape[0] / gray.shape[1])), interpolation=cv2.INTER_AREA
    )
    H = np.array([[0.95, 0.05, 15.0], [-0.04, 1.0, 10.0], [5e-5, -4e-5, 1.0]])
    warped = _warp(gray, H)
    folder = tmp_path_factory.mktemp("photo_pair")
    cv2.imwrite(str(folder / "a.png"), gray)
    cv2.imwrite(str(folder / "b.png"), warped)
    (ka, da), (kb, db) = _sift(gray), _sift(warped)
    h, w = gray.shape
    return (
        ImageData("a.png", 1, folder / "a.png", ka, da, w, h),
        ImageData("b.png", 2, folder / "b.png", kb, db, w, h),
        H,
    )


@pytest.mark.parametrize("name", ["guided_homography", "guided_epipolar"])
def test_classical_guided_baselines_on_known_homography(photo_pair, name):
    a, b, H = photo_pair
    raw = get_matcher("raw", {"device": "cpu"}).match(a, b)
    matcher = get_matcher(name, {"device": "cpu"})
    da, db = (
        normalize_descriptors(a.descriptors, "cpu"),
        normalize_descriptors(b.descriptors, "cpu"),
    )
    model = matcher.seed_model(a, b, da, db)
    assert model is not None
    got = matcher.match(a, b).astype(np.int64)
    assert len(got) >= len(raw) and _share_correct(got, a.keypoints, b.keypoints, H) > 0.9
    pa, pb = (
        torch.from_numpy(a.keypoints[got[:, 0], :2]),
        torch.from_numpy(b.keypoints[got[:, 1], :2]),
    )
    model = torch.tensor(model, dtype=torch.float32)
    if name == "guided_homography":
        assert torch.all(
            torch.linalg.norm(apply_homography(model, pa) - pb, dim=1) < matcher.conf["window_px"]
        )
    else:
        d_b, d_a = epipolar_distances(model, pa, pb)
        assert torch.all(d_b.diagonal() < matcher.conf["band_px"]) and torch.all(
            d_a.diagonal() < matcher.conf["band_px"]
        )


def test_colmap_guided_matching_on_known_homography(photo_pair):
    """COLMAP's own guided matching re-matches along the verified geometry: more matches, still
    right, one-to-one."""

    def as_stored(im):  # SIFT as COLMAP's database stores it (uint8)
        return ImageData(
            im.name,
            im.image_id,
            im.path,
            im.keypoints,
            np.clip(np.round(im.descriptors * 512), 0, 255).astype(np.uint8),
            im.width,
            im.height,
        )

    (a, b), H = map(as_stored, photo_pair[:2]), photo_pair[2]
    raw = get_matcher("raw", {"device": "cpu"}).match(a, b)
    got = get_matcher("guided_colmap", {"device": "cpu"}).match(a, b).astype(np.int64)
    assert len(got) > len(raw) and _share_correct(got, a.keypoints, b.keypoints, H) > 0.9
    assert len(np.unique(got[:, 0])) == len(got) and len(np.unique(got[:, 1])) == len(got)
    with pytest.raises(ValueError, match="SIFT"):
        # float descriptors
        get_matcher("guided_colmap", {"device": "cpu"}).match(photo_pair[0], photo_pair[1])


def test_epipolar_distance_convention_matches_pycolmap():
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], size=(60, 3))
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R, _ = cv2.Rodrigues(np.array([0.0, 0.2, 0.05]))
    xa = (K @ X.T).T
    xb = (K @ (R @ X.T + np.array([[-1.0], [0.1], [0.2]]))).T
    pa, pb = xa[:, :2] / xa[:, 2:], xb[:, :2] / xb[:, 2:]
    F = pycolmap.estimate_fundamental_matrix(pa, pb)["F"]
    d_b, d_a = epipolar_distances(torch.tensor(F), torch.tensor(pa), torch.tensor(pb))
    assert d_b.diagonal().max() < 1e-3 and d_a.diagonal().max() < 1e-3
    assert d_b.median() > 10  # unrelated points are far from each other's epipolar lines


def test_keypoint_scales_from_affine_and_scale_columns():
    kp4 = np.array([[0, 0, 2.0, 0.3], [0, 0, 5.0, 1.0], [0, 0, 1.0, 0.0]], np.float32)
    theta = 0.7
    rot = np.array([np.cos(theta), -np.sin(theta), np.sin(theta), np.cos(theta)])
    # COLMAP affine: scale * rotation
    kp6 = np.concatenate([np.zeros((3, 2)), kp4[:, 2:3] * rot], 1)
    np.testing.assert_allclose(keypoint_scales(kp6), kp4[:, 2], rtol=1e-6)
    np.testing.assert_array_equal(top_scale_indices(kp4, 0.34), [1])


def test_registry():
    assert set(MATCHERS) == {
        "raw",
        "guided",
        "guided_epipolar",
        "guided_homography",
        "guided_colmap",
        "lightglue",
        "guided_lightglue",
        "lighterglue",
        "guided_lighterglue",
    }
    with pytest.raises(ValueError, match="Unknown matcher"):
        get_matcher("nope")
    with pytest.raises(ValueError, match="Unknown raw matcher option"):
        get_matcher("raw", {"ratoi": 0.8})


def test_guided_matcher_end_to_end_on_known_homography(photo_pair):
    a, b, H = photo_pair
    matcher = get_matcher("guided", {"device": "cpu", "ratio": 0.9})
    flows = matcher.coarse_flows(a, b)
    got = matcher.match_flows(a, b, flows)
    np.testing.assert_array_equal(matcher.match(a, b), got)  # features reused from the cache
    assert (
        len(got) > 100 and _share_correct(got.astype(np.int64), a.keypoints, b.keypoints, H) > 0.9
    )
    i, j = got[:, 0].astype(np.int64), got[:, 1].astype(np.int64)
    w = matcher.conf["window_cells"]
    assert np.all(np.linalg.norm(flows.flow_ab[i] - b.keypoints[j, :2], axis=1) < w * flows.cell_b)
    assert np.all(np.linalg.norm(flows.flow_ba[j] - a.keypoints[i, :2], axis=1) < w * flows.cell_a)
    assert a.name in matcher.coarse.cache
    matcher.release(a.name)
    assert a.name not in matcher.coarse.cache


def test_guided_matcher_weights_fallback_is_loud(tmp_path):
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    logger.addHandler(handler)
    try:
        matcher = get_matcher("guided", {"device": "cpu"})
    finally:
        logger.removeHandler(handler)
    warned = [
        r for r in records if r.levelno == logging.WARNING and "coarse filter" in r.getMessage()
    ]
    if DEFAULT_WEIGHTS.exists():
        assert matcher.coarse.conf["mode"] == "filter" and not warned
    else:
        assert matcher.coarse.conf["mode"] == "raw" and len(warned) == 1
    with pytest.raises(FileNotFoundError):
        get_matcher("guided", {"device": "cpu", "weights": str(tmp_path / "missing.safetensors")})


@pytest.mark.parametrize("ratio, raw_ratio", [(0.8, 0.8), (0.9, 0.8), (0.8, None)])
def test_raw_merge_adds_raw_matches_of_unmatched_keypoints_only(photo_pair, ratio, raw_ratio):
    """raw_matches="merge": the guided matches (ratio), plus raw matches (raw_ratio) whose keypoints
    guidance left unmatched; one-to-one."""
    a, b, _ = photo_pair
    guided = get_matcher("guided", {"device": "cpu", "raw_matches": None})
    flows = guided.coarse_flows(a, b)
    only = guided.match_flows(a, b, flows, ratio=ratio).astype(np.int64)
    both = guided.match_flows(
        a, b, flows, ratio=ratio, raw_ratio=raw_ratio, raw_matches="merge"
    ).astype(np.int64)
    raw = get_matcher("raw", {"device": "cpu", "ratio": raw_ratio}).match(a, b).astype(np.int64)
    assert (
        {tuple(m) for m in only}
        <= {tuple(m) for m in both}
        <= {tuple(m) for m in only} | {tuple(m) for m in raw}
    )
    assert len(np.unique(both[:, 0])) == len(both) and len(np.unique(both[:, 1])) == len(both)
    with pytest.raises(ValueError, match=r"takes no option \['min_inliers'\] after its guidance"):
        # a verification option, not one applied after the flows
        guided.match_flows(a, b, flows, min_inliers=15)
    in_both, ga, gb = {tuple(m) for m in both}, set(only[:, 0]), set(only[:, 1])
    # a raw match is kept unless guidance overrules it
    assert all(tuple(m) in in_both or m[0] in ga or m[1] in gb for m in raw)


def test_matching_uses_one_torch_thread_and_leaves_the_process_as_it_was(synthetic_scene, tmp_path):
    """A library changes no global state: building a guided matcher leaves torch's thread count
    alone; match_database matches with the matcher's torch_threads (1 on CPU, the pipeline's speed)
    and restores it. The pair workers still count on one torch thread per pair."""
    import os

    import pycolmap

    from colmap_guided.match import match_database
    from colmap_guided.matchers.base import scoped_torch_threads
    from colmap_guided.matchers.raw import RawMatcher

    class Recording(RawMatcher):
        torch_threads = 1
        seen: set = set()

        def match(self, a, b):
            Recording.seen.add(torch.get_num_threads())
            return super().match(a, b)

    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    with scoped_torch_threads(3):  # a process that uses 3 threads
        guided = get_matcher("guided", {"device": "cpu"})
        assert torch.get_num_threads() == 3
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
        assert guided.torch_threads == 1 and guided.pair_workers == min(8, cores)
        match_database(db, synthetic_scene.image_dir, matcher=Recording())
        assert Recording.seen == {1} and torch.get_num_threads() == 3


def test_default_camera_is_the_one_colmaps_feature_extractor_writes(synthetic_scene, tmp_path):
    """verify.default_camera (the camera of a pair without a database: guided_colmap, imports of
    plain hloc files, benchmarks) equals the camera pycolmap's extractor writes for a photo without
    EXIF focal."""
    import pycolmap
    from PIL import Image

    from colmap_guided import verify

    (tmp_path / "images").mkdir()
    with Image.open(
        synthetic_scene.image_dir / synthetic_scene.names[0]
    ) as im:  # its EXIF focal dropped
        Image.fromarray(np.asarray(im)[:, :400]).save(tmp_path / "images" / "plain.png")
    db = tmp_path / "db.db"
    pycolmap.extract_features(db, tmp_path / "images")
    with pycolmap.Database.open(str(db)) as database:
        (camera,) = database.read_all_cameras()
    ours = verify.default_camera(camera.width, camera.height)
    assert (
        ours.model == camera.model and ours.width == camera.width and ours.height == camera.height
    )
    np.testing.assert_allclose(ours.params, camera.params)


def test_raw_matches_verified_never_loses_what_raw_matching_verifies(photo_pair):
    """raw_matches='verified' (default): with the coarse flow wrong across the whole pair
    (shifted by 120 px), guided matching alone verifies little, and the matcher keeps the raw side's
    verified inliers instead; with the right flow it verifies at least as many inliers as the better
    side."""
    import dataclasses

    from colmap_guided import verify

    a, b, _ = photo_pair
    guided = get_matcher("guided", {"device": "cpu"})
    assert guided.conf["raw_matches"] == "verified"

    def inliers(matches):
        return len(verify.verify_images(a, b, matches, guided.verification_conf).inlier_matches)

    raw = inliers(get_matcher("raw", {"device": "cpu"}).match(a, b))
    right = guided.coarse_flows(a, b)
    wrong = dataclasses.replace(right, flow_ab=right.flow_ab + 120.0, flow_ba=right.flow_ba - 120.0)
    guided_only = {
        name: inliers(guided.match_flows(a, b, flows, raw_matches=None))
        for name, flows in (("right", right), ("wrong", wrong))
    }
    assert guided_only["wrong"] < raw / 4 and raw > 100
    assert inliers(guided.match_flows(a, b, wrong)) >= raw
    assert inliers(guided.match_flows(a, b, right)) >= max(raw, guided_only["right"])
    with pytest.raises(ValueError, match="raw_matches must be"):
        get_matcher("guided", {"device": "cpu", "raw_matches": "union"})


def test_a_new_matcher_plugs_into_the_pipeline_through_the_base_class_only(
    synthetic_scene, tmp_path
):
    """What match_database asks of a matcher is declared on Matcher: ``prepare`` runs once per
    image, before its first pair, and what it puts in ``image.extra`` reaches ``match``;
    ``verification_conf`` sets the pair's two-view verification (an impossible 10**6 inliers: no
    pair verifies); ``release`` comes once per image after its last pair."""
    import pycolmap

    from colmap_guided import database as dbio
    from colmap_guided.match import match_database
    from colmap_guided.matchers.base import Matcher

    class Plugged(Matcher):
        name = "plugged"
        default_conf = {"ratio": 0.8}

        def __init__(self, conf=None):
            super().__init__(conf)
            self.raw = get_matcher("raw", {"ratio": self.conf["ratio"], "device": "cpu"})
            self.prepared, self.released = [], []

        @property
        def verification_conf(self):
            return {"min_num_inliers": 10**6}

        def prepare(self, image):
            self.prepared.append(image.name)
            image.extra["plugged"] = len(image.keypoints)

        def match(self, a, b):
            assert a.extra["plugged"] == len(a.keypoints) and b.extra["plugged"] == len(b.keypoints)
            return self.raw.match(a, b)

        def release(self, name):
            self.released.append(name)

    db = tmp_path / "db.db"
    pycolmap.extract_features(db, synthetic_scene.image_dir)
    matcher = Plugged()
    stats = match_database(db, synthetic_scene.image_dir, pairs_path="exhaustive", matcher=matcher)
    names = sorted(synthetic_scene.names)
    assert sorted(matcher.prepared) == names and sorted(matcher.released) == names
    assert (
        stats["verification"]["min_num_inliers"] == 10**6
        and stats["num_matches"] > 0
        and stats["num_verified_pairs"] == 0
    )
    with dbio.open_database(db) as database:
        assert len(dbio.pair_match_counts(database)) == len(names) * (len(names) - 1) // 2
        assert not any(dbio.pair_inlier_counts(database).values())
        a, b = (
            dbio.read_image_data(database, image, synthetic_scene.image_dir)
            for image in list(dbio.images_by_name(database).values())[:2]
        )
    # A matcher without a guidance step runs variants through the same two-step calls as the guided
    # one.
    matcher.prepare(a), matcher.prepare(b)
    assert np.array_equal(
        matcher.match_flows(a, b, matcher.coarse_flows(a, b)), matcher.raw.match(a, b)
    )
    with pytest.raises(ValueError, match="no option"):
        matcher.match_flows(a, b, None, ratio=0.9)


def test_raw_matches_verified_keeps_a_raw_pair_at_colmaps_threshold_and_guided_at_25():
    """A pair whose raw matches verify 20 inliers (COLMAP's 15 would keep it) and whose guided
    matches are chance matches: the raw matches are kept and pass the pipeline's verification; 20
    correct guided matches alone (under the guided 25) do not pass."""
    from colmap_guided import verify

    rng = np.random.default_rng(0)
    H = np.array([[0.9, 0.05, 40.0], [-0.04, 0.95, 25.0], [2e-5, 1e-5, 1.0]])
    pts = rng.uniform(50, 590, (300, 2)).astype(np.float32)
    proj = np.c_[pts, np.ones(len(pts))] @ H.T
    kp_b = (proj[:, :2] / proj[:, 2:]).astype(np.float32)

    def keypoints(xy):
        return np.c_[xy, np.ones((len(xy), 1)), np.zeros((len(xy), 1))].astype(np.float32)

    desc = np.zeros((len(pts), 128), np.uint8)
    a = ImageData("a.jpg", 1, Path("a.jpg"), keypoints(pts), desc, 640, 640)
    b = ImageData("b.jpg", 2, Path("b.jpg"), keypoints(kp_b), desc, 640, 640)
    right = np.stack([np.arange(20), np.arange(20)], 1)
    chance = np.stack([np.arange(20, 80), rng.permutation(np.arange(20, 300))[:60]], 1)
    guided = get_matcher("guided", {"device": "cpu"})
    assert guided.verification_conf == {"min_num_inliers": 15}
    options = verify.two_view_options(guided.verification_conf)
    cam = verify.default_camera(640, 640)

    def verified(matches):
        return len(
            verify.verify_pair(
                cam, a.keypoints, cam, b.keypoints, np.asarray(matches, np.uint32), options
            ).inlier_matches
        )

    def best_of(guided_matches, raw_matches, raw_below=None):
        matches, geometry = verify.best_of(
            cam, a.keypoints, cam, b.keypoints, guided_matches, lambda: raw_matches, options,
            25, 15, 0.9, raw_below,
        )  # fmt: skip
        # the geometry written with the matches is the pipeline's verification of them
        assert np.array_equal(geometry.inlier_matches, verify.verify_pair(
            cam, a.keypoints, cam, b.keypoints, matches, options).inlier_matches)  # fmt: skip
        return matches

    kept = best_of(chance, np.r_[right, chance[:30]])
    # the raw pair, as plain COLMAP keeps it (before: lost under the guided 25)
    assert verified(kept) == 20
    # 20 guided inliers < 25: rejected
    assert verified(best_of(right, chance)) == 0
    more = np.stack([np.arange(30), np.arange(30)], 1)
    # >= 25 guided inliers pass
    assert verified(best_of(more, chance)) == 30
    assert get_matcher("guided", {"device": "cpu", "raw_matches": None}).verification_conf == {
        "min_num_inliers": 25
    }


def test_raw_matches_verified_keeps_the_raw_pair_when_the_guided_geometry_contradicts_it():
    """Guided and raw matches that both verify on their own but tell two different epipolar
    geometries (one of them holds wrong inliers its own RANSAC accepted: proxy
    sacre_coeur_hloc_realistic, 30-60 % wrong inliers on 11 of 45 pairs): the raw matches are kept,
    as plain COLMAP keeps the pair; when the two agree, the union of their inliers."""
    from colmap_guided import verify

    rng = np.random.default_rng(1)
    K = np.array([[700.0, 0, 320], [0, 700, 320], [0, 0, 1]])

    def project(X, yaw_deg, t):
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        x = (X @ R.T + t) @ K.T
        return (x[:, :2] / x[:, 2:]).astype(np.float32)

    X = np.c_[rng.uniform(-2, 2, (200, 2)), rng.uniform(6, 10, 200)]  # a deep, non-planar scene
    kp_a = project(X, 0, np.zeros(3))
    # true view, then a wrong one
    kp_b = np.r_[project(X, 12, np.array([-1.0, 0, 0])), project(X, -15, np.array([0.8, 0.3, 0]))]

    def keypoints(xy):
        return np.c_[xy, np.ones((len(xy), 1)), np.zeros((len(xy), 1))].astype(np.float32)

    desc = np.zeros((len(kp_b), 128), np.uint8)
    a = ImageData("a.jpg", 1, Path("a.jpg"), keypoints(kp_a), desc[:200], 640, 640)
    b = ImageData("b.jpg", 2, Path("b.jpg"), keypoints(kp_b), desc, 640, 640)
    cam = verify.default_camera(640, 640)
    options = verify.two_view_options({"min_num_inliers": 15})

    def verified(matches):
        return verify.verify_pair(
            cam, a.keypoints, cam, b.keypoints, np.asarray(matches, np.uint32), options
        ).inlier_matches

    right_raw = np.stack([np.arange(0, 40), np.arange(0, 40)], 1)
    right_guided = np.stack([np.arange(20, 100), np.arange(20, 100)], 1)
    # a consistent but wrong geometry
    wrong_guided = np.stack([np.arange(100, 180), np.arange(300, 380)], 1)
    assert len(verified(right_raw)) == 40 and len(verified(wrong_guided)) == 80

    def best_of(guided_matches, raw_matches, min_agreement=0.9, raw_below=None):
        def raw():
            calls.append(1)
            return raw_matches

        calls = []
        matches = verify.best_of(
            cam, a.keypoints, cam, b.keypoints, guided_matches, raw, options, 25, 15,
            min_agreement, raw_below,
        )[0]  # fmt: skip
        return matches, len(calls)

    wrong_geometry = verify.verify_pair(
        cam, a.keypoints, cam, b.keypoints, wrong_guided.astype(np.uint32), options
    )
    # the raw inliers do not fit it
    assert verify.agreement(wrong_geometry, a.keypoints, b.keypoints, right_raw, 4.0) < 0.2
    kept, _ = best_of(wrong_guided, right_raw)
    assert np.array_equal(kept, right_raw)  # 40 raw inliers, not the 80 wrong guided ones
    union = np.asarray(verified(best_of(right_guided, right_raw)[0]))
    # agreeing sides: the union of both
    assert len(union) == 100 and set(union[:, 0]) == set(range(100))
    # the old choice
    assert len(verified(best_of(wrong_guided, right_raw, min_agreement=0.0)[0])) == 80
    # guided matches reaching raw_below inliers are kept without raw matching
    kept, raw_calls = best_of(wrong_guided, right_raw, raw_below=80)
    assert np.array_equal(kept, wrong_guided) and raw_calls == 0
    assert best_of(wrong_guided, right_raw, raw_below=81)[1] == 1
