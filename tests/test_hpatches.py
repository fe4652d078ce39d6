import cv2
import numpy as np
import pytest

from ruslam.data.hpatches import HPatches, rotation_from_homography
from ruslam.eval.matching import warp_points


def blob_image(hw, centre, sigma=3.0):
    ys, xs = np.mgrid[0 : hw[0], 0 : hw[1]].astype(np.float64)
    g = np.exp(-((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / (2 * sigma**2))
    return np.dstack([np.round(g * 255).astype(np.uint8)] * 3)


def centroid(img):
    g = img[..., 0].astype(np.float64)
    g = np.where(g > 0.05 * g.max(), g, 0)
    ys, xs = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
    return np.array([(xs * g).sum() / g.sum(), (ys * g).sum() / g.sum()])


def write_sequence(folder, images, homographies, rotations=None):
    folder.mkdir(parents=True)
    for k, img in enumerate(images, start=1):
        cv2.imwrite(str(folder / f"{k}.ppm"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    for k, H in enumerate(homographies, start=2):
        np.savetxt(folder / f"H_1_{k}", H)
    if rotations is not None:
        np.savetxt(folder / "rotation_deg.txt", rotations)


def test_resize_updates_homography_exactly(tmp_path):
    # image 1 is 480x640 (halved by the reader), image 2 is 120x160 (doubled): a pixel-centre error would show
    # as a 0.25-0.5 px offset of the blob.
    p1 = np.array([300.3, 210.7])
    c, s = 0.25 * np.cos(0.3), 0.25 * np.sin(0.3)
    A = np.array([[c, -s, 40], [s, c, 5], [0, 0, 1]])
    img1 = blob_image((480, 640), p1, sigma=6.0)
    img2 = blob_image((120, 160), warp_points(p1[None], A)[0], sigma=1.5)
    write_sequence(tmp_path / "v_blob", [img1, img2], [A])
    pair = HPatches(tmp_path, size=(240, 320))[0]
    assert pair["image1"].shape == pair["image2"].shape == (240, 320, 3)
    c1, c2 = centroid(pair["image1"]), centroid(pair["image2"])
    assert np.allclose(c1, (p1 + 0.5) * 0.5 - 0.5, atol=0.05)
    assert np.allclose(warp_points(c1[None], pair["H"])[0], c2, atol=0.1)
    assert pair["rotation_deg"] == pytest.approx(np.degrees(0.3), abs=1e-6)  # measured from H


def test_layout_pairs_kinds_and_recorded_rotation(tmp_path):
    img = (np.random.default_rng(0).random((40, 50, 3)) * 255).astype(np.uint8)
    rot90 = np.array([[0, -1, 49], [1, 0, 0], [0, 0, 1]], float)
    write_sequence(tmp_path / "i_a", [img] * 3, [np.eye(3)] * 2)
    write_sequence(tmp_path / "v_b", [img] * 2, [rot90], rotations=[123.0])
    (tmp_path / "notes").mkdir()
    ds = HPatches(tmp_path, size=None)
    assert len(ds) == 3 and [ds[i]["name"] for i in range(3)] == ["i_a/1-2", "i_a/1-3", "v_b/1-2"]
    assert ds[2]["rotation_deg"] == 123.0 and np.array_equal(ds[0]["image2"], img)
    assert len(HPatches(tmp_path, size=None, kinds=["v"])) == 1
    assert rotation_from_homography(rot90, (40, 50)) == pytest.approx(90.0)


def test_bad_inputs_one_sentence_each(tmp_path):
    img = np.zeros((20, 20, 3), np.uint8)
    write_sequence(tmp_path / "v_shape", [img, img], [np.eye(3)])
    np.savetxt(tmp_path / "v_shape" / "H_1_2", np.eye(3)[:2])
    with pytest.raises(ValueError, match=r"H_1_2 must hold an invertible 3x3 matrix, got shape \(2, 3\)"):
        HPatches(tmp_path)
    (tmp_path / "v_shape" / "H_1_2").write_text("1 0 0\n0 one 0\n0 0 1\n")
    with pytest.raises(ValueError, match="Cannot read homography file .*H_1_2"):
        HPatches(tmp_path)
    np.savetxt(tmp_path / "v_shape" / "H_1_2", np.eye(3))
    (tmp_path / "v_shape" / "2.ppm").write_bytes(b"P6 garbage, not an image")
    ds = HPatches(tmp_path)
    with pytest.raises(ValueError, match=r"Cannot read image .*2\.ppm"):
        ds[0]
    (tmp_path / "v_shape" / "H_1_2").unlink()
    with pytest.raises(FileNotFoundError, match="has 2.ppm but no homography file H_1_2"):
        HPatches(tmp_path)
    with pytest.raises(ValueError, match="holds no sequence folder"):
        HPatches(tmp_path / "v_shape")
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        HPatches(tmp_path / "nowhere")
