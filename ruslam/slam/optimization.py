"""Optimisation as functions on arrays: reprojection Jacobians, motion-only pose, SE3/Sim3 pose graph.

The pose graphs are solved by gtsam (Levenberg-Marquardt); bundle adjustment is `ruslam.slam.bundle_adjustment`.
Motion-only pose optimisation runs once or twice per frame on a 6-dof problem; in gtsam it costs ~25 ms per round
for 400 points (one Python call per factor plus a fixed-point variable each) against <1 ms as a vectorised
Gauss-Newton in numpy, so it is written here with the same Huber kernel and ORB-SLAM's 4-round outlier
classification; a test checks it against gtsam on the same problem.

Conventions: poses in and out are 4x4 ``T_cw`` (world -> camera 0). gtsam variables are camera-to-world poses.
Similarities are 4x4 ``[sR | t]`` acting as ``x -> s R x + t``; gtsam's Similarity3 acts as ``s (R x + t)``.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from ruslam.slam.geometry import CHI2_1DOF, CHI2_2DOF, fundamental_from_poses
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
def camera_projection(Xc: np.ndarray, K: np.ndarray, jacobians: bool = True):
    """Pixels [N, 2] of camera points Xc [N, 3], their Jacobian w.r.t. Xc [N, 2, 3] (or None), and the depths."""
    x, y, z = Xc[:, 0], Xc[:, 1], np.maximum(Xc[:, 2], 1e-6)
    fx, fy = K[0, 0], K[1, 1]
    pix = np.stack([fx * x / z + K[0, 2], fy * y / z + K[1, 2]], 1)
    if not jacobians:
        return pix, None, Xc[:, 2]
    J = np.zeros((len(Xc), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * x / z**2
    J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * y / z**2
    return pix, J, Xc[:, 2]


def pose_jacobian(Xc: np.ndarray, J_cam: np.ndarray) -> np.ndarray:
    """d pixel / d left twist on T_cw [N, 2, 6] from d pixel / d Xc: d Xc / d twist = [-[Xc]x | I], and
    a^T [Xc]x = (a x Xc)^T."""
    return np.concatenate([np.cross(Xc[:, None, :], J_cam), J_cam], axis=2)


def reprojection(T_cw, X_w, uv, K, T_extra=None, jacobians: bool = True):
    """Residuals [N, 2] of world points seen from one pose, their Jacobian w.r.t. a left twist on T_cw [N, 2, 6]
    (or None) and the depths. `T_extra` maps camera-0 points into the observing camera of a rig."""
    Xc = X_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    Xs = Xc if T_extra is None else Xc @ T_extra[:3, :3].T + T_extra[:3, 3]
    pix, J, z = camera_projection(Xs, K, jacobians)
    if J is not None and T_extra is not None:
        J = J @ T_extra[:3, :3]
    return pix - uv, None if J is None else pose_jacobian(Xc, J), z


def _skew(v: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] cross-product matrices."""
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def _sampson(F: np.ndarray, h1: np.ndarray, h2: np.ndarray):
    """Sampson distances [N] of homogeneous pixels h1 <-> h2 [3, N] under F, with the epipolar lines in image 1 and
    image 2 [3, N] and the denominator (for the Jacobian)."""
    l2, l1 = F @ h1, F.T @ h2
    denominator = np.sqrt(l2[0] ** 2 + l2[1] ** 2 + l1[0] ** 2 + l1[1] ** 2 + 1e-300)
    return (l2[0] * h2[0] + l2[1] * h2[1] + l2[2]) / denominator, l1, l2, denominator


def _homogeneous(x: np.ndarray) -> np.ndarray:
    return np.vstack([np.asarray(x, np.float64).T, np.ones(len(x))])


