"""Multi-view geometry on arrays: triangulation, two-view initialisation (H vs F), PnP, stereo, Sim3/SE3 RANSAC.

Poses are 4x4 ``T_cw`` (world -> camera); pixels are undistorted, for the ideal pinhole ``K``. Every RANSAC takes a
seed: OpenCV's global RNG is reseeded before each call and our own loops draw from ``numpy.random.default_rng``,
so the synchronous mode reproduces a run exactly.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np

from ruslam.slam.map import inverse_pose, transform

CHI2_2DOF = 5.991  # 95% quantile of chi^2 with 2 degrees of freedom (reprojection error, sigma = 1 px)
CHI2_1DOF = 3.841
CLOSE = 0.75  # two motions triangulating more than this share of the best's points are both plausible
SAME_DEG = 30.0  # translations closer than this are one motion (a plane's two solutions are ~90 deg apart)


def pose_matrix(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R)
    T[:3, 3] = np.ravel(t)
    return T


def project(K: np.ndarray, T_cw: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (pixels [N, 2], depth [N])."""
    return _pinhole(K, transform(T_cw, X))


def _pinhole(K: np.ndarray, Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points [..., N, 3] -> (pixels [..., N, 2], depth [..., N])."""
    z = Xc[..., 2]
    safe = np.where(np.abs(z) < 1e-9, 1e-9, z)
    return (Xc[..., :2] / safe[..., None]) @ K[:2, :2].T + K[:2, 2], z


def triangulate(K1, T1_cw, x1, K2, T2_cw, x2) -> np.ndarray:
    """Linear (DLT) triangulation of matched pixels [N, 2] seen from two posed views -> world points [N, 3]."""
    if len(x1) == 0:
        return np.zeros((0, 3))
    P1 = K1 @ T1_cw[:3]
    P2 = K2 @ T2_cw[:3]
    Xh = cv2.triangulatePoints(P1, P2, np.asarray(x1, np.float64).T, np.asarray(x2, np.float64).T)
    w = Xh[3]
    w = np.where(np.abs(w) < 1e-12, 1e-12, w)
    return (Xh[:3] / w).T


def triangulation_mask(X, K1, T1_cw, x1, K2, T2_cw, x2, max_error_px: float = 2.0, min_parallax_deg: float = 1.0):
    """Points in front of both cameras, reprojecting within `max_error_px`, seen under enough parallax."""
    u1, z1 = project(K1, T1_cw, X)
    u2, z2 = project(K2, T2_cw, X)
    ok = (z1 > 0) & (z2 > 0) & np.all(np.isfinite(X), axis=1)
    ok &= np.sum((u1 - x1) ** 2, 1) < max_error_px**2
    ok &= np.sum((u2 - x2) ** 2, 1) < max_error_px**2
    r1 = X - inverse_pose(T1_cw)[:3, 3]
    r2 = X - inverse_pose(T2_cw)[:3, 3]
    cos = np.sum(r1 * r2, 1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-12)
    return ok & (cos < np.cos(np.deg2rad(min_parallax_deg)))


# --- two-view initialisation -------------------------------------------------------------------------------------
def _homography_score(H, x1, x2, sigma=1.0):
    """ORB-SLAM's symmetric transfer score: sum over inliers of (chi2 threshold - error)."""
    def err(Hm, a, b):
        ah = np.c_[a, np.ones(len(a))] @ Hm.T
        return np.sum((ah[:, :2] / ah[:, 2:3] - b) ** 2, 1) / sigma**2

    e12, e21 = err(H, x1, x2), err(np.linalg.inv(H), x2, x1)
    return np.sum(np.where(e12 < CHI2_2DOF, CHI2_2DOF - e12, 0) + np.where(e21 < CHI2_2DOF, CHI2_2DOF - e21, 0))


def _fundamental_score(F, x1, x2, sigma=1.0):
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    l2, l1 = h1 @ F.T, h2 @ F  # epipolar lines in image 2 and image 1
    num = np.sum(h2 * l2, 1) ** 2
    e2 = num / np.maximum(l2[:, 0] ** 2 + l2[:, 1] ** 2, 1e-12) / sigma**2
    e1 = num / np.maximum(l1[:, 0] ** 2 + l1[:, 1] ** 2, 1e-12) / sigma**2
    # errors gated by the 1-dof threshold but scored against the 2-dof one, so H and F scores are comparable
    return np.sum(np.where(e2 < CHI2_1DOF, CHI2_2DOF - e2, 0) + np.where(e1 < CHI2_1DOF, CHI2_2DOF - e1, 0))


def _triangulated(candidates, K, x1, x2, max_error_px, step):
    """(points it explains, T2, X, good mask, parallax) per candidate motion (R, t) with camera 1 at the origin. Good
    points reproject within `max_error_px` in front of both cameras. For a map's first points a match is explained
    when it is good, or reprojects as well but is seen under less parallax than that error subtends, too little to
    tell in front from behind (ORB-SLAM's CheckRT): under forward motion noise puts the points near the focus of
    expansion on either side, while a plane's spurious solution, rotating by about the parallax angle, lends them
    parallax and keeps them all in front. A `step` counts its good points (its close motions go to the last motion's
    rotation, and more of them made the desk's chained odometry worse). The parallax is the 50th smallest good point's
    for a map's first points, the median for a step (forward motion leaves the points near the focus of expansion
    without any)."""
    T1 = np.eye(4)
    undecided_deg = np.rad2deg(max_error_px / K[0, 0])
    results = []
    for R, t in candidates:
        T2 = pose_matrix(R, np.ravel(t) / max(np.linalg.norm(t), 1e-12))
        X = triangulate(K, T1, x1, K, T2, x2)
        (u1, z1), (u2, z2) = project(K, T1, X), project(K, T2, X)
        fits = np.all(np.isfinite(X), axis=1) & (np.sum((u1 - x1) ** 2, 1) < max_error_px**2)
        fits &= np.sum((u2 - x2) ** 2, 1) < max_error_px**2
        good = fits & (z1 > 0) & (z2 > 0)
        r1, r2 = X, X - inverse_pose(T2)[:3, 3]  # camera 1 sits at the origin
        cos = np.sum(r1 * r2, 1) / np.maximum(np.linalg.norm(r1, axis=1) * np.linalg.norm(r2, axis=1), 1e-12)
        angle = np.rad2deg(np.arccos(np.clip(cos, -1, 1)))
        explained = good if step else good | (fits & (angle < undecided_deg))
        parallax = np.sort(angle[good])
        rank = len(parallax) // 2 if step else min(49, len(parallax) - 1)
        results.append((int(explained.sum()), T2, X, good, parallax[rank] if len(parallax) else 0.0))
    if step:
        return results
    # of two motions with one rotation and opposite translations (the decompositions' twins), which share the points
    # without parallax, the one with more points in front
    return [r for r in results if not any(np.allclose(o[1][:3, :3], r[1][:3, :3]) and o[3].sum() > r[3].sum()
                                          for o in results)]


def _best_motion(results, min_parallax_deg, min_points, rotation_ratio=0.5, prior_R=None, step=False, rivals=()):
    """Of `_triangulated` results, the motion that explains the most matches; when two hypotheses are close, the one
    nearer the rotation prior (`prior_R`, default none: identity) when it is clearly nearer, else for a map's first
    points the one with clearly the most good points, else none. `rivals`: the other model's results, which can only
    refuse a map's first points: a near-planar view with little parallax lets E and H triangulate as many points
    along different translations (ORB on the desk: E's 180 points, 93 deg from H's 205, which were right)."""
    results = sorted(results, key=lambda r: -r[0])
    if max(np.count_nonzero(r[3]) for r in results) < min_points:
        return None
    close = [r for r in results if r[0] > CLOSE * results[0][0]]
    # a rival counts when it could be taken itself (enough parallax); one along the translation of one of ours is
    # the same motion (H and E both hold it)
    close += [r for r in rivals if r[0] > CLOSE * results[0][0] and r[4] >= min_parallax_deg and
              all(_angle_deg(r[1][:3, 3], c[1][:3, 3]) > SAME_DEG for c in close)]
    if len(close) > 1:
        # A plane (a seafloor seen from above) has two exact solutions, the spurious one rotating the camera by
        # about the parallax angle (Faugeras-Lustman): between video frames the one closer to the expected rotation
        # (none, or the last motion's) is the real one when it is clearly closer; otherwise the one that puts clearly
        # the most points in front, or wait for a better pair.
        prior = np.eye(3) if prior_R is None else prior_R

        def off_prior(r):
            return rotation_deg(r[1][:3, :3] @ prior.T)

        close.sort(key=off_prior)
        if not step and off_prior(close[0]) > rotation_ratio * off_prior(close[1]):
            close.sort(key=lambda r: -np.count_nonzero(r[3]))
            if np.count_nonzero(close[1][3]) > CLOSE * np.count_nonzero(close[0][3]):
                return None
        if any(close[0] is r for r in rivals):
            return None
    _, T2, X, good, par = close[0]
    if good.sum() < min_points or par < min_parallax_deg:
        return None
    return T2, X, good


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12), -1, 1))))


