"""Very large scans: the extraction paths' peak memory stays a few bytes per pixel of the scan."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 12000, 9000  # 108 MP
# Growth of the peak RSS per pixel of the scan; the pixels decoded in full cost ~11 bytes in float
# and Pillow copies (18 with SIFT's grey pre-pass), COLMAP's own reader ~4.
MAX_BYTES_PER_PIXEL = 8

# Each stage in one process: the peak RSS is reset (Linux clear_refs) before it, measured after it.
STAGES = r"""
import json, sys
from pathlib import Path

def status():
    fields = dict(line.split(":", 1) for line in open("/proc/self/status"))
    return {key: int(fields[key].split()[0]) * 1024 for key in ("VmRSS", "VmHWM")}

def measure(run):
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")
    before = status()["VmRSS"]
    result = run()
    return {"growth": status()["VmHWM"] - before, **result}

from colmap_guided import database as dbio, features
from colmap_guided.features import aliked as lf
from colmap_guided.coarse import CoarseMatcher

scan, work = Path(sys.argv[1]), Path(sys.argv[2])
out = {}

def sift():
    database = work / "database.db"
    conf = {"max_image_size": 1000, "num_threads": 1}
    stats = features.extract_features(database, scan.parent, [scan.name], conf)
    with dbio.open_database(database) as db:
        keypoints = dbio.read_keypoints(db, dbio.read_image(db, scan.name).image_id)
    return {"prepared": stats["prepared"], "max_xy": keypoints[:, :2].max(0).tolist(),
            "num": len(keypoints)}

out["sift"] = measure(sift)
try:
    conf = lf.check_conf({"max_image_size": 512, "device": "cpu"})
    model, device = lf.load_model(conf)
except FileNotFoundError:
    pass
else:
    def aliked():
        keypoints, _ = lf.extract_image(model, device, scan, conf)
        return {"max_xy": keypoints[:, :2].max(0).tolist(), "num": len(keypoints)}

    out["aliked"] = measure(aliked)
coarse = CoarseMatcher({"mode": "raw", "device": "cpu"})
out["coarse"] = measure(lambda: {"size": [coarse.extract_path(scan).geometry.width]})
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def faded_scan(tmp_path_factory) -> Path:
    """A 108 MP JPEG of a faded print: random texture (SIFT and ALIKED find keypoints at any
    scale down to 1/12) in 64 grey levels, so SIFT runs on the stretched grey copy."""
    small = np.random.default_rng(0).integers(0, 256, (HEIGHT // 12, WIDTH // 12, 3), np.uint8)
    scan = cv2.resize(small, (WIDTH, HEIGHT), interpolation=cv2.INTER_LINEAR) // 4 + 96
    path = tmp_path_factory.mktemp("scan") / "scan.jpg"
    cv2.imwrite(str(path), scan, [cv2.IMWRITE_JPEG_QUALITY, 85])
    return path


def test_a_large_scan_is_extracted_in_a_few_bytes_per_pixel(faded_scan, tmp_path):
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux's /proc/self/clear_refs to measure each stage's peak RSS")
    run = subprocess.run(
        [sys.executable, "-c", STAGES, str(faded_scan), str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    stages = json.loads(run.stdout.splitlines()[-1])
    pixels = WIDTH * HEIGHT
    for name, stage in stages.items():
        assert stage["growth"] < MAX_BYTES_PER_PIXEL * pixels, (name, stage["growth"] / pixels)
    sift = stages["sift"]
    assert sift["prepared"] == ["scan.jpg"] and sift["num"] > 1000
    # keypoints in the scan's full-size pixel frame
    for stage in (sift, stages.get("aliked", sift)):
        assert (
            0.95 * WIDTH < stage["max_xy"][0] < WIDTH
            and 0.95 * HEIGHT < stage["max_xy"][1] < HEIGHT
        )
    assert stages["coarse"]["size"] == [WIDTH]
