"""Bad input: every odd file either works or is skipped with a reason (report.json), nothing else
lost; every unusable command gives one line that says what to do. Real files, real COLMAP."""

from __future__ import annotations

import json
import re
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from PIL import Image

from colmap_guided import images
from colmap_guided.__main__ import main
from colmap_guided.log import set_verbosity
from colmap_guided.reconstruct import reconstruct
from colmap_guided.report import summary_text
from colmap_guided.synthetic import render_scene

GLOG_LINE = re.compile(r"^[IWE]\d{8} ", re.M)
OUR_ERROR = re.compile(r"^\[[\d:]+ colmap_guided ERROR\] (.+)$", re.M)


def _texture(h: int = 120, w: int = 160, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def _exif_rotated(rgb: np.ndarray, path: Path) -> None:
    """Pixels stored rotated 90° CCW with orientation 6 ('rotate 90° CW to display')."""
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(np.ascontiguousarray(np.rot90(rgb, 1))).save(
        path, exif=exif.tobytes(), quality=92
    )


def write_bad_files(folder: Path, rgb: np.ndarray) -> dict[str, str]:
    """The unusable files; {name: a word the skip reason must contain}."""
    folder.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(folder / "_good.jpg", quality=92)
    good = (folder / "_good.jpg").read_bytes()
    (folder / "_good.jpg").unlink()
    (folder / "truncated.jpg").write_bytes(good[: len(good) // 2])
    damaged = bytearray(good)
    damaged[len(damaged) // 3 : len(damaged) // 3 + 1500] = (
        np.random.default_rng(1).integers(0, 256, 1500, dtype=np.uint8).tobytes()
    )
    (folder / "corrupt.jpg").write_bytes(bytes(damaged))
    (folder / "notes.jpg").write_text("These are the archivist's notes, not a photo.\n")
    (folder / "empty.png").write_bytes(b"")
    Image.fromarray(rgb).save(folder / "modern.webp")
    Image.fromarray(rgb[:40, :50]).save(folder / "tiny.jpg")
    Image.fromarray(rgb).convert("L").save(folder / "_g.png")
    png = (folder / "_g.png").read_bytes()
    (folder / "_g.png").unlink()
    (folder / "truncated.png").write_bytes(png[: len(png) // 2])
    return {
        "truncated.jpg": "truncated",
        "corrupt.jpg": "damaged",
        "notes.jpg": "not an image",
        "empty.png": "empty",
        "modern.webp": "convert",
        "tiny.jpg": "too small",
        "truncated.png": "truncated",
    }


def write_good_variants(folder: Path, views: list[np.ndarray]) -> list[str]:
    """Odd but usable photos (one synthetic view each); returns their COLMAP names."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "sub a").mkdir()
    (folder / "sub b").mkdir()
    # duplicate file names in sub-folders
    Image.fromarray(views[0]).save(folder / "sub a" / "photo.jpg", quality=92)
    Image.fromarray(views[1]).save(folder / "sub b" / "photo.jpg", quality=92)
    # CMYK, unicode, spaces
    Image.fromarray(views[2]).convert("CMYK").save(folder / "Sacré Cœur 1890.jpg", quality=92)
    cv2.imwrite(
        str(folder / "gray16.png"),
        cv2.cvtColor(views[3], cv2.COLOR_RGB2GRAY).astype(np.uint16) * 257,
    )
    Image.fromarray(np.dstack([views[4], np.full(views[4].shape[:2], 180, np.uint8)])).save(
        folder / "alpha.png"
    )
    _exif_rotated(views[5], folder / "exif_rotated.jpg")
    cv2.imwrite(str(folder / "rgb16.tif"), (views[6].astype(np.uint16) * 257)[:, :, ::-1])
    Image.fromarray(views[7]).convert("LA").save(folder / "gray_alpha.png")
    return [
        "Sacré Cœur 1890.jpg",
        "alpha.png",
        "exif_rotated.jpg",
        "gray16.png",
        "gray_alpha.png",
        "rgb16.tif",
        "sub a/photo.jpg",
        "sub b/photo.jpg",
    ]


def test_check_images_gives_a_reason_for_each_unusable_file(tmp_path):
    rgb = _texture()
    expected = write_bad_files(tmp_path, rgb)
    good = {
        "cmyk.jpg": lambda p: Image.fromarray(rgb).convert("CMYK").save(p),
        "gray16.tif": lambda p: cv2.imwrite(
            str(p), cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.uint16) * 257
        ),
        "rgba.tif": lambda p: Image.fromarray(rgb).convert("RGBA").save(p),
        "palette.png": lambda p: Image.fromarray(rgb).convert("P").save(p),
        "bilevel.png": lambda p: Image.fromarray(rgb).convert("1").save(p),
        "float.tif": lambda p: Image.fromarray(
            cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255
        ).save(p),
        "exif6.jpg": lambda p: _exif_rotated(rgb, p),
        "progressive.jpg": lambda p: Image.fromarray(rgb).save(p, progressive=True),
        "photo.bmp": lambda p: Image.fromarray(rgb).save(p),
    }
    for name, make in good.items():
        make(tmp_path / name)
    names = sorted(p.name for p in tmp_path.iterdir())
    ok, skipped = images.check_images(tmp_path, names)
    assert sorted(ok) == sorted(good)
    assert set(skipped) == set(expected)
    for name, word in expected.items():
        assert word in skipped[name], (name, skipped[name])
    # What the checks let through, COLMAP reads; what they skip is damaged (COLMAP would silently
    # use grey fill).
    for name in ok:
        assert pycolmap.Bitmap.read(str(tmp_path / name), True) is not None, name
    # why the check is needed
    assert pycolmap.Bitmap.read(str(tmp_path / "truncated.jpg"), True) is not None


def test_read_image_is_colmaps_frame_and_pixels(tmp_path):
    rgb = _texture(96, 128, seed=3)
    rng = np.random.default_rng(4)
    deep = rng.integers(0, 65536, (96, 128, 3), dtype=np.uint16)
    files = {
        "exif6.jpg": lambda p: _exif_rotated(rgb, p),
        "cmyk.jpg": lambda p: Image.fromarray(rgb).convert("CMYK").save(p, quality=95),
        "gray16.png": lambda p: cv2.imwrite(str(p), deep[:, :, 0]),
        "rgb16.png": lambda p: cv2.imwrite(str(p), deep),
        "rgb16.tif": lambda p: cv2.imwrite(str(p), deep),
        "la.png": lambda p: Image.fromarray(rgb).convert("LA").save(p),
        "rgba.png": lambda p: Image.fromarray(np.dstack([rgb, rgb[:, :, 0]])).save(p),
        "float.tif": lambda p: Image.fromarray(
            cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255
        ).save(p),
        "palette.png": lambda p: Image.fromarray(rgb).convert("P").save(p),
    }
    for name, make in files.items():
        make(tmp_path / name)
        ours = images.read_image(tmp_path / name)
        colmaps = pycolmap.Bitmap.read(str(tmp_path / name), True).to_array()
        assert ours.dtype == np.uint8 and ours.shape == colmaps.shape, name
        assert np.abs(ours.astype(int) - colmaps.astype(int)).max() <= 1, name
    # EXIF orientation is NOT applied: the stored (rotated) grid, like COLMAP's keypoints and camera
    # size.
    assert images.read_image(tmp_path / "exif6.jpg").shape == (128, 96, 3)
    assert images.image_size(tmp_path / "exif6.jpg") == (96, 128)
    thumb, sx, sy = images.read_thumbnail(tmp_path / "exif6.jpg", 64)
    assert thumb.shape == (64, 48, 3) and sx == pytest.approx(0.5) and sy == pytest.approx(0.5)
    with pytest.raises(ValueError, match="Cannot read image"):
        images.read_image(tmp_path / "missing.jpg")


def test_every_reader_reads_exif_rotated_photos_in_colmaps_frame(tmp_path, monkeypatch):
    """A JPEG tagged 'rotate 90°' (orientation 6) is read in its stored frame, where COLMAP's
    keypoints are, by every path that opens photos: archival CLI, historical proxy,
    the matching preset's features (the coarse matcher: tests/test_coarse_matcher.py). OpenCV's
    imread would rotate it."""
    from colmap_guided import archival
    from colmap_guided.paths import REPO_ROOT
    from recon_scripts.evaluation import proxy
    from recon_scripts.matching import verified_pairs as bench

    photos = tmp_path / "data" / "rotated_set" / "images"
    photos.mkdir(parents=True)
    for i in range(2):
        _exif_rotated(_texture(160, 96, seed=i), photos / f"p{i}.jpg")  # stored 160 wide, 96 high
    stored = (160, 96)
    assert images.image_size(photos / "p0.jpg") == stored and cv2.imread(
        str(photos / "p0.jpg")
    ).shape[:2] == (160, 96)

    archival.main([str(photos / "p0.jpg"), "--out", str(tmp_path / "degraded")])
    assert images.image_size(tmp_path / "degraded" / "p0.jpg") == stored

    scene = proxy.build_scene(
        "rotated_set",
        tmp_path / "proxy",
        data_dir=tmp_path / "data",
        n_distractors=0,
        max_size=None,
        crop=0.0,
    )
    manifest = json.loads((scene / "manifest.json").read_text(encoding="utf-8"))
    assert {e["era"] for e in manifest["images"]} == {"historical", "modern"}
    for entry in manifest["images"]:
        assert images.image_size(scene / "images" / entry["name"]) == stored, entry

    monkeypatch.setenv("COLMAP_GUIDED_DATA", str(tmp_path / "data"))
    pair = {"a": photos / "p0.jpg", "b": photos / "p1.jpg"}
    _, sift = bench.read_pair(bench.extract([pair], "sift", tmp_path / "bench_cache"), pair)
    assert (sift.width, sift.height) == stored and len(sift.keypoints) > 20
    assert sift.keypoints[:, 0].max() > 100  # x along the stored 160 px side
    # Training views and anything else: no second decoder of photo files in the package or the
    # scripts.
    sources = [
        *(REPO_ROOT / "colmap_guided").rglob("*.py"),
        *(REPO_ROOT / "recon_scripts").rglob("*.py"),
    ]
    assert [p.name for p in sources if "cv2.imread(" in p.read_text(encoding="utf-8")] == []


def _huge_png(path: Path, side: int = 10240) -> None:
    """A ~105 MP grey PNG written row by row (a flat page with a textured square): cheap to make."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + tag
            + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        )

    patch = np.kron(
        np.random.default_rng(0).integers(0, 256, (128, 128), dtype=np.uint8),
        np.ones((8, 8), np.uint8),
    )
    comp = zlib.compressobj(1)
    flat = b"\x00" + bytes([128]) * side
    parts = []
    for y in range(side):
        if 4000 <= y < 5024:
            row = np.full(side, 128, np.uint8)
            row[4000:5024] = patch[y - 4000]
            parts.append(comp.compress(b"\x00" + row.tobytes()))
        else:
            parts.append(comp.compress(flat))
    parts.append(comp.flush())
    with open(path, "wb") as f:
        f.write(
            b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0))
        )
        f.write(chunk(b"IDAT", b"".join(parts)) + chunk(b"IEND", b""))


def test_huge_image_is_checked_without_decoding_it(tmp_path):
    """A 105 MP scan: the up-front check reads headers and CRCs only (a full decode would take
    105+ MB)."""
    _huge_png(tmp_path / "huge.png")
    code = textwrap.dedent(
        f"""
        import resource
        from colmap_guided import images
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        ok, skipped = images.check_images({str(tmp_path)!r}, ["huge.png"])
        grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
        print(ok, skipped, grown)
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    grown = int(out.stdout.split()[-1])
    assert "['huge.png'] {}" in out.stdout
    # ru_maxrss is in kB on Linux
    assert grown < 40_000, f"the check grew the process by {grown} kB"
    assert "100 MP or more" in out.stderr


@pytest.mark.slow
def test_huge_image_extracts_with_keypoints_in_full_size_pixels(tmp_path):
    """COLMAP downscales the 105 MP scan for SIFT (max_image_size) and maps keypoints back to full
    size."""
    from colmap_guided.features import extract_features

    folder = tmp_path / "images"
    folder.mkdir()
    _huge_png(folder / "huge.png")
    db_path = tmp_path / "database.db"
    out = extract_features(db_path, folder, ["huge.png"], {"max_image_size": 1600})
    assert out["skipped"] == {}
    with pycolmap.Database.open(str(db_path)) as db:
        image = db.read_all_images()[0]
        camera = db.read_camera(image.camera_id)
        xy = db.read_keypoints(image.image_id)[:, :2]
    assert (camera.width, camera.height) == (10240, 10240)
    assert len(xy) > 50
    # The texture is in [4000, 5024]^2 of the full-size image.
    assert xy.min() > 3900 and xy.max() < 5130


@pytest.mark.parametrize("matcher", ["raw", "guided"])
def test_bad_and_odd_photos_end_to_end(tmp_path, capfd, matcher):
    """Skipped ones listed with reasons; every odd-but-valid photo registered; the photos never
    written. Called as a library with COLMAP's log at its own default (everything), the run is still
    quiet. The guided matcher sees the same pixels as COLMAP (a 16-bit grey scan is not white to its
    coarse network)."""
    scene = render_scene(tmp_path / "render", num_images=8, width=400, height=300)
    views = [cv2.imread(str(scene.image_dir / n))[:, :, ::-1] for n in scene.names]
    # unicode and spaces in the path
    folder = tmp_path / "Archives Saint-Jacques — fonds 1890" / "images"
    good = write_good_variants(folder, views)
    bad = write_bad_files(folder, views[0])
    before = images.folder_digests(folder)

    out = tmp_path / "sortie résultats"
    saved_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0  # a fresh Python session's setting
    try:
        result = reconstruct(folder.parent, output=out, matcher=matcher)
    finally:
        pycolmap.logging.minloglevel = saved_level
    assert not GLOG_LINE.search(capfd.readouterr().err), "COLMAP's own log must be quiet by default"

    assert images.folder_digests(folder) == before, "the photo folder was written to"
    assert set(result["skipped_images"]) == set(bad)
    for name, word in bad.items():
        assert word in result["skipped_images"][name]
    # Guided too: the coarse network is not rotation invariant (exif_rotated.jpg's stored grid is
    # turned 90° from the other views), but the guided matcher keeps raw matches where they verify
    # more.
    assert sorted(result["model"]["registered_images"]) == sorted(good), result["model"]
    saved = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert saved["skipped_images"] == result["skipped_images"]
    text = summary_text(result)
    for name in bad:
        assert name in text
    with pycolmap.Database.open(str(out / "database.db")) as db:
        cameras = {im.name: db.read_camera(im.camera_id) for im in db.read_all_images()}
    # stored frame
    assert (cameras["exif_rotated.jpg"].width, cameras["exif_rotated.jpg"].height) == (300, 400)
    assert "Sacré Cœur 1890.jpg" in (out / "report.html").read_text(encoding="utf-8")


def _cli(argv: list[str], capfd) -> tuple[int, str, str]:
    """main() in this process; our logger writes to the stderr of the moment, which capfd
    captures."""
    try:
        code = main([str(a) for a in argv])
    finally:
        set_verbosity(False, False)
    out, err = capfd.readouterr()
    return code, out, err


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err
    lines = OUR_ERROR.findall(err)
    assert len(lines) == 1, err
    return lines[0]


def test_cli_errors_are_one_actionable_line(tmp_path, capfd):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _cli(
        ["reconstruct", empty, "--output", tmp_path / "o1", "--matcher", "raw"], capfd
    )
    assert code == 2 and "No images" in _one_error_line(err)

    code, _, err = _cli(
        ["reconstruct", tmp_path / "nowhere", "--output", tmp_path / "o2", "--matcher", "raw"],
        capfd,
    )
    assert code == 2 and "does not exist" in _one_error_line(err)

    allbad = tmp_path / "allbad"
    write_bad_files(allbad, _texture())
    code, _, err = _cli(
        ["reconstruct", allbad, "--output", tmp_path / "o3", "--matcher", "raw"], capfd
    )
    assert code == 2 and "None of the 7 image(s)" in _one_error_line(err)

    for weights, word in (
        (tmp_path / "missing.safetensors", "no such file"),
        (tmp_path / "broken.safetensors", "not a readable safetensors"),
    ):
        if "broken" in weights.name:
            weights.write_bytes(b"\x00\x01garbage" * 100)
        code, _, err = _cli(
            [
                "reconstruct",
                allbad,
                "--output",
                tmp_path / "o4",
                "--matcher",
                "guided",
                "--weights",
                weights,
            ],
            capfd,
        )
        assert code == 2 and word in _one_error_line(err)
        assert not (tmp_path / "o4").exists(), "a bad --weights must fail before any work"
    # A readable safetensors file that is not coarse-filter weights: refused by the guided matcher,
    # before extraction.
    from safetensors.numpy import save_file

    save_file({"w": np.zeros((2, 2), np.float32)}, str(tmp_path / "other.safetensors"))
    code, _, err = _cli(
        [
            "reconstruct",
            allbad,
            "--output",
            tmp_path / "o5",
            "--matcher",
            "guided",
            "--weights",
            tmp_path / "other.safetensors",
        ],
        capfd,
    )
    assert code == 2 and "other.safetensors" in _one_error_line(err)
    assert not (tmp_path / "o5" / "database.db").exists()


def test_single_image_one_line_and_verbose_shows_colmap_log(tmp_path, capfd):
    folder = tmp_path / "one"
    folder.mkdir()
    Image.fromarray(_texture(240, 320)).save(folder / "only.jpg")
    code, _, err = _cli(
        ["reconstruct", folder, "--output", tmp_path / "out", "--matcher", "raw", "--verbose"],
        capfd,
    )
    assert code == 2 and "Only 1 usable image" in _one_error_line(err)
    assert GLOG_LINE.search(err), "--verbose must show COLMAP's own log"
    # extracts again
    code, _, err = _cli(
        ["reconstruct", folder, "--output", tmp_path / "out2", "--matcher", "raw"], capfd
    )
    assert code == 2 and "Only 1 usable image" in _one_error_line(err)
    assert not GLOG_LINE.search(err), "COLMAP's log must be quiet by default"


def test_no_model_is_said_plainly_with_what_to_try(tmp_path, capfd):
    """Photos that share nothing: no pair verifies, mapping starts no model, and the summary says so
    instead of pointing at a sparse/0 that does not exist."""
    folder = tmp_path / "unrelated"
    folder.mkdir()
    for seed in range(3):
        Image.fromarray(_texture(240, 320, seed=seed)).save(folder / f"photo_{seed}.png")
    code, out, _ = _cli(
        ["reconstruct", folder, "--output", tmp_path / "out", "--matcher", "raw"], capfd
    )
    assert code == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text(encoding="utf-8"))
    assert report["model"]["num_models"] == 0 and report["num_registered"] == 0
    assert report["no_model"]["linked"] == [] and "nothing links them" in report["no_model"]["why"]
    assert not (tmp_path / "out" / "sparse" / "0").exists()
    assert "No model was made" in out and "--camera_mode single" in out
    assert "sparse/0" not in out


def test_a_matcher_that_cannot_match_the_features_fails_before_any_work(synthetic_scene, tmp_path):
    """LightGlue matches ALIKED only (``feature_types``): with SIFT, reconstruct refuses before
    extracting anything, and match_database on a SIFT database before writing any match; the line
    says what to run."""
    from colmap_guided import database as dbio
    from colmap_guided.features import extract_features
    from colmap_guided.match import match_database
    from colmap_guided.matchers.lightglue import LightGlueMatcher
    from colmap_guided.matchers.raw import RawMatcher

    class AlikedOnly(RawMatcher):
        name = "aliked_only"
        feature_types = LightGlueMatcher.feature_types

    assert LightGlueMatcher.feature_types == ("aliked",)
    line = "needs aliked features, not sift: run reconstruct with --features aliked"
    with pytest.raises(ValueError, match=line):
        reconstruct(
            synthetic_scene.image_dir.parent,
            image_path=synthetic_scene.image_dir,
            output=tmp_path / "ws",
            matcher=AlikedOnly(),
            feature_conf={"type": "sift"},
        )
    assert not (tmp_path / "ws").exists()
    db = tmp_path / "sift" / "database.db"
    db.parent.mkdir()
    extract_features(db, synthetic_scene.image_dir, synthetic_scene.names[:2])
    with pytest.raises(ValueError, match=line):
        match_database(db, synthetic_scene.image_dir, "exhaustive", AlikedOnly())
    with dbio.open_database(db) as opened:
        assert dbio.pair_match_counts(opened) == {}


def test_an_option_the_matcher_does_not_take_names_a_matcher_that_does(tmp_path):
    """A ValueError in the library; the command line exits with it as a usage error (status 1)."""
    from colmap_guided.__main__ import build_parser
    from colmap_guided.cli import matcher_conf_from_args

    line = "--weights does not apply to the raw matcher; pass --matcher guided "
    args = build_parser().parse_args(["match", "--database_path", "d", "--image_path", "i"])
    args.weights = tmp_path / "w.safetensors"
    with pytest.raises(ValueError, match=line):
        matcher_conf_from_args(args, "raw")
    with pytest.raises(SystemExit, match=f"^error: {line}") as err:
        main(
            [
                "reconstruct",
                str(tmp_path / "scene"),
                "--output",
                str(tmp_path / "out"),
                "--matcher",
                "raw",
                "--weights",
                str(tmp_path / "w.safetensors"),
            ]
        )
    assert isinstance(err.value.code, str)  # Python prints it and exits with status 1
    assert not (tmp_path / "out").exists()
