"""Archival degradations: shapes, determinism, and that every effect does what it claims."""

import cv2
import numpy as np
import pytest

from colmap_guided import archival, cards
from colmap_guided.paths import shared_data_dir


@pytest.fixture(scope="module")
def photo(shared_data):
    path = shared_data_dir() / "lightglue_assets" / "images" / "sacre_coeur1.jpg"
    if not path.exists():
        candidates = sorted((shared_data_dir() / "sacre_coeur_hloc" / "images").glob("*.jpg"))
        path = candidates[0]
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert bgr is not None, path
    rgb = np.ascontiguousarray(bgr[..., ::-1])
    return cv2.resize(
        rgb, (480, int(round(480 * rgb.shape[0] / rgb.shape[1]))), interpolation=cv2.INTER_AREA
    )


def _colourfulness(img):
    f = img.astype(np.float32)
    return float(np.abs(f - f.mean(2, keepdims=True)).mean())


def test_shapes_dtypes_and_gray_input(photo):
    out = archival.degrade(photo, 0)
    assert out.dtype == np.uint8 and out.shape == photo.shape
    gray = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    out = archival.degrade(gray, 0, effects=["sepia", "grain"])
    assert out.shape == photo.shape and out.dtype == np.uint8
    with pytest.raises(TypeError):
        archival.degrade(photo.astype(np.float32), 0)
    with pytest.raises(ValueError):
        archival.degrade(photo, 0, effects=["sparkles"])
    with pytest.raises(ValueError):
        archival.apply_preset(photo, "nonexistent")


def test_deterministic_by_seed(photo):
    a = archival.degrade(photo, np.random.default_rng(7), strength=1.2, crop=0.2)
    b = archival.degrade(photo, np.random.default_rng(7), strength=1.2, crop=0.2)
    c = archival.degrade(photo, np.random.default_rng(8), strength=1.2, crop=0.2)
    assert np.array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)
    for name in archival.PRESETS:
        assert np.array_equal(
            archival.apply_preset(photo, name, 3), archival.apply_preset(photo, name, 3)
        )


def test_zero_strength_is_identity(photo):
    assert np.array_equal(
        archival.degrade(photo, 0, strength=0.0, effects=list(archival.EFFECTS)), photo
    )
    assert np.array_equal(archival.apply_preset(photo, "none"), photo)


def test_each_effect_changes_the_image_the_way_it_should(photo):
    f = photo.astype(np.float32)

    def run(name, seed=1):
        return archival.degrade(photo, seed, effects=[name]).astype(np.float32)

    assert _colourfulness(photo) > 5
    g = run("grayscale")
    assert _colourfulness(g) < 0.6  # channels equal up to rounding
    s = run("sepia")
    assert s[..., 0].mean() > s[..., 2].mean() + 10  # warm: red over blue
    faded = run("fade")
    assert faded.std() < 0.8 * f.std() and faded.min() > f.min() + 5  # less contrast, lifted blacks

    def lap(im):
        return float(
            np.abs(
                cv2.Laplacian(cv2.cvtColor(im.astype(np.uint8), cv2.COLOR_RGB2GRAY), cv2.CV_32F)
            ).mean()
        )

    assert lap(run("blur")) < 0.7 * lap(f)  # high frequencies removed
    grain = run("grain")
    assert lap(grain) > 1.3 * lap(f) and abs(grain.mean() - f.mean()) < 3  # noise, same brightness
    jp = run("jpeg")
    assert 0.5 < np.abs(jp - f).mean() < 10  # lossy but recognisable
    v = run("vignette")
    h, w = photo.shape[:2]

    def corner(im):
        return im[: h // 8, : w // 8].mean() / max(
            im[3 * h // 8 : 5 * h // 8, 3 * w // 8 : 5 * w // 8].mean(), 1
        )

    assert corner(v) < 0.85 * corner(f)  # corners darker relative to the centre
    sc = run("scratches")
    changed = np.abs(sc - f).max(axis=2) > 30
    assert 1e-4 < changed.mean() < 0.05  # thin lines and specks: few pixels, strongly changed


def test_crop_offset_maps_points(photo):
    out, (x0, y0) = archival.degrade(photo, 5, strength=0.0, crop=0.3, return_offset=True)
    h, w = out.shape[:2]
    assert (
        0.69 * photo.shape[0] <= h <= photo.shape[0]
        and 0.69 * photo.shape[1] <= w <= photo.shape[1]
    )
    # a pixel of the output at (x, y) is the input pixel at (x + x0, y + y0)
    assert np.array_equal(out, photo[y0 : y0 + h, x0 : x0 + w])


def test_random_subset_varies_with_seed(photo):
    outs = [archival.degrade(photo, s) for s in range(6)]
    gray = [_colourfulness(o) < 1 for o in outs]
    assert any(gray) and not all(gray)  # both black-and-white and colour looks occur
    means = [o.astype(np.float32).mean() for o in outs]
    assert np.std(means) > 1.0  # different seeds give visibly different looks


def test_halftone_prints_dots_of_the_same_tone(photo):
    f = photo.astype(np.float32)
    dots = archival.degrade(photo, 2, effects=["halftone"]).astype(np.float32)
    assert abs(dots.mean() - f.mean()) < 12  # the screen keeps the tone
    assert np.abs(dots - f).mean() > 5  # ... in dots
    gray = archival.degrade(photo, 2, effects=["grayscale", "halftone"])
    assert _colourfulness(gray) < 0.6  # one screen for a gray print


def test_postcards_and_collages_are_what_the_card_finder_reads(photo, tmp_path):
    """The simulated cards: the picture box, and a collage's panels, found where they were put."""
    card, box = archival.mount(photo, archival.PAPERS[1], 30, ("Partie am Schloss",))
    cv2.imwrite(str(tmp_path / "card.jpg"), card[..., ::-1])
    found = cards.find_layout(tmp_path / "card.jpg")
    assert found.border and not found.panels
    assert np.abs(np.subtract(found.picture, box)).max() <= 3
    # smooth colour prints at the proxy's size: the picture, not the whole card
    large = cv2.resize(photo, None, fx=1024 / photo.shape[1], fy=1024 / photo.shape[1])
    for seed in range(3):
        card, box = archival.postcard(archival.apply_preset(large, "postcard_colour", seed), seed)
        cv2.imwrite(str(tmp_path / "colour.jpg"), card[..., ::-1])
        found = cards.find_layout(tmp_path / "colour.jpg")
        assert not found.whole and np.abs(np.subtract(found.picture, box)).max() <= 15, seed
    flipped = np.ascontiguousarray(photo[:, ::-1])
    card, boxes = archival.collage([photo, flipped], archival.PAPERS[0], 30, 20)
    cv2.imwrite(str(tmp_path / "collage.jpg"), card[..., ::-1])
    found = cards.find_layout(tmp_path / "collage.jpg")
    assert len(found.panels) == 2
    assert np.abs(np.subtract(found.panels, boxes)).max() <= 3
