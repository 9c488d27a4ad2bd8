"""Training data: F from SfM poses, GT matches, synthetic homography pairs, batches and sampling."""

import numpy as np
import pytest
import torch

from colmap_guided.geometry import apply_h
from colmap_guided.images import read_image
from colmap_guided.train import augment, scenes, views
from colmap_guided.train import data as D
from colmap_guided.train import geometry as G
from colmap_guided.train.losses import epipolar_distance

SMALL = dict(
    train_scenes=["bundler_et", "vggsfm_statue", "bundler_kermit"],
    val_scenes=["strecha_entry_P10"],
    max_images_per_scene=4,
    resolution=160,
    n_variants=3,
    n_synthetic=1,
    val_pairs_per_scene=3,
)


@pytest.fixture(scope="module")
def small_data(tmp_path_factory, shared_data):
    return D.CoarseTrainData({**SMALL, "cache_dir": str(tmp_path_factory.mktemp("cache"))})


def _dist(F, xa, xb):
    return epipolar_distance(
        torch.tensor(F)[None],
        torch.tensor(xa, dtype=torch.float64)[None],
        torch.tensor(xb, dtype=torch.float64)[None],
    )[0].numpy()


def test_sfm_pairs_and_fundamental_matrices(shared_data):
    scene = scenes.load_scene("strecha_entry_P10", min_shared=30)
    assert len(scene.images) == 10 and len(scene.pairs) > 20
    assert all(p.n_shared >= 30 for p in scene.pairs)
    for p in scene.pairs[:10]:
        A, B = scene.images[p.a], scene.images[p.b]
        xa, xb = G.ideal_pixels(A.camera, p.xy_a), G.ideal_pixels(B.camera, p.xy_b)
        d = _dist(p.F, xa, xb)
        # pseudo-GT reprojection error level
        assert np.median(d) < 0.5 and np.percentile(d, 90) < 2.0
        # wrong pairing of the same points is far from the lines: the check has teeth
        assert np.median(_dist(p.F, xa, np.roll(xb, 7, axis=0))) > 20
        # F in scaled frames
        sa, sb = np.array([0.4, 0.41]), np.array([0.25, 0.26])
        assert (
            np.median(_dist(G.scale_fundamental(p.F, sa, sb), xa * sa, xb * sb))
            < 0.5 * sb.max() + 1e-6
        )


def test_pair_mining_counts_shared_tracks(shared_data):
    import pycolmap

    rec = pycolmap.Reconstruction(str(scenes.scene_model_dir("bundler_et")))
    scene = scenes.load_scene("bundler_et", min_shared=30)
    by_name = {im.name: im for im in rec.images.values()}
    p = scene.pairs[0]
    ids_a = {q.point3D_id for q in by_name[p.a].points2D if q.has_point3D()}
    ids_b = {q.point3D_id for q in by_name[p.b].points2D if q.has_point3D()}
    assert p.n_shared == len(ids_a & ids_b)
    all_pairs = scenes.load_scene("bundler_et", min_shared=1).pairs
    assert len(all_pairs) > len(scene.pairs)  # the threshold removes weak pairs


def test_synthetic_homography_pair_is_exact(small_data):
    key = next(k for k in small_data.views if k.startswith("syn/"))
    view = small_data.views[key]
    im = small_data.scenes[view.scene].images[view.name]
    photo = read_image(im.path).astype(np.float32)
    warped = augment.warp_image(
        photo.astype(np.uint8), view.H, view.geometry.width, view.geometry.height
    ).astype(np.float32)
    rng = np.random.default_rng(0)
    pts = np.stack([rng.uniform(0, im.width, 4000), rng.uniform(0, im.height, 4000)], 1)
    mapped = apply_h(view.H, pts)
    ok = (
        views.inside(mapped, view.geometry)
        & (mapped.min(1) > 2)
        & (mapped[:, 0] < view.geometry.width - 2)
        & (mapped[:, 1] < view.geometry.height - 2)
    )
    assert ok.sum() > 200
    # pixel value in the photo at p (pixel centre convention) vs in the warp at H p
    a = photo[np.floor(pts[ok, 1]).astype(int), np.floor(pts[ok, 0]).astype(int)]
    b = warped[np.floor(mapped[ok, 1]).astype(int), np.floor(mapped[ok, 0]).astype(int)]
    err = np.abs(a - b).mean()
    err_shuffled = np.abs(a - np.roll(b, 13, axis=0)).mean()
    assert err < 0.5 * err_shuffled
    # the synthetic sample's matches satisfy its induced F (in resized frames)
    s = small_data.synthetic_sample(im, 0, 0, np.random.default_rng(1))
    assert len(s.pts_a) > 10
    d = _dist(s.F, s.pts_a * s.a.geometry.scale, s.pts_b * s.b.geometry.scale)
    assert d.max() < 1e-6
    # and the cached render of that view is the same warp, with the stored H
    assert small_data.render(key).shape == (view.geometry.height, view.geometry.width, 3)


