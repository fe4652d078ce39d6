"""Loop closing: eq. 9 scores, retrieval, temporal consistency; the full loop on a drifting sequence (slow)."""

import itertools

import numpy as np

from ruslam.models.feature_matching import match_knn_ratio
from ruslam.slam.atlas import Atlas
from ruslam.slam.geometry import pose_matrix
from ruslam.slam.loop_closing import KeyFrameDatabase, LoopCloser, LoopConfig
from ruslam.slam.map import Frame, KeyFrame, Map

K = np.array([[450.0, 0, 320], [0, 450.0, 240], [0, 0, 1]])
IDS = itertools.count()  # keyframe ids (a run's Map numbers them; these keyframes are built by hand)


def keyframe(g, index=0):
    f = Frame(index=index, timestamp=float(index), keypoints=np.zeros((0, 2)), descriptors=np.zeros((0, 8), np.float32),
              K=K, image_size=(640, 480), global_descriptor=np.asarray(g, np.float32), T_cw=np.eye(4))
    return KeyFrame(f, next(IDS))


def _yaw(deg):
    a = np.radians(deg)
    return np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])


def test_eq9_scores_match_the_definition():
    rng = np.random.default_rng(0)
    vectors = rng.normal(size=(20, 4096)) * rng.uniform(0.5, 3.0, (20, 1))  # unnormalised on purpose
    db = KeyFrameDatabase()
    for v in vectors:
        db.add(keyframe(v))
    q = rng.normal(size=4096)
    unit = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    expected = 1.0 - np.linalg.norm(unit - q / np.linalg.norm(q), axis=1)
    assert np.allclose(db.scores(q), expected, atol=1e-5)
    assert np.isclose(db.scores(vectors[3] * 7.0)[3], 1.0, atol=1e-5)  # same direction: distance 0
    e = np.zeros(4096)
    e[0] = 1.0
    db2 = KeyFrameDatabase()
    db2.add(keyframe(np.eye(4096)[1]))
    assert np.isclose(db2.scores(e)[0], 1.0 - np.sqrt(2.0), atol=1e-6)  # orthogonal unit vectors


def test_query_ranks_and_excludes():
    rng = np.random.default_rng(1)
    base = rng.normal(size=64)
    db = KeyFrameDatabase()
    kfs = [keyframe(base + rng.normal(0, s, 64), i) for i, s in enumerate([0.1, 0.5, 1.0, 2.0, 4.0])]
    for k in kfs:
        db.add(k)
    assert db.query(base, k=3) == kfs[:3]
    kfs[0].is_bad = True
    assert db.query(base, k=2, exclude={kfs[1]}) == kfs[2:4]
    scores = db.scores(base)
    assert db.query(base, k=5, min_score=float(scores[2]) + 1e-6) == [kfs[1]]


def test_a_culled_keyframe_leaves_the_database_and_frees_its_arrays():
    rng = np.random.default_rng(3)
    m = Atlas().active
    vectors = rng.normal(size=(4, 4096))
    kfs = [m.new_keyframe(Frame(i, float(i), rng.uniform(0, 480, (500, 2)), rng.normal(size=(500, 64)).astype(
        np.float32), K, (640, 480), global_descriptor=vectors[i].astype(np.float32),
        T_cw=pose_matrix(np.eye(3), [0.1 * i, 0, 0]))) for i in range(4)]
    for child, parent in itertools.pairwise(kfs):
        child.parent = parent
    db = KeyFrameDatabase()
    for k in kfs[:3]:
        db.add(k)
    m.remove_keyframe(kfs[2])
    released = kfs[2]
    assert released.descriptors.size == 0 and released.descriptors.base is None  # a copy, not a view of the array
    assert released.keypoints.size == 0 and released.global_descriptor is None
    assert np.allclose(kfs[2].pose(), pose_matrix(np.eye(3), [0.2, 0, 0]))  # still posed through its parent
    db.add(kfs[3])
    assert db.keyframes == [kfs[0], kfs[1], kfs[3]] and len(db) == 3
    unit = vectors[[0, 1, 3]] / np.linalg.norm(vectors[[0, 1, 3]], axis=1, keepdims=True)
    assert np.allclose(db.scores(vectors[0]), 1.0 - np.linalg.norm(unit - unit[0], axis=1), atol=1e-6)


