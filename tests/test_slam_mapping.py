"""Local mapping: new points triangulated between a keyframe and its neighbours."""

import numpy as np

from ruslam.slam.atlas import Atlas
from ruslam.slam.geometry import pose_matrix, project
from ruslam.slam.local_mapping import LocalMapper, MappingConfig
from ruslam.slam.map import Frame, inverse_pose

K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
DOWN = np.diag([1.0, -1.0, -1.0])  # camera looking down


def test_a_keypoint_whose_match_is_already_mapped_is_not_triangulated_with_a_look_alike():
    """Repetitive texture puts look-alikes on a keypoint's epipolar line. Where the neighbour's keypoint that matches
    best already observes a map point, the free look-alike behind it is no match: triangulated, it makes a point at
    the look-alike's depth (a scale error the map keeps). It is a rival in the ratio test; distinct free keypoints
    are still triangulated."""
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(200, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    floor = np.c_[rng.uniform(-1.5, 1.5, (200, 2)), rng.uniform(-0.1, 0.1, 200)]
    T_kf, T_n = (inverse_pose(pose_matrix(DOWN, [x, 0.0, 2.0])) for x in (0.3, 0.0))
    # the landmark whose keypoint in the neighbour is already mapped, and a look-alike on the new keyframe's ray
    # through it (at 0.7x its distance, so the look-alike triangulates exactly, seen by the neighbour alone)
    target = 0
    centre = inverse_pose(T_kf)[:3, 3]
    look_alike = centre + 0.7 * (floor[target] - centre)
    look_alike_desc = desc[target] + 0.03 * rng.normal(size=32).astype(np.float32)

    atlas = Atlas()
    store, mapper = atlas.store, LocalMapper(atlas, MappingConfig(), binary=False)

    def keyframe(T, X, D):
        uv, _ = project(K, T, X)
        return atlas.active.new_keyframe(Frame(len(atlas.active.keyframes), 0.0, uv, D, K, (640, 480), T_cw=T))

    kf = keyframe(T_kf, floor, desc)
    n = keyframe(T_n, np.r_[floor, look_alike[None]], np.r_[desc, look_alike_desc[None]])
    mapped = np.arange(100)  # landmarks both keyframes already observe (their covisibility)
    for i in mapped:
        j = atlas.active.new_point(floor[i], desc[i], n)
        for k in (kf, n):
            if i != target or k is n:  # the new keyframe did not find the target's point
                store.add_observation(j, k, int(i))
    atlas.active.update_connections(kf)

    mapper._triangulate(kf)

    assert kf.points[target] < 0
    new = kf.points[100:]
    assert np.count_nonzero(new >= 0) >= 90
    errors = np.linalg.norm(store.position[new[new >= 0]] - floor[100:][new >= 0], axis=1)
    assert errors.max() < 1e-6