def sampson(T_21: np.ndarray, x1: np.ndarray, x2: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Signed Sampson distances [N] (px) of matches x1 <-> x2 to the epipolar geometry of the relative pose T_21
    (camera 1 -> camera 2, both with K); independent of the translation's length."""
    return _sampson(fundamental_from_poses(K, K, T_21), _homogeneous(x1), _homogeneous(x2))[0]


def _epipolar_terms(T_cw, epipolar, K):
    """Sampson residuals [N, 1] of `epipolar` = (T_cw of an earlier view, its pixels, this view's pixels, each match's
    noise in units of sigma), divided by that noise, and their Jacobian w.r.t. a left twist (omega, v) on T_cw [N, 1,
    6]: the relative pose moves the same way, R -> (I + [omega]x) R and t -> t + omega x t + v, so E = [t]x R moves by
    [omega x t]x R + [t]x [omega]x R and by [v]x R."""
    T_prev, x1, x2, noise = epipolar
    T_rel = T_cw @ inverse_pose(T_prev)
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    if not np.linalg.norm(t) > 0:  # no translation, no epipolar geometry (the last pose as a start)
        return np.zeros((len(x1), 1)), np.zeros((len(x1), 1, 6))
    K_inv = np.linalg.inv(K)
    h1, h2 = _homogeneous(x1), _homogeneous(x2)
    e, l1, l2, denominator = _sampson(fundamental_from_poses(K, K, T_rel), h1, h2)
    axes = _skew(np.eye(3))
    dE = np.concatenate([_skew(np.cross(np.eye(3), t)) @ R + _skew(t) @ axes @ R, axes @ R])  # [6, 3, 3]
    dF = K_inv.T @ dE @ K_inv
    dl2, dl1 = dF @ h1, np.swapaxes(dF, 1, 2) @ h2  # [6, 3, N]: the lines' derivatives
    d_numerator = dl2[:, 0] * h2[0] + dl2[:, 1] * h2[1] + dl2[:, 2]
    d_squares = 2 * (l2[0] * dl2[:, 0] + l2[1] * dl2[:, 1] + l1[0] * dl1[:, 0] + l1[1] * dl1[:, 1])
    J = d_numerator / denominator - e * d_squares / (2 * denominator**2)
    return (e / noise)[:, None], (J.T / noise[:, None])[:, None, :]


def optimize_pose(
    T_cw: np.ndarray, X_w: np.ndarray, uv: np.ndarray, K: np.ndarray,
    uv_right: np.ndarray | None = None, K_right: np.ndarray | None = None, T_c1_c0: np.ndarray | None = None,
    rounds: int = 4, iterations: int = 10, chi2: float = CHI2_2DOF, sigma: float = 1.0,
    epipolar: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine a camera pose against fixed world points (Huber IRLS, ORB-SLAM's 4 rounds of outlier rejection).

    `uv_right` [N, 2] (NaN where absent) adds the right-camera observations of a stereo rig (`T_c1_c0` maps
    camera-0 coordinates to camera 1). `epipolar` = (T_cw of an earlier view, pixels there, pixels here, each match's
    noise in units of sigma: a pyramid's scale) adds matches to that view by their Sampson distance (chi2 with 1 dof):
    two-view constraints on the rotation and the translation's direction. `sigma` is the keypoint noise in pixels (the
    Huber width and the chi2 test scale with it). Returns (T_cw, inlier mask [N] of the world points).
    """
    delta = HUBER_DELTA * sigma
    chi2 = chi2 * sigma**2
    T = T_cw.copy()
    n = len(X_w)
    inlier = np.ones(n, bool)
    has_right = np.zeros(n, bool) if uv_right is None else np.all(np.isfinite(uv_right), axis=1)
    if n < 3:
        return T, np.zeros(n, bool)
    epipolar_inlier = None if epipolar is None else np.ones(len(epipolar[1]), bool)
    for r in range(rounds):
        robust = r < rounds - 1
        for _ in range(iterations):
            res, J, z = reprojection(T, X_w, uv, K)
            terms = [(res, J, inlier & (z > 0), delta)]
            if has_right.any():
                rr, Jr, zr = reprojection(T, X_w[has_right], uv_right[has_right], K_right, T_c1_c0)
                terms.append((rr, Jr, inlier[has_right] & (zr > 0), delta))
            if epipolar is not None:
                terms.append((*_epipolar_terms(T, epipolar, K), epipolar_inlier, np.sqrt(CHI2_1DOF) * sigma))
            H = np.zeros((6, 6))
            b = np.zeros(6)
            for e, Je, use, huber in terms:
                err = np.linalg.norm(e, axis=1)
                w = np.where(err <= huber, 1.0, huber / np.maximum(err, 1e-12)) if robust else 1.0
                wJ = (w * use)[:, None, None] * Je
                H += wJ.reshape(-1, 6).T @ Je.reshape(-1, 6)
                b += wJ.reshape(-1, 6).T @ e.ravel()
            if np.linalg.matrix_rank(H) < 6:
                return T_cw.copy(), np.zeros(n, bool)
            step = -np.linalg.solve(H + 1e-6 * np.eye(6), b)
            T = se3_exp(step) @ T
            if np.linalg.norm(step) < 1e-7:
                break
        res, _, z = reprojection(T, X_w, uv, K, jacobians=False)
        e2 = np.sum(res**2, 1)
        if has_right.any():
            rr, _, zr = reprojection(T, X_w[has_right], uv_right[has_right], K_right, T_c1_c0,
                                            jacobians=False)
            e2[has_right] += np.sum(rr**2, 1)
        thresh = np.where(has_right, chi2 * 1.3, chi2)  # ORB-SLAM: 7.815 (3 dof) for stereo, 5.991 for mono
        inlier = (e2 < thresh) & (z > 0)
        if epipolar is not None:
            e = sampson(T @ inverse_pose(epipolar[0]), *epipolar[1:3], K) / epipolar[3]
            epipolar_inlier = e**2 < CHI2_1DOF * sigma**2
        if inlier.sum() < 3:
            break
    return orthonormalize(T), inlier


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
    prior = gtsam.PriorFactorSimilarity3 if similarity else gtsam.PriorFactorPose3
    hold = gtsam.noiseModel.Isotropic.Sigma(dim, 1e-6)  # a tight prior: NonlinearEquality's constrained noise model
    # is eliminated by QR, 58 s against 0.16 s for one solve of a 243-keyframe graph with 16,020 edges
    for (i, j), S_ij, w in zip(edges, relative, weights, strict=True):
        noise = gtsam.noiseModel.Isotropic.Sigma(dim, 1.0 / np.sqrt(w))
        graph.add(between(X(int(i)), X(int(j)), to_var(S_ij), noise))
    for i in fixed:
        graph.add(prior(X(int(i)), to_var(inverse_pose(poses[i])), hold))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    if similarity:
        return np.stack([inverse_pose(_sim3_matrix(result.atSimilarity3(X(i)))) for i in range(len(poses))])
    return np.stack([inverse_pose(result.atPose3(X(i)).matrix()) for i in range(len(poses))])
