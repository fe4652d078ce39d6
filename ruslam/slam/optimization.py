"""Optimisation as functions on arrays: motion-only pose, local bundle adjustment, SE3/Sim3 pose graph.

Local BA and the pose graphs are solved by gtsam (Levenberg-Marquardt, Huber kernel on projections). Motion-only
pose optimisation runs once or twice per frame on a 6-dof problem; in gtsam it costs ~25 ms per round for 400
points (one Python call per factor plus a fixed-point variable each) against <1 ms as a vectorised Gauss-Newton in
numpy, so it is written here with the same Huber kernel and ORB-SLAM's 4-round outlier classification; a test
checks it against gtsam on the same problem.

Conventions: poses in and out are 4x4 ``T_cw`` (world -> camera 0). gtsam variables are camera-to-world poses.
A stereo observation of the right camera is a projection factor whose ``body_P_sensor`` is ``T_c0_c1``.
Similarities are 4x4 ``[sR | t]`` acting as ``x -> s R x + t``; gtsam's Similarity3 acts as ``s (R x + t)``.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from ruslam.slam.geometry import CHI2_2DOF
from ruslam.slam.map import inverse_pose, orthonormalize

HUBER_DELTA = float(np.sqrt(CHI2_2DOF))


# --- small Lie helpers -------------------------------------------------------------------------------------------
def se3_exp(delta: np.ndarray) -> np.ndarray:
    """exp of a twist (omega, v) as a 4x4 matrix."""
    w, v = delta[:3], delta[3:]
    theta = np.linalg.norm(w)
    R = cv2.Rodrigues(w.reshape(3, 1))[0]
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * W
    else:
        V = np.eye(3) + (1 - np.cos(theta)) / theta**2 * W + (theta - np.sin(theta)) / theta**3 * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(T[:3, :3]), T[:3, 3])


def _sim3(S: np.ndarray) -> gtsam.Similarity3:
    s = float(np.cbrt(np.linalg.det(S[:3, :3])))
    return gtsam.Similarity3(gtsam.Rot3(S[:3, :3] / s), S[:3, 3] / s, s)


def _sim3_matrix(S: gtsam.Similarity3) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = S.scale() * S.rotation().matrix()
    out[:3, 3] = S.scale() * np.asarray(S.translation())
    return out


def _cal(K: np.ndarray) -> gtsam.Cal3_S2:
    return gtsam.Cal3_S2(K[0, 0], K[1, 1], K[0, 1], K[0, 2], K[1, 2])


# --- motion-only pose optimisation (numpy) -----------------------------------------------------------------------
def _residuals_jacobians(T_cw, X_w, uv, K, T_extra=None):
    """Reprojection residuals [N, 2] and their Jacobians [N, 2, 6] w.r.t. a left twist on T_cw."""
    Xc = X_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    A = np.broadcast_to(np.eye(3), (len(X_w), 3, 3))
    Xs = Xc
    if T_extra is not None:  # observation made by another camera of the rig: x_s = T_extra x_c
        Xs = Xc @ T_extra[:3, :3].T + T_extra[:3, 3]
        A = np.broadcast_to(T_extra[:3, :3], (len(X_w), 3, 3))
    x, y, z = Xs[:, 0], Xs[:, 1], np.maximum(Xs[:, 2], 1e-6)
    fx, fy = K[0, 0], K[1, 1]
    proj = np.stack([fx * x / z + K[0, 2], fy * y / z + K[1, 2]], 1)
    Jp = np.zeros((len(X_w), 2, 3))
    Jp[:, 0, 0], Jp[:, 0, 2] = fx / z, -fx * x / z**2
    Jp[:, 1, 1], Jp[:, 1, 2] = fy / z, -fy * y / z**2
    skew = np.zeros((len(X_w), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -Xc[:, 2], Xc[:, 1], -Xc[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = Xc[:, 2], -Xc[:, 1], Xc[:, 0]
    dX = np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], axis=2)  # d Xc / d twist
    J = Jp @ A @ dX
    return proj - uv, J, Xs[:, 2]


def optimize_pose(
    T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray, K: np.ndarray,
    uv_right: np.ndarray | None = None, K_right: np.ndarray | None = None, T_c1_c0: np.ndarray | None = None,
    rounds: int = 4, iterations: int = 10, chi2: float = CHI2_2DOF, sigma: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine a camera pose against fixed world points (Huber IRLS, ORB-SLAM's 4 rounds of outlier rejection).

    `uv_right` [N, 2] (NaN where absent) adds the right-camera observations of a stereo rig (`T_c1_c0` maps
    camera-0 coordinates to camera 1). `sigma` is the keypoint noise in pixels (the Huber width and the chi2
    test scale with it). Returns (T_cw, inlier mask [N]).
    """
    delta = HUBER_DELTA * sigma
    chi2 = chi2 * sigma**2
    T = T_cw.copy()
    n = len(X_w)
    inlier = np.ones(n, bool)
    has_right = np.zeros(n, bool) if uv_right is None else np.all(np.isfinite(uv_right), axis=1)
    if n < 3:
        return T, np.zeros(n, bool)
    for r in range(rounds):
        robust = r < rounds - 1
        for _ in range(iterations):
            res, J, z = _residuals_jacobians(T, X_w, uv, K)
            terms = [(res, J, inlier & (z > 0))]
            if has_right.any():
                rr, Jr, zr = _residuals_jacobians(T, X_w[has_right], uv_right[has_right], K_right, T_c1_c0)
                terms.append((rr, Jr, inlier[has_right] & (zr > 0)))
            H = np.zeros((6, 6))
            b = np.zeros(6)
            for e, Je, use in terms:
                err = np.linalg.norm(e, axis=1)
                w = np.where(err <= delta, 1.0, delta / np.maximum(err, 1e-12)) if robust else 1.0
                w = w * use
                H += np.einsum("n,nki,nkj->ij", w, Je, Je)
                b += np.einsum("n,nki,nk->i", w, Je, e)
            if np.linalg.matrix_rank(H) < 6:
                return T_cw.copy(), np.zeros(n, bool)
            step = -np.linalg.solve(H + 1e-6 * np.eye(6), b)
            T = se3_exp(step) @ T
            if np.linalg.norm(step) < 1e-7:
                break
        res, _, z = _residuals_jacobians(T, X_w, uv, K)
        e2 = np.sum(res**2, 1)
        if has_right.any():
            rr, _, zr = _residuals_jacobians(T, X_w[has_right], uv_right[has_right], K_right, T_c1_c0)
            e2[has_right] += np.sum(rr**2, 1)
        thresh = np.where(has_right, chi2 * 1.3, chi2)  # ORB-SLAM: 7.815 (3 dof) for stereo, 5.991 for mono
        inlier = (e2 < thresh) & (z > 0)
        if inlier.sum() < 3:
            break
    return orthonormalize(T), inlier