def test_archival_variants_differ_and_are_deterministic(small_data):
    key0 = next(
        k
        for k in small_data.views
        if k.startswith("img/") and k.endswith("/v0") and "bundler_et" in k
    )
    key1 = key0[:-1] + "1"
    clean, degraded = small_data.render(key0), small_data.render(key1)
    assert clean.shape == degraded.shape
    assert np.abs(clean.astype(int) - degraded).mean() > 2
    assert np.array_equal(degraded, small_data.render(key1))


def test_sampler_is_seeded_and_balanced(small_data):
    a = small_data.sample_batch(np.random.default_rng(3), 8, 4)
    b = small_data.sample_batch(np.random.default_rng(3), 8, 4)
    assert [(s.a.key, s.b.key) for s in a] == [(s.a.key, s.b.key) for s in b]
    neg = [s for s in a if not s.positive]
    assert len(neg) == 4 and all(s.a.scene != s.b.scene for s in neg)
    pos = [s for s in a if s.positive]
    assert all(s.a.scene == s.b.scene for s in pos)
    many = small_data.sample_batch(np.random.default_rng(4), 200, 0)
    kinds = {s.source for s in many}
    assert kinds == {"sfm", "synthetic"}
    assert any("/v1" in s.a.key or "/v1" in s.b.key for s in many)  # archival versions are drawn
    assert any("/v2" in s.a.key or "/v2" in s.b.key for s in many)  # and small soft scans
    # either image may be old
    assert any(s.a.key.endswith("/v0") and "/v0" not in s.b.key for s in many)
    assert any("/v0" not in s.a.key and s.b.key.endswith("/v0") for s in many)
    assert set(small_data.val_scenes).isdisjoint(s.a.scene for s in many)


@pytest.mark.parametrize("max_cells", [None, 5])
def test_collate_cell_indices_and_padding(small_data, max_cells):
    rng = np.random.default_rng(5)
    samples = small_data.sample_batch(rng, 6, 2)
    if max_cells:
        samples = [views.crop_sample(s, max_cells, rng) for s in samples]
        assert all(s.a.grid[2] <= max_cells and s.b.grid[3] <= max_cells for s in samples)
    batch = D.collate(samples, small_data, with_features=False)
    wa = batch["xy_a"].shape[2]
    wb = batch["xy_b"].shape[2]
    n_kept = 0
    for i, s in enumerate(samples):
        m = batch["matches"][i]
        valid = m[:, 0] >= 0
        got = {(int(a), int(b)) for a, b in m[valid]}
        # brute force: nearest cell centre of each GT point, kept when both cells are in the windows
        want = set()
        for pa, pb in zip(s.pts_a, s.pts_b):
            flat = []
            for view, p, w in ((s.a, pa, wa), (s.b, pb, wb)):
                g = view.geometry
                idx = int(np.argmin(np.linalg.norm(g.cell_centers() - p, axis=1)))
                row, col = divmod(idx, g.grid_width)
                r0, c0, h, ww = view.grid
                flat.append(
                    (row - r0) * w + (col - c0)
                    if 0 <= row - r0 < h and 0 <= col - c0 < ww
                    else None
                )
            if None not in flat:
                want.add(tuple(flat))
        assert got == want
        n_kept += int(valid.sum())
        for view, key in ((s.a, "xy_a"), (s.b, "xy_b")):
            _, _, h, ww = view.grid
            # the window's centres
            assert np.allclose(batch[key][i, :h, :ww].numpy(), view.crop_xy())
    if not max_cells:
        assert n_kept == sum(len(s.pts_a) for s in samples)  # nothing dropped without windows
    assert n_kept > 0


def test_cached_features_match_backbone(small_data):
    from colmap_guided.coarse.model import CoarseNet
    from colmap_guided.train.trainer import _NormalizedBackbone

    keys = sorted(small_data.views)[:2]
    model = CoarseNet()
    small_data.build_cache(_NormalizedBackbone(model), keys)
    x = torch.from_numpy(small_data.render(keys[0])).permute(2, 0, 1).float()[None]
    with torch.no_grad():
        ref = model.extract_features(model.normalize(x))[0]
    got = small_data.features(keys[0])
    assert got.shape == ref.shape
    assert torch.allclose(got, ref, atol=2e-3)  # float16 storage
    # L2-normalised per cell
    assert torch.allclose(got.norm(dim=0), torch.ones_like(got[0]), atol=5e-3)


def test_soft_scan_is_a_soft_copy_in_place(shared_data):
    """A small, soft scan (scale gaps) loses fine detail but stays pixel-aligned with the photo
    (the view's geometry is unchanged)."""
    import cv2

    path = next(iter(scenes.load_scene("strecha_entry_P10").images.values())).path
    img = cv2.resize(read_image(path), (512, 336), interpolation=cv2.INTER_AREA)
    out = augment.soft_scan(img, np.random.default_rng(0))
    assert out.shape == img.shape and out.dtype == np.uint8

    def detail(x):
        return cv2.Laplacian(
            cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32), cv2.CV_32F
        ).var()

    assert detail(out) < 0.3 * detail(img)

    def low(x):
        return cv2.GaussianBlur(x.astype(np.float32), (0, 0), 3)

    aligned = np.abs(low(out) - low(img)).mean()
    assert aligned < 0.5 * np.abs(low(out) - low(np.roll(img, 4, axis=1))).mean()