def rotation_deg(R: np.ndarray) -> float:
    """The angle of a rotation matrix (or of a pose's rotation), in degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R[:3, :3]) - 1) / 2, -1.0, 1.0))))


def _two_view_model(x1, x2, K, seed, method, iterations, min_parallax_deg, min_points, homography_ratio, sigma,
                    prior_R, step):
    """H and E by one robust estimator (`method`), the better-scoring model decomposed: (best motion or None, name)."""
    cv2.setRNGSeed(seed)
    H, _ = cv2.findHomography(x1, x2, method, 2.0 * sigma, maxIters=iterations, confidence=0.999)
    cv2.setRNGSeed(seed)
    try:
        E, _ = cv2.findEssentialMat(x1, x2, K, method, 0.999, 1.0 * sigma, maxIters=iterations)
    except cv2.error:  # the 5-point polynomial degenerates on exact pure rotations
        E = None
    E = E[:3] if E is not None and E.shape[0] >= 3 else None  # the 5-point solver may return several
    K_inv = np.linalg.inv(K)
    s_h = _homography_score(H, x1, x2, sigma) if H is not None else 0.0
    s_e = _fundamental_score(K_inv.T @ E @ K_inv, x1, x2, sigma) if E is not None else 0.0
    if s_h + s_e <= 0:
        return None, None
    motions = {"homography": [], "essential": []}
    if H is not None:
        _, Rs, ts, _ = cv2.decomposeHomographyMat(H, K)
        motions["homography"] = list(zip(Rs, ts, strict=True))
    if E is not None:
        R1, R2, t = cv2.decomposeEssentialMat(E)
        motions["essential"] = [(R1, t), (R1, -t), (R2, t), (R2, -t)]
    model, rival = ("homography", "essential") if s_h / (s_h + s_e) > homography_ratio else \
        ("essential", "homography")
    rivals = [] if step else _triangulated(motions[rival], K, x1, x2, 2.0 * sigma, step)  # a step: its prior decides
    return _best_motion(_triangulated(motions[model], K, x1, x2, 2.0 * sigma, step), min_parallax_deg, min_points,
                        prior_R=prior_R, step=step, rivals=rivals), model


def two_view_initialization(
    x1: np.ndarray, x2: np.ndarray, K: np.ndarray, seed: int = 0, min_parallax_deg: float = 1.0,
    min_points: int = 50, homography_ratio: float = 0.40, sigma: float = 1.0, prior_R: np.ndarray | None = None,
    step: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str] | None:
    """Monocular map initialisation from matches x1 <-> x2 (ORB-SLAM: score H against the epipolar model, keep the
    better one). The epipolar model is the calibrated 5-point essential matrix (keypoints are undistorted with a
    known K), not ORB-SLAM's F: F's two extra degrees of freedom absorb noise and outliers, and with ~100 noisy
    matches its translation came out over 10 deg off for most pairs (tests/test_slam_geometry.py).

    Returns (T2_cw with camera 1 at the origin, world points [N, 3], valid mask [N], model name) with the scene
    scaled to unit median depth in camera 1, or None when the geometry is not trustworthy (too little parallax,
    ambiguous solutions, too few points). `sigma` is the keypoint noise in px: models are scored against it, so a
    learned extractor's noisier keypoints do not make E look better than H on a flat seafloor.
    `prior_R`: the expected rotation of camera 2 relative to camera 1 (a motion model), None for no rotation;
    `step`: a frame-to-frame step (bridge, odometry) rather than a map's first points: the median parallax is
    tested, and of two close hypotheses the one nearer the prior is taken.
    A step's models come first from locally optimised RANSAC (OpenCV's USAC, adaptive iterations): with a third of
    its matches right, 500 plain samples return no model or one off by tens of degrees; when that motion fails the
    checks, plain RANSAC's is tried (on repeated tiles the two differ). A map's first points keep plain RANSAC, whose
    models the 0.40 H-vs-epipolar ratio was set with (USAC's H and F started DEV `hard` and `pitch58_s3` worse).
    """
    if len(x1) < max(min_points, 8):
        return None
    x1 = np.asarray(x1, np.float64)
    x2 = np.asarray(x2, np.float64)
    searches = ((cv2.USAC_ACCURATE, 5000), (cv2.RANSAC, 500)) if step else ((cv2.RANSAC, 500),)
    for method, iterations in searches:
        best, model = _two_view_model(x1, x2, K, seed, method, iterations, min_parallax_deg, min_points,
                                      homography_ratio, sigma, prior_R, step)
        if best is not None:
            break
    if best is None:
        return None
    T2, X, good = best
    median_depth = np.median(X[good, 2])
    if not median_depth > 0:
        return None
    X = X / median_depth
    T2 = T2.copy()
    T2[:3, 3] /= median_depth
    return T2, X, good, model


def interpolate_pose(T1: np.ndarray, T2: np.ndarray, a: float) -> np.ndarray:
    """The pose `a` of the way from T1 to T2, on SE(3)."""
    step = gtsam.Pose3.Logmap(gtsam.Pose3(T2 @ inverse_pose(T1)))
    return gtsam.Pose3.Expmap(a * step).matrix() @ T1


def step_min_parallax_deg(K: np.ndarray, sigma: float, depth_error: float = 0.5) -> float:
    """The parallax (deg) at which a point's depth is known to `depth_error` (relative) from keypoints with `sigma`
    px of noise. A frame-to-frame step (bridge, odometry) needs no more at its median point: its scale is a median
    over tens of points, whose error is several times smaller."""
    return float(np.degrees(sigma / (depth_error * K[0, 0])))


# --- absolute pose -----------------------------------------------------------------------------------------------
def solve_pnp_ransac(
    X: np.ndarray, x: np.ndarray, K: np.ndarray, seed: int = 0, max_error_px: float = 4.0, iterations: int = 200,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera pose T_cw from world points [N, 3] and their pixels [N, 2] (P3P RANSAC + inlier refinement)."""
    if len(X) < 6:
        return None
    cv2.setRNGSeed(seed)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        np.ascontiguousarray(X, np.float64), np.ascontiguousarray(x, np.float64), K, None,
        iterationsCount=iterations, reprojectionError=max_error_px, confidence=0.999, flags=cv2.SOLVEPNP_AP3P,
    )
    if not ok or inliers is None or len(inliers) < 6:
        return None
    mask = np.zeros(len(X), bool)
    mask[inliers.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(X[mask].astype(np.float64), x[mask].astype(np.float64), K, None, rvec, tvec)
    return pose_matrix(cv2.Rodrigues(rvec)[0], tvec), mask


# --- stereo ------------------------------------------------------------------------------------------------------
def fundamental_from_poses(K1, K2, T_21) -> np.ndarray:
    """F with x2^T F x1 = 0 for cameras related by T_21 (camera 1 -> camera 2)."""
    R, t = T_21[:3, :3], T_21[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K2).T @ tx @ R @ np.linalg.inv(K1)


def epipolar_mask(F, x1, x2, max_px: float) -> np.ndarray:
    """[N1, N2] bool: x2 lies within `max_px` pixels (image 2) of the epipolar line of x1. Lines are normalised
    first, so the dense part is one product and one comparison (8x faster than dividing the distance matrix)."""
    lines = np.c_[x1, np.ones(len(x1))] @ F.T
    lines /= np.maximum(np.linalg.norm(lines[:, :2], axis=1, keepdims=True), 1e-12)
    num = lines[:, :2] @ x2.T
    num += lines[:, 2:3]
    return np.abs(num, out=num) < max_px


# --- similarity / rigid alignment --------------------------------------------------------------------------------
def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> np.ndarray:
    """Least-squares S (4x4, sR|t) with dst ~ s R src + t (Umeyama 1991); rigid when with_scale is False.
    Batched: src, dst [..., N, 3] -> S [..., 4, 4]."""
    mu_s, mu_d = src.mean(-2), dst.mean(-2)
    a, b = src - mu_s[..., None, :], dst - mu_d[..., None, :]
    cov = np.swapaxes(b, -1, -2) @ a / src.shape[-2]
    U, D, Vt = np.linalg.svd(cov)
    S = np.broadcast_to(np.eye(3), cov.shape).copy()
    S[..., 2, 2] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)
    R = U @ S @ Vt
    var = np.mean(np.sum(a * a, -1), -1)
    trace = D[..., 0] + D[..., 1] + D[..., 2] * S[..., 2, 2]
    scale = np.where(var > 0, trace / np.where(var > 0, var, 1.0), 1.0) if with_scale else np.ones_like(var)
    T = np.broadcast_to(np.eye(4), (*cov.shape[:-2], 4, 4)).copy()
    T[..., :3, :3] = scale[..., None, None] * R
    T[..., :3, 3] = mu_d - (T[..., :3, :3] @ mu_s[..., None])[..., 0]
    return T