# --- local bundle adjustment (gtsam) -----------------------------------------------------------------------------
def bundle_adjustment(
    poses: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs_pose: np.ndarray, obs_point: np.ndarray,
    obs_uv: np.ndarray, K: np.ndarray, obs_right: np.ndarray | None = None, K_right: np.ndarray | None = None,
    T_c0_c1: np.ndarray | None = None, iterations: tuple[int, int] = (5, 10), chi2: float = CHI2_2DOF,
    sigma: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Huber-robust BA of keyframe poses T_cw [P, 4, 4] and points [M, 3] from observations [O] (gtsam LM).

    `fixed` [P] marks poses held constant (the keyframes that see local points from outside the local window).
    `obs_right` [O] marks observations made by the right camera of a stereo rig. As in ORB-SLAM: a first robust
    pass, then observations with chi2 > 5.991 or behind the camera are dropped and the rest is refined again.
    `sigma` is the keypoint noise in pixels. Returns (poses, points, inlier mask over observations).
    """
    chi2 = chi2 * sigma**2
    cal, cal_r = _cal(K), _cal(K_right) if K_right is not None else None
    body_r = _pose3(T_c0_c1) if T_c0_c1 is not None else None
    obs_right = np.zeros(len(obs_pose), bool) if obs_right is None else obs_right
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(HUBER_DELTA), gtsam.noiseModel.Isotropic.Sigma(2, sigma))
    inlier = np.ones(len(obs_pose), bool)
    values = gtsam.Values()
    for i, T in enumerate(poses):
        values.insert(X(i), _pose3(inverse_pose(T)))
    for j, p in enumerate(points):
        values.insert(L(j), np.asarray(p, float))
    if not np.any(fixed):  # gauge: hold the first pose
        fixed = fixed.copy()
        fixed[0] = True
    # Held poses/points get tight priors, not NonlinearEquality: gtsam eliminates constrained factors by QR, which
    # made this function 3.4x slower (bench/bundle_adjustment.py). Held poses are returned as given.
    hold6, hold3 = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
    factors = [
        gtsam.GenericProjectionFactorCal3_S2(obs_uv[o], noise, X(int(i)), L(int(j)), cal_r, body_r) if right
        else gtsam.GenericProjectionFactorCal3_S2(obs_uv[o], noise, X(int(i)), L(int(j)), cal)
        for o, (i, j, right) in enumerate(zip(obs_pose, obs_point, obs_right, strict=True))
    ]
    for stage, iters in enumerate(iterations):
        graph = gtsam.NonlinearFactorGraph()
        for i in np.nonzero(fixed)[0]:
            graph.add(gtsam.PriorFactorPose3(X(int(i)), values.atPose3(X(int(i))), hold6))
        for o in np.nonzero(inlier)[0]:
            graph.add(factors[o])
        counts = np.bincount(obs_point[inlier], minlength=len(points))
        for j in np.nonzero(counts < 2)[0]:  # a point left with < 2 measurements has no depth: hold it
            graph.add(gtsam.PriorFactorPoint3(L(int(j)), values.atPoint3(L(int(j))), hold3))
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(iters)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        if stage < len(iterations) - 1:
            inlier &= _observation_chi2(values, obs_pose, obs_point, obs_uv, obs_right, K, K_right, T_c0_c1) < chi2
    out_poses = np.stack([inverse_pose(values.atPose3(X(i)).matrix()) for i in range(len(poses))])
    out_poses[fixed] = poses[fixed]  # exactly as given (the priors let them move by ~1e-6)
    out_points = np.stack([values.atPoint3(L(j)) for j in range(len(points))]) if len(points) else points
    final = _observation_chi2(values, obs_pose, obs_point, obs_uv, obs_right, K, K_right, T_c0_c1) < chi2
    return out_poses, out_points, final


def _observation_chi2(values, obs_pose, obs_point, obs_uv, obs_right, K, K_right, T_c0_c1) -> np.ndarray:
    """Squared reprojection error of each observation (inf when behind the camera)."""
    n_pose = int(obs_pose.max()) + 1 if len(obs_pose) else 0
    T_cw = np.stack([inverse_pose(values.atPose3(X(i)).matrix()) for i in range(n_pose)]) if n_pose else None
    used = np.unique(obs_point)
    positions = np.zeros((int(used.max()) + 1 if len(used) else 0, 3))
    for j in used:
        positions[j] = values.atPoint3(L(int(j)))
    P = positions[obs_point]
    out = np.full(len(obs_pose), np.inf)
    if not len(obs_pose):
        return out
    T = T_cw[obs_pose]
    Xc = np.einsum("nij,nj->ni", T[:, :3, :3], P) + T[:, :3, 3]
    Kobs = np.broadcast_to(K, (len(P), 3, 3)).copy()
    if obs_right.any():
        T_c1_c0 = inverse_pose(T_c0_c1)
        Xc[obs_right] = Xc[obs_right] @ T_c1_c0[:3, :3].T + T_c1_c0[:3, 3]
        Kobs[obs_right] = K_right
    z = Xc[:, 2]
    ok = z > 1e-6
    uv = np.stack([Kobs[:, 0, 0] * Xc[:, 0] / np.where(ok, z, 1) + Kobs[:, 0, 2],
                   Kobs[:, 1, 1] * Xc[:, 1] / np.where(ok, z, 1) + Kobs[:, 1, 2]], 1)
    out[ok] = np.sum((uv - obs_uv) ** 2, 1)[ok]
    return out


# --- pose graphs (gtsam) -----------------------------------------------------------------------------------------
def pose_graph_optimization(
    poses: np.ndarray, edges: np.ndarray, relative: np.ndarray, fixed: list[int], similarity: bool,
    weights: np.ndarray | None = None, iterations: int = 20,
) -> np.ndarray:
    """Essential-graph optimisation: poses S_iw [P, 4, 4] (similarities when `similarity`), edges [E, 2] (i, j)
    with measured S_ij = S_iw S_jw^-1 [E, 4, 4]. Returns the corrected S_iw (Sim3 for monocular, SE3 for stereo).
    """
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    weights = np.ones(len(edges)) if weights is None else weights
    to_var = _sim3 if similarity else _pose3
    for i, S in enumerate(poses):
        values.insert(X(i), to_var(inverse_pose(S)))  # variable = S_wi
    dim = 7 if similarity else 6
    between = gtsam.BetweenFactorSimilarity3 if similarity else gtsam.BetweenFactorPose3
    equality = gtsam.NonlinearEqualitySimilarity3 if similarity else gtsam.NonlinearEqualityPose3
    for (i, j), S_ij, w in zip(edges, relative, weights, strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(dim, 1.0 / np.sqrt(w))
        graph.add(between(X(int(i)), X(int(j)), to_var(S_ij), noise))
    for i in fixed:
        graph.add(equality(X(int(i)), to_var(inverse_pose(poses[i]))))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    if similarity:
        return np.stack([inverse_pose(_sim3_matrix(result.atSimilarity3(X(i)))) for i in range(len(poses))])
    return np.stack([inverse_pose(result.atPose3(X(i)).matrix()) for i in range(len(poses))])