def _loop_closer(consistency=3):
    cfg = LoopConfig(min_keyframes=0, exclude_recent=0, consistency=consistency, min_score=0.0)
    return LoopCloser(Atlas(), None, cfg, binary=False, stereo=False)


def _covisible(lc, group):
    for a in group:
        for b in group:
            if a is not b:
                lc.map.covisibility[a][b] = 50


def test_candidate_needs_consecutive_consistent_detections():
    rng = np.random.default_rng(2)
    lc = _loop_closer()
    place = rng.normal(size=256)
    old = [keyframe(place + rng.normal(0, 0.2, 256), i) for i in range(3)]  # an old, mutually covisible group
    others = [keyframe(rng.normal(size=256), 10 + i) for i in range(5)]
    for k in old + others:
        lc.map.add_keyframe(k)
        lc.database.add(k)
    _covisible(lc, old)
    found = []
    for i in range(4):  # four new keyframes back at the old place, not covisible with it
        q = keyframe(place + rng.normal(0, 0.2, 256), 100 + i)
        lc.map.add_keyframe(q)
        found.append(lc._detect(q))
    assert found[0] == [] and found[1] == []  # first and second sightings: not yet consistent
    assert found[2] and found[2][0] in old and found[3]
    # detections that jump between unrelated places never become consistent
    lc2 = _loop_closer()
    places = [rng.normal(size=256) for _ in range(4)]
    for p in places:
        k = keyframe(p)
        lc2.map.add_keyframe(k)
        lc2.database.add(k)
    for p in places:
        q = keyframe(p + rng.normal(0, 0.1, 256))
        lc2.map.add_keyframe(q)
        assert lc2._detect(q) == []


def test_a_loop_verified_by_consecutive_keyframes_closes_without_the_cost_check():
    """The cost check refuses every candidate here; a place verified by `consistency` keyframes in a row is closed
    all the same, a place verified once, or by keyframes that a keyframe without a verified loop interrupts, is not,
    nor one whose correction turns the camera beyond half its field of view."""
    lc = _loop_closer()
    place = [keyframe(np.ones(8), i) for i in range(3)]
    elsewhere = keyframe(-np.ones(8), 3)
    for k in [*place, elsewhere]:
        lc.map.add_keyframe(k)
    _covisible(lc, place)
    closed = []
    lc._undoes_the_motion = lambda kf, cand, S: False
    lc._lowers_residuals = lambda kf, cand, S, matches: False
    lc._correct = lambda kf, cand, S, points: closed.append((kf.index, cand.index))
    verified = {}  # new keyframe index -> the keyframe it verifies a loop to (none: no loop verified)
    lc._detect = lambda kf: [verified[kf.index]] if kf.index in verified else []
    lc._verify = lambda kf, cand: (np.eye(4), np.zeros(0, int), (np.zeros(0, int), np.zeros(0, int)))

    def new_keyframes(loops: dict, first: int):
        for i in range(first, first + len(loops)):
            verified.clear()
            if loops[i] is not None:
                verified[i] = loops[i]
            q = keyframe(np.zeros(8), i)
            lc.map.add_keyframe(q)
            lc.process(q)

    new_keyframes({10: place[0], 11: elsewhere, 12: place[1], 13: None, 14: place[2], 15: place[0]}, 10)
    assert closed == []  # never three in a row at one place
    new_keyframes({16: place[1]}, 16)  # the third in a row at the covisible group: closed
    assert closed == [(16, place[1].index)]
    turned = pose_matrix(_yaw(90), np.zeros(3))  # a look-alike after a quarter turn, verified three times in a row
    lc._verify = lambda kf, cand: (turned, np.zeros(0, int), (np.zeros(0, int), np.zeros(0, int)))
    new_keyframes({17: place[0], 18: place[1], 19: place[2]}, 17)
    assert closed == [(16, place[1].index)]