def sim3_ransac(
    P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray, K1: np.ndarray, K2: np.ndarray,
    with_scale: bool = True, seed: int = 0, iterations: int = 300, max_error_px: float = 3.0, min_inliers: int = 20,
) -> tuple[np.ndarray, np.ndarray] | None:
    """S12 (camera 2 -> camera 1 similarity) from 3D-3D matches P1[i] <-> P2[i] in each camera's frame.

    As in ORB-SLAM's Sim3Solver an inlier must reproject within `max_error_px` in both images: S12 P2 onto x1
    and S12^-1 P1 onto x2. Every hypothesis is fitted and scored at once (arrays, not a loop); the first with the
    most inliers wins and is refitted on all its inliers.
    """
    n = len(P1)
    if n < max(3, min_inliers):
        return None
    rng = np.random.default_rng(seed)

    def inliers(S):  # S [..., 4, 4] -> masks [..., n]
        A = S[..., :3, :3]
        u1, z1 = _pinhole(K1, P2 @ np.swapaxes(A, -1, -2) + S[..., None, :3, 3])
        A_inv = np.linalg.inv(A)
        t_inv = -(A_inv @ S[..., :3, 3, None])[..., 0]
        u2, z2 = _pinhole(K2, P1 @ np.swapaxes(A_inv, -1, -2) + t_inv[..., None, :])
        return (z1 > 0) & (z2 > 0) & (np.sum((u1 - x1) ** 2, -1) < max_error_px**2) & (
            np.sum((u2 - x2) ** 2, -1) < max_error_px**2)

    samples = np.array([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    hypotheses = umeyama(P2[samples], P1[samples], with_scale)
    finite = np.all(np.isfinite(hypotheses), axis=(1, 2))
    if not finite.any():
        return None
    counts = np.full(iterations, -1)
    counts[finite] = inliers(hypotheses[finite]).sum(1)
    best_S = hypotheses[int(np.argmax(counts))]
    best_mask = inliers(best_S)
    if best_mask.sum() < min_inliers:
        return None
    for _ in range(2):  # refit on inliers, re-classify
        S = umeyama(P2[best_mask], P1[best_mask], with_scale)
        mask = inliers(S)
        if mask.sum() < best_mask.sum():
            break
        best_mask, best_S = mask, S
    return best_S, best_mask
