"""The Atlas: maps, records that follow rescaled/culled keyframes, and the Sim3 merge of two maps."""

import itertools

import numpy as np

from ruslam.slam.atlas import Atlas
from ruslam.slam.geometry import pose_matrix
from ruslam.slam.local_mapping import LocalMapper, MappingConfig
from ruslam.slam.loop_closing import LoopCloser, LoopConfig, _rigid
from ruslam.slam.map import Frame, KeyFrame, Map, inverse_pose
from ruslam.slam.optimization import se3_exp

K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
DOWN = np.diag([1.0, -1.0, -1.0])  # camera looking down
IDS = itertools.count()  # keyframe ids (a run's Map numbers them; these keyframes are built by hand)


def T_true(x, z=2.0):
    return inverse_pose(pose_matrix(DOWN, [x, 0.0, z]))


def _keyframe(T_true_cw, T_est, landmarks, descriptors, store, points, index, rng, g=None):
    """A keyframe at true pose T_true_cw (its pixels), estimated pose T_est, observing `points` (ids in `store`)."""
    from ruslam.slam.geometry import project

    uv, z = project(K, T_true_cw, landmarks)
    vis = np.nonzero((z > 0) & (uv[:, 0] > 0) & (uv[:, 1] > 0) & (uv[:, 0] < 639) & (uv[:, 1] < 479))[0]
    f = Frame(index=index, timestamp=float(index), keypoints=uv[vis] + rng.normal(0, 0.3, (len(vis), 2)),
              descriptors=descriptors[vis], K=K, image_size=(640, 480),
              global_descriptor=None if g is None else np.asarray(g, np.float32), T_cw=T_est)
    kf = KeyFrame(f, next(IDS))
    for i, lm in enumerate(vis):
        store.add_observation(points[lm], kf, i)
    return kf


def _two_maps(rng, D):
    """An inactive map in the true frame (3 keyframes) and the active map in frame D (x_D = D x_true)."""
    landmarks = np.c_[rng.uniform(-2, 2, (400, 2)), rng.uniform(-0.2, 0.2, 400)]
    desc = rng.normal(size=(400, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    atlas = Atlas()
    store = atlas.store
    old_map = atlas.active
    holder = KeyFrame(Frame(0, 0.0, np.zeros((0, 2)), desc[:0], K, (640, 480), T_cw=np.eye(4)), next(IDS))
    old_pts = np.array([store.add(x, d, holder) for x, d in zip(landmarks, desc, strict=True)])
    old = [_keyframe(T_true(x), T_true(x), landmarks, desc, store, old_pts, i, rng)
           for i, x in enumerate([-0.3, 0.0, 0.3])]
    _fill(old_map, old, old_pts)
    new_map = atlas.new_map()
    new_pts = np.array([store.add(D[:3, :3] @ x + D[:3, 3], d, holder) for x, d in zip(landmarks, desc, strict=True)])
    new = [_keyframe(T_true(x), _rigid(T_true(x) @ inverse_pose(D)), landmarks, desc, store, new_pts, 10 + i, rng)
           for i, x in enumerate([0.5, 0.7, 0.9])]
    _fill(new_map, new, new_pts)
    return atlas, old, new, old_pts, new_pts


def _fill(m: Map, kfs, points):
    for j in points.tolist():
        if m.store.observations[j]:
            m.store.reference[j] = next(iter(m.store.observations[j]))
            m.points.add(j)
    for k in kfs:
        m.add_keyframe(k)
    for a, b in zip(kfs[:-1], kfs[1:], strict=True):
        b.parent = a
    for k in kfs:
        m.update_connections(k)


def _centre(T_cw):
    return inverse_pose(T_cw)[:3, 3]


def test_new_map_keeps_the_old_one_and_drops_an_empty_one():
    atlas = Atlas()
    first = atlas.active
    atlas.new_map()  # the first map is empty: replaced, not kept
    assert atlas.maps == [atlas.active] and atlas.active is not first
    atlas.active.new_keyframe(Frame(0, 0.0, np.zeros((0, 2)), np.zeros((0, 8), np.float32), K, (640, 480),
                                    T_cw=np.eye(4)))
    kept = atlas.active
    atlas.new_map()
    assert atlas.inactive() == [kept] and len(atlas.maps) == 2


def test_merge_moves_the_active_map_by_sim3_and_records_follow():
    rng = np.random.default_rng(5)
    D = pose_matrix(se3_exp(np.array([0, 0, np.deg2rad(30), 0, 0, 0]))[:3, :3], [1.5, -0.4, 0.2], s=0.4)
    atlas, old, new, old_pts, new_pts = _two_maps(rng, D)
    # a frame tracked in the active map before the merge, recorded against new[1]; its true pose is x = 0.8
    atlas.record(99, 99.0, new[1], _rigid(T_true(0.8) @ inverse_pose(D)))
    lc = LoopCloser(atlas, LocalMapper(atlas, MappingConfig(), binary=False), LoopConfig(), binary=False, stereo=False)
    # a culled keyframe of the active map: its pose must follow its parent through the merge's scale change
    atlas.active.remove_keyframe(new[2])
    assert new[2].is_bad
    before = max(np.linalg.norm(_centre(k.pose()) - _centre(T_true(x))) for k, x in zip(new, [0.5, 0.7, 0.9],
                                                                                          strict=True))
    lc.process(new[1])
    assert lc.merges == [(new[1].index, old[2].index)]  # found among the inactive map's latest keyframes
    assert atlas.maps == [old[0].map] and atlas.active is old[0].map and new[0].map is old[0].map
    after = max(np.linalg.norm(_centre(k.pose()) - _centre(T_true(x))) for k, x in zip(new, [0.5, 0.7, 0.9],
                                                                                         strict=True))
    assert before > 1.0 and after < 0.01
    record = atlas.records[0]
    assert np.linalg.norm(_centre(record.T_cw()) - _centre(T_true(0.8))) < 0.01
    # the joined region shares points now (duplicates fused)
    seen = set(new[1].points[new[1].points >= 0].tolist())
    assert len(seen & set(old_pts.tolist())) > 0.5 * len(seen)


def test_no_merge_without_a_geometric_link():
    rng = np.random.default_rng(6)
    atlas, old, new, _, _ = _two_maps(rng, np.eye(4))
    for k in new:  # the active map sees other landmarks: descriptors no longer match the old map's
        k.descriptors = rng.normal(size=k.descriptors.shape).astype(np.float32)
    lc = LoopCloser(atlas, LocalMapper(atlas, MappingConfig(), binary=False), LoopConfig(), binary=False, stereo=False)
    lc.process(new[1])
    assert lc.merges == [] and len(atlas.maps) == 2


def test_every_run_numbers_its_keyframes_and_points_from_zero_across_its_maps():
    # ids seed loop closing's RANSAC and order sets: numbered per process, a run's result depended on what ran
    # before it (a grid cell alone or after another); point ids are rows of the run's store
    f = Frame(0, 0.0, np.zeros((0, 2)), np.zeros((0, 8), np.float32), K, (640, 480), T_cw=np.eye(4))
    for _ in range(2):
        atlas = Atlas()
        kf = atlas.active.new_keyframe(f)
        p = atlas.active.new_point(np.zeros(3), np.zeros(8, np.float32), kf)
        second_map = atlas.new_map()
        kf2 = second_map.new_keyframe(f)
        q = second_map.new_point(np.zeros(3), np.zeros(8, np.float32), kf2)
        assert (kf.id, p, kf2.id, q) == (0, 0, 1, 1)
        assert p in atlas.maps[0].points and q in second_map.points and second_map.keyframes == [kf2]