def test_covisible_neighbours_are_not_loop_candidates():
    rng = np.random.default_rng(3)
    lc = _loop_closer(consistency=1)
    place = rng.normal(size=128)
    a, b = keyframe(place), keyframe(place + rng.normal(0, 0.05, 128))
    for k in (a, b):
        lc.map.add_keyframe(k)
    lc.database.add(a)
    lc.map.covisibility[a][b] = lc.map.covisibility[b][a] = 40
    assert lc._detect(b) == []
    del lc.map.covisibility[a][b], lc.map.covisibility[b][a]
    assert lc._detect(b) == [a]


def _observing_keyframe(T_true, T_est, landmarks, descriptors, store, points, index, rng):
    """A keyframe at true pose T_true (its pixels), estimated pose T_est, observing `points` (ids in `store`, one per
    landmark)."""
    from ruslam.slam.geometry import project

    uv, z = project(K, T_true, landmarks)
    vis = np.nonzero((z > 0) & (uv[:, 0] > 0) & (uv[:, 1] > 0) & (uv[:, 0] < 639) & (uv[:, 1] < 479))[0]
    f = Frame(index=index, timestamp=float(index), keypoints=uv[vis] + rng.normal(0, 0.3, (len(vis), 2)),
              descriptors=descriptors[vis], K=K, image_size=(640, 480),
              global_descriptor=np.ones(8, np.float32), T_cw=T_est)
    kf = KeyFrame(f, next(IDS))
    for i, l in enumerate(vis):
        store.add_observation(points[l], kf, i)
    return kf


