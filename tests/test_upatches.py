import cv2
import numpy as np
import pytest

from ruslam.data.hpatches import HPatches, rotation_from_homography, zoom_from_homography
from ruslam.data.upatches import build_upatches, sample_homography, upatches_from_folder
from ruslam.eval.matching import inside_image, warp_points

HW = (60, 80)


def write_images(folder, n, hw=(50, 70)):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    for i in range(n):
        cv2.imwrite(str(folder / f"{i + 1}.png"), (rng.random((*hw, 3)) * 255).astype(np.uint8))
    return folder


@pytest.mark.parametrize("max_rot", [180.0, 20.0])
def test_fit_inside_views_stay_inside_and_rotation_is_recorded(max_rot):
    rng = np.random.default_rng(0)
    angles = []
    for _ in range(200):
        H, angle = sample_homography(rng, HW, max_rotation_deg=max_rot, perspective=0.1, fit_inside=True)
        # every corner of image 2 sees a point of image 1
        corners = np.array([[-0.5, -0.5], [79.5, -0.5], [79.5, 59.5], [-0.5, 59.5]])
        back = warp_points(corners, np.linalg.inv(H))
        assert np.all(back >= -0.5 - 1e-6) and np.all(back[:, 0] <= 79.5 + 1e-6) and np.all(back[:, 1] <= 59.5 + 1e-6)
        angles.append(angle)
    angles = np.abs(angles)
    assert angles.max() <= max_rot and angles.max() > 0.8 * max_rot  # the whole range is used
    for _ in range(20):  # without perspective jitter the content rotation measured from H is the recorded one
        H, angle = sample_homography(rng, HW, max_rotation_deg=max_rot, perspective=0.0, fit_inside=True)
        assert rotation_from_homography(H, HW) == pytest.approx(angle, abs=1e-4)


def test_fit_inside_forces_a_zoom_in_and_the_default_draws_zoom_around_one():
    rng = np.random.default_rng(0)
    hw = (480, 640)
    inside = [zoom_from_homography(sample_homography(rng, hw, fit_inside=True)[0], hw) for _ in range(300)]
    free = [zoom_from_homography(sample_homography(rng, hw, perspective=0.0)[0], hw) for _ in range(300)]
    assert min(inside) > 1.0 and np.median(inside) > 1.5  # the first builder: always a zoom-in
    assert 0.8 - 1e-9 <= min(free) and max(free) <= 1.25 + 1e-9  # log-uniform in zoom_range
    assert np.median(free) == pytest.approx(1.0, abs=0.05)
    assert np.mean(np.log(free)) == pytest.approx(0.0, abs=0.03)  # symmetric in log: as many zoom-ins as outs
    # with perspective jitter, the zoom at the centre stays near the drawn range
    jittered = [zoom_from_homography(sample_homography(rng, hw)[0], hw) for _ in range(300)]
    assert 0.6 < min(jittered) and max(jittered) < 1.6 and abs(np.median(jittered) - 1) < 0.1


def test_zoom_from_homography_of_a_known_similarity():
    s, t = 1.5, np.radians(30)
    H = np.array([[s * np.cos(t), -s * np.sin(t), 7], [s * np.sin(t), s * np.cos(t), -3], [0, 0, 1]])
    assert zoom_from_homography(H, (60, 80)) == pytest.approx(1.5)
    assert zoom_from_homography(np.linalg.inv(H), (60, 80)) == pytest.approx(1 / 1.5)


def test_default_views_have_borders_that_the_shared_view_filter_drops():
    rng = np.random.default_rng(3)
    corners = np.array([[-0.5, -0.5], [79.5, -0.5], [79.5, 59.5], [-0.5, 59.5]])
    outside, overlap = 0, []
    ys, xs = np.mgrid[0:60, 0:80]
    grid = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    for _ in range(100):
        H, _ = sample_homography(rng, HW)
        outside += not inside_image(warp_points(corners, np.linalg.inv(H)), HW).all()
        overlap.append(inside_image(warp_points(grid, np.linalg.inv(H)), HW).mean())
    assert outside > 50  # most views see beyond image 1 (borders allowed)
    assert min(overlap) > 0.4 and np.median(overlap) > 0.6  # yet every pair shares a large view


def test_border_pixels_come_from_outside_image_one(tmp_path):
    # image 1 bright everywhere: a keypoint-free check that the invalid part of image 2 is exactly what maps
    # outside image 1 (the part the shared-view filter removes), and nothing is black-filled
    img = np.full((60, 80, 3), 200, np.uint8)
    img[:, :40] = 90
    ds = HPatches(build_upatches([("a", img)], tmp_path / "u", {"source": "test"}, num_warps=5, size=HW), size=None)
    ys, xs = np.mgrid[0:60, 0:80]
    grid = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    seen_border = False
    for i in range(len(ds)):
        pair = ds[i]
        valid = inside_image(warp_points(grid, np.linalg.inv(pair["H"])), HW).reshape(HW)
        seen_border |= not valid.all()
        assert pair["image2"].min() >= 90 - 1  # replicated edges, no black fill
    assert seen_border


