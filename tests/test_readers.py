"""Sequence readers on tiny generated folders in every layout, bad input, and the real ground-truth files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ruslam.data.readers import (
    FrameReadError,
    read_aqualoc,
    read_euroc,
    read_euroc_groundtruth,
    read_image_folder,
    read_tum,
    read_tum_trajectory,
)

# EuRoC VI-sensor extrinsics (cam -> body), as in mav0/cam*/sensor.yaml.
T_BS0 = np.array([0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
                  0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
                  -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949, 0, 0, 0, 1]).reshape(4, 4)
T_BS1 = np.array([0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
                  0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
                  -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038, 0, 0, 0, 1]).reshape(4, 4)
STAMPS = [1403715273262142976, 1403715273312143104, 1403715273362142976]


def _image(seed, shape=(48, 64)):
    return np.random.default_rng(seed).integers(0, 255, shape, dtype=np.uint8)


def _sensor_yaml(T):
    data = ", ".join(repr(float(x)) for x in T.ravel())
    return ("sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [" + data + "]\nrate_hz: 20\n"
            "resolution: [64, 48]\ncamera_model: pinhole\nintrinsics: [45.8, 45.7, 31.5, 23.5]\n"
            "distortion_model: radial-tangential\ndistortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]\n")


def _body_poses():
    rot = Rotation.from_euler("xyz", [[0.1, 0.2, 0.3], [0.15, 0.2, 0.35], [0.2, 0.25, 0.4]]).as_matrix()
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, :3] = rot
    poses[:, :3, 3] = [[1, 2, 3], [1.1, 2, 3], [1.2, 2.1, 3]]
    return poses


def make_euroc(root):
    for c, T in enumerate([T_BS0, T_BS1]):
        d = root / "mav0" / f"cam{c}"
        (d / "data").mkdir(parents=True)
        (d / "sensor.yaml").write_text(_sensor_yaml(T))
        (d / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.png\n" for t in STAMPS))
        for i, t in enumerate(STAMPS):
            cv2.imwrite(str(d / "data" / f"{t}.png"), _image(10 * c + i))
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir(parents=True)
    q = Rotation.from_matrix(_body_poses()[:, :3, :3]).as_quat()
    rows = [f"{t},{p[0]},{p[1]},{p[2]},{w},{x},{y},{z}" + ",0" * 9
            for t, p, (x, y, z, w) in zip(STAMPS, _body_poses()[:, :3, 3], q, strict=True)]
    (gt / "data.csv").write_text("#timestamp, p_RS_R_x [m], ...\n" + "\n".join(rows) + "\n")
    return root


def test_euroc_stereo(tmp_path):
    seq = read_euroc(make_euroc(tmp_path / "MH_01_easy"))
    assert seq.name == "MH_01_easy" and len(seq) == 3 and seq.stereo
    assert np.allclose(seq.timestamps, np.array(STAMPS) * 1e-9)
    assert np.allclose(seq.T_cam0_cam1, np.linalg.inv(T_BS0) @ T_BS1)
    assert np.linalg.norm(seq.T_cam0_cam1[:3, 3]) == pytest.approx(0.110, abs=0.001)  # EuRoC baseline
    assert np.allclose(seq.groundtruth.poses, _body_poses() @ T_BS0)  # T_world_cam0 = T_world_body T_BS
    assert seq.cameras[0].fx == 45.8 and seq.cameras[0].model == "pinhole" and seq.cameras[0].dist[0] == -0.28
    left, right = seq.load(1)
    assert left.dtype == np.uint8 and np.array_equal(left, _image(1)) and np.array_equal(right, _image(11))
    mono = read_euroc(tmp_path / "MH_01_easy" / "mav0", stereo=False)
    assert len(mono.cameras) == 1 and mono.T_cam0_cam1 is None and len(mono.load(0)) == 1


def test_euroc_bad_input(tmp_path):
    root = make_euroc(tmp_path / "seq")
    (root / "mav0" / "cam1" / "sensor.yaml").unlink()
    with pytest.raises(FileNotFoundError, match="cam1/sensor.yaml"):
        read_euroc(root)
    seq = read_euroc(root, stereo=False)
    (root / "mav0" / "cam0" / "data" / f"{STAMPS[2]}.png").write_bytes(b"not a png")
    with pytest.raises(FrameReadError, match=f"{STAMPS[2]}.png"):
        seq.load(2)
    (root / "mav0" / "cam0" / "data.csv").write_text("#timestamp [ns],filename\n")
    with pytest.raises(ValueError, match="lists no images"):
        read_euroc(root, stereo=False)
    with pytest.raises(FileNotFoundError, match="not a EuRoC sequence"):
        read_euroc(tmp_path / "empty")


def _write_aqualoc(folder, csv_name, image_dir, n=6):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / image_dir).mkdir(parents=True)
    stamps = [1529000000000000000 + 50_000_000 * i for i in range(n)]
    rows = "".join(f"{t},frame{i:06d}.png\n" for i, t in enumerate(stamps))
    (folder / csv_name).write_text("#timestamp [ns],img_name\n" + rows)
    for i in range(min(n, 6)):  # the reader checks only the first file; keep the long lists cheap
        cv2.imwrite(str(folder / image_dir / f"frame{i:06d}.png"), _image(i))
    return np.array(stamps) * 1e-9


def test_aqualoc_harbor_ground_truth_indexed_by_image(tmp_path):
    root = tmp_path / "harbor_01"
    stamps = _write_aqualoc(root, "harbor_img_sequence_01.csv", "raw_data/harbor_images_sequence_01")
    (root / "new_harbor_colmap_traj_sequence_01.txt").write_text(
        "0 1 2 3 0 0 0 1\n2 1.5 2 3 0 0 0.7071068 0.7071068\n5 2 2 3 0 0 0 1\n")
    (root / "harbor_colmap_traj_sequence_01.txt").write_text("0 9 9 9 0 0 0 1\n")  # the old scale: not preferred
    seq = read_aqualoc(root, site="harbor")
    assert seq.cameras[0].model == "fisheye" and seq.cameras[0].fx == 256.214
    assert np.allclose(seq.groundtruth.timestamps, stamps[[0, 2, 5]])
    assert np.allclose(seq.groundtruth.positions[:, 0], [1, 1.5, 2])
    assert np.allclose(seq.groundtruth.poses[1, :3, :3], Rotation.from_euler("z", 90, degrees=True).as_matrix())
    assert np.array_equal(seq.load(3)[0], _image(3))


def test_aqualoc_archaeo_layout_and_errors(tmp_path):
    root = tmp_path / "archaeo_03"
    _write_aqualoc(root, "raw_data/img_sequence_3.csv", "raw_data/images_sequence_3")
    seq = read_aqualoc(root, site="archaeo")
    assert seq.cameras[0].model == "pinhole" and seq.cameras[0].width == 968 and seq.groundtruth is None
    gt = tmp_path / "gt.txt"
    gt.write_text("0 1 2 3 0 0 0 1\n40 1 2 3 0 0 0 1\n")
    with pytest.raises(ValueError, match="indexes image 40"):
        read_aqualoc(root, site="archaeo", groundtruth=gt)
    with pytest.raises(FileNotFoundError, match="image list"):
        read_aqualoc(tmp_path / "archaeo_03" / "raw_data" / "images_sequence_3", site="archaeo")
    with pytest.raises(ValueError, match="site"):
        read_aqualoc(root, site="reef")


def test_tum(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    (root / "rgb").mkdir(parents=True)
    lines = []
    for i in range(3):
        cv2.imwrite(str(root / "rgb" / f"{i}.png"), np.dstack([_image(i)] * 2 + [np.zeros((48, 64), np.uint8)]))
        lines.append(f"{1305031102.175304 + i * 0.03:.6f} rgb/{i}.png")
    (root / "rgb.txt").write_text("# color images\n# file\n# timestamp filename\n" + "\n".join(lines) + "\n")
    (root / "groundtruth.txt").write_text("# ground truth\n1305031102.1 1 2 3 0 0 0 1\n1305031102.2 1 2 4 0 0 0 1\n")
    seq = read_tum(root)
    assert seq.cameras[0].fx == 517.3 and len(seq) == 3 and seq.timestamps[0] == pytest.approx(1305031102.175304)
    image = seq.load(0)[0]
    assert image.shape == (48, 64, 3) and image[..., 2].max() > 0 and image[..., 0].max() == 0  # BGR file -> RGB
    assert np.allclose(seq.groundtruth.positions[:, 2], [3, 4])
    with pytest.raises(ValueError, match="freiburg"):
        read_tum(root.rename(tmp_path / "my_tum_copy"))


def test_image_folder(tmp_path):
    root = tmp_path / "imgs"
    root.mkdir()
    for i in [2, 10, 1]:
        cv2.imwrite(str(root / f"img{i}.png"), _image(i))
    with pytest.raises(FileNotFoundError, match="calibration.yaml"):
        read_image_folder(root)
    (root / "calibration.yaml").write_text("model: pinhole\nwidth: 64\nheight: 48\nintrinsics: [50, 50, 32, 24]\n"
                                           "distortion: [0, 0, 0, 0]\nfps: 4\n")
    seq = read_image_folder(root)
    assert [p[0].name for p in seq.image_paths] == ["img1.png", "img2.png", "img10.png"]  # natural order
    assert np.allclose(seq.timestamps, [0, 0.25, 0.5]) and np.array_equal(seq.load(1)[0], _image(2))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="holds no images"):
        read_image_folder(empty)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_image_folder(tmp_path / "missing")


def test_real_euroc_ground_truth_is_left_camera(shared_data):
    """ASL body ground truth x cam0 T_BS reproduces ORB-SLAM3's left-camera positions of V1_02 (to 0.1 mm)."""
    folder = shared_data / "trajectories"
    cam = read_euroc_groundtruth(folder / "evo_test_data" / "V102_groundtruth.csv", T_BS0)
    body = read_euroc_groundtruth(folder / "evo_test_data" / "V102_groundtruth.csv")
    ref = read_euroc_groundtruth(folder / "euroc_groundtruth" / "V102_GT.txt")
    i = np.clip(np.searchsorted(cam.timestamps, ref.timestamps), 0, len(cam) - 1)
    same = np.abs(cam.timestamps[i] - ref.timestamps) < 1e-4
    assert same.sum() > 1000
    assert np.abs(cam.positions[i[same]] - ref.positions[same]).max() < 1e-4
    assert np.abs(body.positions[i[same]] - ref.positions[same]).max() > 0.03  # T_BS matters


def test_real_tum_and_aqualoc_ground_truth(shared_data, tmp_path):
    from evo.tools import file_interface

    folder = shared_data / "trajectories"
    path = folder / "evo_test_data" / "freiburg1_xyz-groundtruth.txt"
    ours, evo_traj = read_tum_trajectory(path), file_interface.read_tum_trajectory_file(str(path))
    assert np.allclose(ours.timestamps, evo_traj.timestamps) and np.allclose(ours.poses, np.array(evo_traj.poses_se3))
    root = tmp_path / "harbor_01"
    _write_aqualoc(root, "harbor_img_sequence_01.csv", "images", n=4590)
    seq = read_aqualoc(root, groundtruth=folder / "aqualoc_groundtruth" / "new_sequence_01_gt.txt")
    assert len(seq.groundtruth) == 918 and seq.groundtruth.path_length() == pytest.approx(36.7, abs=0.1)
    assert np.allclose(np.diff(seq.groundtruth.timestamps), 0.25)  # every 5th image of a 20 Hz list