def _drifted_revisit(rng, before_group=None):
    """A loop over a plane seen from 2 m: three old keyframes at their true poses (x = -0.3, 0, 0.3) and three of a
    second pass (x = -0.2, 0.1, 0.4) in a map drifted by a similarity D (scale 1.08, 4 deg, 0.25 m), duplicating the
    old points; the second pass hangs off the first through one drifted edge. `before_group(...)` may add second-pass
    keyframes before those three. Returns (loop closer, old, new, T_true, old points)."""
    from ruslam.slam.local_mapping import LocalMapper, MappingConfig
    from ruslam.slam.loop_closing import _rigid
    from ruslam.slam.map import inverse_pose
    from ruslam.slam.optimization import se3_exp

    landmarks = np.c_[rng.uniform(-2, 2, (400, 2)), rng.uniform(-0.2, 0.2, 400)]
    desc = rng.normal(size=(400, 32)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    down = np.diag([1.0, -1.0, -1.0])  # camera looking down from 2 m

    def T_true(x):
        return inverse_pose(pose_matrix(down, [x, 0.0, 2.0]))

    D = pose_matrix(se3_exp(np.array([0, 0, np.deg2rad(4), 0, 0, 0]))[:3, :3], [0.25, -0.1, 0.05], s=1.08)
    m = Map()
    atlas = Atlas(m)
    mapper = LocalMapper(atlas, MappingConfig(), binary=False)
    lc = LoopCloser(atlas, mapper, LoopConfig(global_bundle_adjustment=False), binary=False, stereo=False)
    placeholder = keyframe(np.ones(8))  # points need a creator; the real one is set below
    store = atlas.store
    old_pts = np.array([store.add(x, d, placeholder) for x, d in zip(landmarks, desc, strict=True)])
    new_pts = np.array([store.add(D[:3, :3] @ x + D[:3, 3], d, placeholder)
                        for x, d in zip(landmarks, desc, strict=True)])
    old = [_observing_keyframe(T_true(x), T_true(x), landmarks, desc, store, old_pts, i, rng)
           for i, x in enumerate([-0.3, 0.0, 0.3])]
    new = [_observing_keyframe(T_true(x), _rigid(T_true(x) @ inverse_pose(D)), landmarks, desc, store, new_pts,
                               10 + i, rng) for i, x in enumerate([-0.2, 0.1, 0.4])]
    earlier = [] if before_group is None else before_group(T_true, D, landmarks, desc, store, new_pts, new)
    for j in range(len(store.observations)):
        if store.observations[j]:
            store.reference[j] = next(iter(store.observations[j]))
            m.points.add(int(j))
    chain = old + earlier + new
    for k in chain:
        m.add_keyframe(k)
    for a, b in zip(chain[:-1], chain[1:], strict=True):
        b.parent = a  # odometry: the new keyframes hang off the old ones through a drifted edge
    for k in chain:
        m.update_connections(k)
    return lc, old, new, T_true, old_pts


def test_loop_correction_removes_drift_and_fuses_duplicates():
    from ruslam.slam.geometry import pose_matrix
    from ruslam.slam.map import inverse_pose
    from ruslam.slam.optimization import se3_exp

    lc, old, new, T_true, old_pts = _drifted_revisit(np.random.default_rng(4))

    def centre_error(kfs):
        return max(np.linalg.norm(inverse_pose(k.T_cw)[:3, 3] - inverse_pose(T_true(x))[:3, 3])
                   for k, x in zip(kfs, [-0.2, 0.1, 0.4], strict=True))

    before = centre_error(new)
    found = lc._verify(new[-1], old[1])
    assert found is not None
    S12, loop_points, matches = found
    # the correction is predicted before anything moves: the true similarity lowers the reprojection cost, a wrong
    # one (a look-alike place 0.6 m and 20 deg away) raises it and is refused
    wrong = pose_matrix(se3_exp(np.array([0, 0, np.deg2rad(20), 0, 0, 0]))[:3, :3], [0.6, 0.2, 0.0]) @ S12
    assert not lc._lowers_residuals(new[-1], old[1], wrong, matches)
    assert lc._lowers_residuals(new[-1], old[1], S12, matches)
    lc._correct(new[-1], old[1], S12, loop_points)
    assert before > 0.2 and centre_error(new) < 0.1 * before
    assert lc.loops == [(new[-1].index, old[1].index)]
    # duplicates were fused: the new keyframes now observe the old points
    seen = {j for k in new for j in k.points[k.points >= 0].tolist()}
    assert len(seen & set(old_pts.tolist())) > 0.8 * len(seen)


def test_a_link_fusion_adds_on_this_side_of_the_loop_does_not_change_the_correction():
    """A second-pass keyframe just before the corrected group (covisible with the group's first keyframe only) holds
    duplicates of points the current keyframe sees, and fusing merges them, which links it to the current keyframe.
    That link is not one across the loop: measured on the corrected poses it would hold the uncorrected keyframe where
    it was (on the tiled pool it left a 0.3 m step between the group and the track before it). The correction must be
    the one made without the merge."""
    from ruslam.slam.loop_closing import _rigid
    from ruslam.slam.map import inverse_pose

    def corrected(merge: bool):
        duplicates = {}

        def before_group(T_true, D, landmarks, desc, store, new_pts, new):
            seen = [set(k.points.tolist()) for k in new]
            first_only = [i for i, j in enumerate(new_pts) if j in seen[0] and j not in seen[1] | seen[2]]
            last = [i for i, j in enumerate(new_pts) if j in seen[2]][:45]  # a weak link (no essential-graph edge)
            own = [store.add(D[:3, :3] @ landmarks[i] + D[:3, 3], desc[i], new[0]) for i in last]
            T = T_true(-0.6)
            kf = _observing_keyframe(T, _rigid(T @ inverse_pose(D)), landmarks[first_only + last],
                                     desc[first_only + last], store, np.r_[new_pts[first_only], own], 9,
                                     np.random.default_rng(0))
            duplicates.update({j: new_pts[i] for i, j in zip(last, own, strict=True) if store.observations[j]})
            return [kf]

        lc, old, new, _, _ = _drifted_revisit(np.random.default_rng(4), before_group)
        earlier = next(k for k in lc.map.keyframes if k.index == 9)
        assert earlier not in lc.map.neighbours(new[-1]) and earlier in lc.map.neighbours(new[0])
        assert len(duplicates) >= 20
        fuse = lc.mapper.fuse_points

        def fuse_and_merge(kf, points, **kw):
            out = fuse(kf, points, **kw)
            for dup, point in list(duplicates.items()):  # the duplicates merged
                lc.map.replace_point(dup, int(lc.atlas.store.resolve(np.array([point]))[0]))
                del duplicates[dup]
            return out

        if merge:
            lc.mapper.fuse_points = fuse_and_merge
        S12, loop_points, _ = lc._verify(new[-1], old[1])
        lc._correct(new[-1], old[1], S12, loop_points)
        assert (earlier in lc.map.neighbours(new[-1])) == merge  # the link fusion added
        return earlier.T_cw

    assert np.allclose(corrected(merge=True), corrected(merge=False), atol=1e-9)


def _revisit(matching: int, look_alike: bool, pair_matcher_calls: list):
    """A loop closer, a current keyframe and an old one 0.1 m apart seeing the same 400 landmarks (no drift). The
    texture repeats: all but `matching` landmarks have a twin with the same descriptor elsewhere in view, so the
    ratio test keeps only the `matching` unique ones (fewer than `min_matches`); with `look_alike` those sit on the
    wrong landmarks in the current keyframe (a place that looks the same, geometry that does not agree). The pair
    matcher returns the true correspondences and records its calls."""
    from ruslam.slam.geometry import pose_matrix
    from ruslam.slam.local_mapping import LocalMapper, MappingConfig
    from ruslam.slam.map import inverse_pose

    rng = np.random.default_rng(5)
    landmarks = np.c_[rng.uniform(-1.2, 1.2, 400), rng.uniform(-0.9, 0.9, 400), rng.uniform(-0.2, 0.2, 400)]

    def unit(d):
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    twins = (400 - matching) // 2
    base = rng.normal(size=(matching + twins, 32))
    desc_old = unit(np.r_[base, base[matching:]] + rng.normal(0, 0.01, (matching + 2 * twins, 32)))
    desc_new = unit(desc_old + rng.normal(0, 0.02, desc_old.shape))
    if look_alike:
        desc_new[:matching] = desc_new[rng.permutation(matching)]
    down = np.diag([1.0, -1.0, -1.0])

    def T(x):
        return inverse_pose(pose_matrix(down, [x, 0.0, 2.0]))

    atlas = Atlas(Map())
    lc = LoopCloser(atlas, LocalMapper(atlas, MappingConfig(), binary=False), LoopConfig(), binary=False,
                    stereo=False)
    store = atlas.store
    placeholder = keyframe(np.ones(8))
    old_pts = np.array([store.add(x, d, placeholder) for x, d in zip(landmarks, desc_old, strict=True)])
    new_pts = np.array([store.add(x, d, placeholder) for x, d in zip(landmarks, desc_new, strict=True)])
    old = _observing_keyframe(T(0.0), T(0.0), landmarks, desc_old, store, old_pts, 0, rng)
    new = _observing_keyframe(T(0.1), T(0.1), landmarks, desc_new, store, new_pts, 10, rng)
    landmark_of_old = {int(p): i for i, p in enumerate(old_pts)}
    landmark_of_new = {int(p): i for i, p in enumerate(new_pts)}

    def pair_matcher(kp1, d1, size1, kp2, d2, size2):  # (new, old) -> the true correspondences
        pair_matcher_calls.append(len(kp1))
        where = {landmark_of_old[int(p)]: j for j, p in enumerate(old.points)}
        a = [i for i, p in enumerate(new.points) if landmark_of_new[int(p)] in where]
        return np.array(a), np.array([where[landmark_of_new[int(new.points[i])]] for i in a])

    lc.pair_matcher = pair_matcher
    atlas.active.add_keyframe(old)
    atlas.active.add_keyframe(new)
    for j in np.r_[old_pts, new_pts]:
        if store.observations[j]:
            store.reference[j] = next(iter(store.observations[j]))
            atlas.active.points.add(int(j))
    return lc, new, old


def test_pair_matcher_only_for_knn_matches_that_agree_on_a_similarity():
    # a revisit where kNN finds 12 matches (< min_matches 20) on the right landmarks: they agree on one similarity,
    # so the pair matcher is asked for more and the loop is verified
    calls = []
    lc, new, old = _revisit(12, look_alike=False, pair_matcher_calls=calls)
    assert lc.cfg.pair_matcher_min_inliers <= 12 < lc.cfg.min_matches
    ia, ib = lc.atlas.store.matched(new), lc.atlas.store.matched(old)
    assert len(match_knn_ratio(new.descriptors[ia], old.descriptors[ib], False, 0.7, 0.8)[0]) == 12
    assert lc._verify(new, old) is not None
    assert len(calls) == 1
    # the same number of kNN matches on a look-alike place: no similarity, the pair matcher is never called
    calls = []
    lc, new, old = _revisit(12, look_alike=True, pair_matcher_calls=calls)
    assert lc._verify(new, old) is None
    assert calls == []


def test_a_correction_that_undoes_the_motion_between_the_loop_keyframes_is_refused():
    from ruslam.slam.geometry import pose_matrix
    from ruslam.slam.loop_closing import undoes_the_motion
    from ruslam.slam.map import inverse_pose

    def T_cw(centre, heading):
        return inverse_pose(pose_matrix(_yaw(heading), centre))

    # 1 m along x, a 90 deg corner, 1 m along y: keyframes every 0.25 m
    leg = [T_cw([x, 0, 0], 0) for x in np.linspace(0, 1, 5)] + [T_cw([1, y, 0], 90) for y in np.linspace(0, 1, 5)]
    path = np.stack(leg)
    start = leg[0].copy()
    start[:3] *= 0.9  # a similarity: the loop also rescales
    assert undoes_the_motion(path, start)  # back at the first corner: the look-alike place
    drifted = T_cw([1.1, 0.95, 0], 95)  # 0.1 m and 5 deg of drift over 2 m and 90 deg
    assert not undoes_the_motion(path, drifted)
    # turning in place: a correction of 5 cm is more than half the distance travelled, but not of the rotation
    spin = np.stack([T_cw([0, 0, 0], h) for h in range(0, 181, 20)])
    assert not undoes_the_motion(spin, T_cw([0.05, 0, 0], 175))
    assert undoes_the_motion(spin, T_cw([0.05, 0, 0], 0))


def test_a_correction_beyond_half_the_field_of_view_turns_out_of_view():
    from ruslam.slam.loop_closing import turns_out_of_view

    T = pose_matrix(_yaw(30), np.array([0.2, 0.0, 1.0]))
    for deg, beyond in [(5, False), (30, False), (40, True), (90, True), (-90, True)]:  # K: 640 px at f 450, 35.4 deg
        S = pose_matrix(_yaw(deg) @ T[:3, :3], T[:3, 3] + 0.3)
        S[:3] *= 0.6  # a similarity: the loop also rescales
        assert turns_out_of_view(T, S, K, (640, 480)) == beyond
    narrow = K.copy()
    narrow[0, 0] = 1000.0  # 17.7 deg
    assert turns_out_of_view(T, pose_matrix(_yaw(25) @ T[:3, :3], T[:3, 3]), narrow, (640, 480))