def test_old_mode_stays_available_and_is_recorded(tmp_path):
    img = (np.random.default_rng(0).random((60, 80, 3)) * 255).astype(np.uint8)
    old = build_upatches([("a", img)], tmp_path / "old", {"source": "t"}, num_warps=4, size=HW, fit_inside=True)
    ds = HPatches(old, size=None)
    corners = np.array([[-0.5, -0.5], [79.5, -0.5], [79.5, 59.5], [-0.5, 59.5]])
    for i in range(len(ds)):
        back = warp_points(corners, np.linalg.inv(ds[i]["H"]))
        assert inside_image(back - np.sign(back - [40, 30]) * 1e-6, HW).all()
        assert ds[i]["zoom"] > 1.0
    import json
    manifest = json.loads((old / "upatches.json").read_text())
    assert manifest["fit_inside"] is True and "scale_range" in manifest and "zoom_range" not in manifest
    with pytest.raises(ValueError, match="zoom_range must satisfy"):
        build_upatches([("a", img)], tmp_path / "bad", {"source": "t"}, size=HW, zoom_range=(1.2, 0.8))


def test_warped_content_follows_the_homography(tmp_path):
    # a blob at p in image 1 must appear at H p in every warped image (checks direction and pixel centres)
    ys, xs = np.mgrid[0:120, 0:160].astype(float)
    p = np.array([83.0, 57.0])
    blob = np.exp(-((xs - p[0]) ** 2 + (ys - p[1]) ** 2) / (2 * 2.5**2))
    img = np.dstack([np.round(blob * 255).astype(np.uint8)] * 3)
    ds = HPatches(build_upatches([("blob", img)], tmp_path / "u", {"source": "test"}, num_warps=4, size=(120, 160),
                                 max_rotation_deg=180, scale_range=(0.9, 1.0), perspective=0.05), size=None)
    for i in range(len(ds)):
        pair = ds[i]
        q = warp_points(p[None], pair["H"])[0]
        if not inside_image(q[None], (110, 150))[0] or not inside_image(q[None] - 10, (100, 140))[0]:
            continue  # blob near or beyond the border of the view
        g = pair["image2"][..., 0].astype(float)
        g = np.where(g > 0.1 * g.max(), g, 0)
        c = np.array([(xs * g).sum() / g.sum(), (ys * g).sum() / g.sum()])
        assert np.allclose(c, q, atol=0.35), (pair["name"], c, q)


def test_folder_build_layout_seed_and_reuse(tmp_path):
    src = write_images(tmp_path / "src", 3)
    ds = upatches_from_folder(src, tmp_path / "u", num_images=2, eval_size=HW, num_warps=3, size=HW, seed=5)
    assert sorted(p.name for p in (tmp_path / "u").iterdir()) == ["upatches.json", "v_1", "v_2"]
    names = sorted(p.name for p in (tmp_path / "u" / "v_1").iterdir())
    assert names == ["1.ppm", "2.ppm", "3.ppm", "4.ppm", "H_1_2", "H_1_3", "H_1_4", "rotation_deg.txt"]
    assert len(ds) == 6 and ds[0]["image1"].shape == (*HW, 3)
    # reference image is the source resized; same seed reproduces, another seed differs
    again = upatches_from_folder(src, tmp_path / "u2", num_images=2, eval_size=HW, num_warps=3, size=HW, seed=5)
    other = upatches_from_folder(src, tmp_path / "u3", num_images=2, eval_size=HW, num_warps=3, size=HW, seed=6)
    assert np.array_equal(again[4]["image2"], ds[4]["image2"]) and np.array_equal(again[4]["H"], ds[4]["H"])
    assert not np.allclose(other[4]["H"], ds[4]["H"])
    # a finished identical build is reused; a different one is refused
    stamp = (tmp_path / "u" / "v_1" / "2.ppm").stat().st_mtime_ns
    upatches_from_folder(src, tmp_path / "u", num_images=2, eval_size=HW, num_warps=3, size=HW, seed=5)
    assert (tmp_path / "u" / "v_1" / "2.ppm").stat().st_mtime_ns == stamp
    with pytest.raises(FileExistsError, match="already exists and was not built with these parameters"):
        upatches_from_folder(src, tmp_path / "u", num_images=2, eval_size=HW, num_warps=3, size=HW, seed=7)


def test_bad_folders_one_sentence_each(tmp_path):
    src = write_images(tmp_path / "src", 3)
    with pytest.raises(ValueError, match=r"holds 3 image\(s\) .* fewer than the 5 asked"):
        upatches_from_folder(src, tmp_path / "u", num_images=5)
    (src / "2.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match=r"Cannot read image .*2\.png"):
        upatches_from_folder(src, tmp_path / "u", num_images=3, size=HW)
    assert not (tmp_path / "u").exists() and list(tmp_path.iterdir()) == [src]  # nothing half-written
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        upatches_from_folder(tmp_path / "missing", tmp_path / "u", num_images=1)


def test_real_underwater_folder(shared_data, tmp_path):
    folder = shared_data / "underwater_euvp"
    with pytest.raises(ValueError, match="holds 23 image"):
        upatches_from_folder(folder, tmp_path / "u", num_images=24)
    ds = upatches_from_folder(folder, tmp_path / "u", num_images=2, num_warps=1, size=(120, 160), eval_size=(120, 160))
    assert [ds[i]["name"] for i in range(2)] == ["v_1/1-2", "v_2/1-2"]
