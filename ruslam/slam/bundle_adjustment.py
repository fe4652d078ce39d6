"""Bundle adjustment as a function on arrays: keyframe poses and points from their observations.

Two solvers of the same problem (Huber kernel on projections, held keyframes, ORB-SLAM's two passes with the
chi2 > 5.991 observations dropped in between):

- ``schur`` (default, ``mapping.ba_solver``): gtsam's Levenberg-Marquardt in numpy on the reduced camera system
  (the points eliminated by the Schur complement, the 3x3 point blocks factored all at once): the same whitened
  Huber cost, lambda schedule, step acceptance (model fidelity), indeterminate-system test and termination, so it
  takes gtsam's steps. On the local BAs recorded from real runs (`bench/ba_regression.py`: TUM cabinet, the pool
  and desk sequences, robustness-grid variants) every problem ends within 1e-5 relative of gtsam's cost and 0.07 mm
  / 0.0001 deg of its poses, 2-3x faster; numpy releases the GIL while it runs.
- ``gtsam``: the graph in gtsam's Levenberg-Marquardt, eliminated points first (the Schur order), the reference;
  gtsam holds the GIL while it solves.

Poses in and out are 4x4 ``T_cw``; held poses come back exactly as given.
"""

from __future__ import annotations

import gtsam
import numpy as np
import scipy.linalg
from gtsam.symbol_shorthand import X

from ruslam.slam.geometry import CHI2_2DOF
from ruslam.slam.map import inverse_pose
from ruslam.slam.optimization import HUBER_DELTA, _cal, _pose3, camera_projection, pose_jacobian, se3_exp

SOLVERS = ("schur", "gtsam")


def bundle_adjustment(
    poses: np.ndarray, fixed: np.ndarray, points: np.ndarray, obs_pose: np.ndarray, obs_point: np.ndarray,
    obs_uv: np.ndarray, K: np.ndarray, obs_right: np.ndarray | None = None, K_right: np.ndarray | None = None,
    T_c0_c1: np.ndarray | None = None, iterations: tuple[int, int] = (5, 10), chi2: float = CHI2_2DOF,
    sigma: float = 1.0, solver: str = "gtsam", should_stop=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Huber-robust BA of keyframe poses T_cw [P, 4, 4] and points [M, 3] from observations [O].

    `fixed` [P] marks poses held constant (the keyframes that see local points from outside the local window; the
    first pose when none is). `obs_right` [O] marks observations made by the right camera of a stereo rig
    (`T_c0_c1`, `K_right`). A point left with fewer than two measurements in a pass has no depth and is held.
    `sigma` is the keypoint noise in pixels. `should_stop` (a callable, optional) is checked before each LM
    iteration: when it turns true the solve returns what it has and skips the second pass (ORB-SLAM's interrupted
    local BA; the threaded mode's solver child sets it when the tracker wants a keyframe). Returns (poses, points,
    inlier mask over observations).
    """
    if solver not in SOLVERS:
        raise ValueError(f"mapping.ba_solver must be one of {SOLVERS}, got {solver!r}.")
    fixed = np.asarray(fixed, bool).copy()
    if not fixed.any():  # gauge
        fixed[0] = True
    obs_right = np.zeros(len(obs_pose), bool) if obs_right is None else np.asarray(obs_right, bool)
    order = np.argsort(obs_pose, kind="stable")
    obs = (np.asarray(obs_pose, int)[order], np.asarray(obs_point, int)[order], np.asarray(obs_uv, float)[order],
           obs_right[order])
    solve = _schur_levenberg_marquardt if solver == "schur" else _gtsam_levenberg_marquardt
    chi2 = chi2 * sigma**2
    inlier = np.ones(len(obs_pose), bool)
    T, Xw = poses.copy(), np.asarray(points, float).copy()
    for stage, iters in enumerate(iterations):
        T, Xw = solve(T, fixed, Xw, obs, inlier, K, K_right, T_c0_c1, iters, sigma, should_stop)
        if should_stop is not None and should_stop():  # interrupted: no second pass (ORB-SLAM)
            break
        if stage < len(iterations) - 1:
            inlier &= observation_chi2(T, Xw, obs, K, K_right, T_c0_c1) < chi2
    T[fixed] = poses[fixed]
    if np.count_nonzero(fixed) == 1 and not obs_right.any():
        T, Xw = _keep_scale(poses, points, T, Xw, fixed)
    inlier = np.empty(len(order), bool)
    inlier[order] = observation_chi2(T, Xw, obs, K, K_right, T_c0_c1) < chi2
    return T, Xw, inlier


def _keep_scale(poses, points, T, Xw, fixed):
    """A monocular BA with one held pose leaves the scale free (the cost is invariant to scaling about that camera),
    and LM drifts along it (16x in one local BA of a young forward-moving map): the solution is scaled about the held
    camera so that the median free camera or point keeps its distance from it (far, uncertain points do not weigh
    more than near ones)."""
    centres = lambda P: -np.einsum("nji,nj->ni", P[:, :3, :3], P[:, :3, 3])  # noqa: E731
    anchor = centres(poses[fixed])[0]
    a = np.linalg.norm(np.concatenate([centres(T[~fixed]), Xw]) - anchor, axis=1)
    b = np.linalg.norm(np.concatenate([centres(poses[~fixed]), points]) - anchor, axis=1)
    s = float(np.median(b[a > 1e-12] / a[a > 1e-12])) if np.any(a > 1e-12) else 1.0
    if not np.isfinite(s) or s <= 0 or abs(s - 1.0) < 1e-12:
        return T, Xw
    T = T.copy()
    T[~fixed, :3, 3] = -np.einsum("nij,nj->ni", T[~fixed, :3, :3], anchor + s * (centres(T[~fixed]) - anchor))
    return T, anchor + s * (Xw - anchor)


def _linearize(T, Xw, obs, K, K_right=None, T_c0_c1=None, jacobians: bool = True):
    """Residuals [O, 2], Jacobians w.r.t. the pose twist [O, 2, 6] and the point [O, 2, 3], and depths [O], for
    observations sorted by pose (one matrix product per pose instead of per-row 3x3 products)."""
    oi, oj, uv, right = obs
    bounds = np.searchsorted(oi, np.arange(len(T) + 1))
    Xc = np.empty((len(oi), 3))
    for i in np.nonzero(np.diff(bounds))[0]:
        s = slice(bounds[i], bounds[i + 1])
        Xc[s] = Xw[oj[s]] @ T[i, :3, :3].T + T[i, :3, 3]
    pix, J, z = camera_projection(Xc, K, jacobians)
    if right.any():  # right-camera observations of a stereo rig
        T_c1_c0 = inverse_pose(T_c0_c1)
        pr, Jr, z[right] = camera_projection(Xc[right] @ T_c1_c0[:3, :3].T + T_c1_c0[:3, 3], K_right, jacobians)
        pix[right] = pr
        if jacobians:
            J[right] = Jr @ T_c1_c0[:3, :3]
    res = pix - uv
    if not jacobians:
        return res, None, None, z
    J_point = np.empty_like(J)
    for i in np.nonzero(np.diff(bounds))[0]:
        s = slice(bounds[i], bounds[i + 1])
        J_point[s] = J[s] @ T[i, :3, :3]
    return res, pose_jacobian(Xc, J), J_point, z


def observation_chi2(T, Xw, obs, K, K_right=None, T_c0_c1=None) -> np.ndarray:
    """Squared reprojection error (px^2) of each observation (sorted by pose); inf when behind the camera."""
    res, _, _, z = _linearize(T, Xw, obs, K, K_right, T_c0_c1, jacobians=False)
    return np.where(z > 1e-6, np.sum(res**2, 1), np.inf)


def robust_cost(T, Xw, obs, use, K, K_right=None, T_c0_c1=None, sigma: float = 1.0) -> float:
    """gtsam's error of the projection factors in `use` (observations sorted by pose): the Huber loss of each
    whitened reprojection error (pixels / sigma, width `HUBER_DELTA`), an observation behind its camera counted as
    gtsam's projection factor does (the error (2 fx, 2 fx))."""
    return float(np.sum(_huber_terms(T, Xw, obs, K, K_right, T_c0_c1, sigma, False)[0][use]))


def _huber_terms(T, Xw, obs, K, K_right, T_c0_c1, sigma, jacobians=True):
    """Per observation: Huber loss [O], whitened residual [O, 2], whitened Jacobians (pose [O, 2, 6], point
    [O, 2, 3]; zero behind the camera) and the Huber weight [O], as gtsam's robust projection factor linearises."""
    res, Jc, Jx, z = _linearize(T, Xw, obs, K, K_right, T_c0_c1, jacobians)
    behind = ~(z > 0)  # gtsam's cheirality test: the factor's error is (2 fx, 2 fx), its Jacobians zero
    if behind.any():
        fx = np.where(obs[3], K_right[0, 0] if K_right is not None else K[0, 0], K[0, 0])
        res[behind] = 2.0 * fx[behind, None]
    res = res / sigma
    err = np.linalg.norm(res, axis=1)
    loss = np.where(err <= HUBER_DELTA, 0.5 * err**2, HUBER_DELTA * (err - 0.5 * HUBER_DELTA))
    if not jacobians:
        return loss, res
    Jc, Jx = Jc / sigma, Jx / sigma
    Jc[behind], Jx[behind] = 0.0, 0.0
    w = np.where(err <= HUBER_DELTA, 1.0, HUBER_DELTA / np.maximum(err, 1e-300))
    return loss, res, Jc, Jx, w


def _schur_levenberg_marquardt(T, fixed, Xw, obs, use, K, K_right, T_c0_c1, iterations, sigma, should_stop=None):
    """gtsam's Levenberg-Marquardt (`LevenbergMarquardtOptimizer` with default parameters) over the observations
    in `use`, in numpy with the points eliminated by the Schur complement.

    As gtsam: the cost is the sum of Huber losses of the whitened errors; each iteration linearises once (Huber
    weights as gtsam's robust noise model reweights), then tries lambda * I (from 1e-5) until a step's model fidelity
    (cost decrease / decrease of the linearised cost) exceeds 1e-3: x10 on a failed try, /10 on success; it gives up
    at lambda >= 1e5 or when a step changes the cost by less than 1e-5 of it. `iterations` counts successful steps,
    and the pass ends when one lowers the cost by <= 1e-5 relative or absolute (gtsam's checkConvergence). Held
    poses and depth-less points are constants here (gtsam: tight priors, the same solution within 1e-9)."""
    oi, oj = obs[0], obs[1]
    M = len(Xw)
    slot = np.full(len(T), -1)
    slot[~fixed] = np.arange(int((~fixed).sum()))
    nf = int((~fixed).sum())
    movable = np.bincount(oj[use], minlength=M) >= 2  # others are held (no depth)
    pose_free = slot[oi] >= 0
    cx = np.nonzero(use & pose_free & movable[oj])[0]  # observations coupling a free pose and a free point
    cx = cx[np.argsort(oj[cx], kind="stable")]  # by point, for the chunks of the reduced system
    bounds = np.searchsorted(oi, np.arange(len(T) + 1))
    free_poses = np.nonzero(~fixed)[0]
    eye3, eye6 = np.eye(3), np.eye(6)

    cost = robust_cost(T, Xw, obs, use, K, K_right, T_c0_c1, sigma)
    lam = 1e-5  # lambdaInitial
    done = 0  # gtsam's iterations(): successful steps
    while done < iterations and cost > 0:
        if should_stop is not None and should_stop():
            break
        before = cost
        _, res, Jc, Jx, w = _huber_terms(T, Xw, obs, K, K_right, T_c0_c1, sigma)
        w = w * use
        old_linear = 0.5 * float(np.sum(w * np.sum(res**2, 1)))  # gtsam's linear.error(0) (reweighted)
        wJc, wJx = w[:, None, None] * Jc, w[:, None, None] * Jx
        Hcc, gc = np.zeros((nf, 6, 6)), np.zeros((nf, 6))
        for i in free_poses:  # one product per free pose
            sl = slice(bounds[i], bounds[i + 1])
            Hcc[slot[i]] = wJc[sl].reshape(-1, 6).T @ Jc[sl].reshape(-1, 6)
            gc[slot[i]] = wJc[sl].reshape(-1, 6).T @ res[sl].ravel()
        Hxx = _sum_blocks(_outer(wJx, Jx), oj, M)
        gx = np.where(movable[:, None], _sum_blocks(np.sum(wJx * res[:, :, None], 1), oj, M), 0.0)
        Hxc = _outer(wJx[cx], Jc[cx])  # [C, 3, 6]
        while True:  # gtsam's tryLambda until it returns true
            success = stop = False
            step = _damped_step(Hcc, gc, Hxx, gx, Hxc, cx, oj, slot, oi, movable, lam, nf, eye3, eye6)
            if step is not None:
                dc, dx = step
                dpose = np.zeros((len(T), 6))
                dpose[free_poses] = dc
                moved = np.einsum("oij,oj->oi", Jc, dpose[oi]) + np.einsum("oij,oj->oi", Jx, dx[oj])
                new_linear = 0.5 * float(np.sum(w * np.sum((res + moved) ** 2, 1)))
                linear_change = old_linear - new_linear
                if linear_change >= 0:
                    T_new = T.copy()
                    for i in free_poses:
                        T_new[i] = se3_exp(dpose[i]) @ T[i]
                    X_new = Xw + dx
                    new_cost = robust_cost(T_new, X_new, obs, use, K, K_right, T_c0_c1, sigma)
                    change = cost - new_cost
                    if linear_change > np.finfo(float).eps * old_linear:
                        success = change / linear_change > 1e-3  # minModelFidelity
                    stop = abs(change) < 1e-5 * cost  # relativeErrorTol: not worth larger lambdas
            if success:
                T, Xw, cost = T_new, X_new, new_cost
                lam /= 10
                done += 1
                break
            if stop:
                break
            lam *= 10
            if lam >= 1e5:  # lambdaUpperBound: gtsam gives up
                break
        decrease = before - cost
        if decrease <= 1e-5 or decrease / before <= 1e-5:  # checkConvergence (an unchanged cost included)
            break
    return T, Xw


def _damped_step(Hcc, gc, Hxx, gx, Hxc, cx, oj, slot, oi, movable, lam, nf, eye3, eye6):
    """The solution (pose steps [nf, 6], point steps [M, 3]) of (H + lam I) d = -g by the Schur complement, or
    None where gtsam's sequential Cholesky (points, then poses, one variable at a time) finds the damped system
    indeterminate: a block that is not positive definite, or whose factor's last two diagonal entries differ by 14
    binary orders of magnitude or more (`_determinate`), which makes gtsam count the try as failed."""
    M = len(Hxx)
    Hxx_d = Hxx + lam * eye3
    Hxx_d[~movable] = eye3
    try:
        L = np.linalg.cholesky(Hxx_d)
    except np.linalg.LinAlgError:
        return None
    if not _determinate(L[:, 1, 1], L[:, 2, 2]):
        return None
    Linv = np.linalg.inv(L)
    Hxx_inv = np.swapaxes(Linv, 1, 2) @ Linv
    dc = np.zeros((nf, 6))
    if nf:
        S, rhs = _reduced_camera_system(Hxc, oj[cx], slot[oi[cx]], Hxx_inv, gx, nf)
        S = -S
        for k in range(nf):
            S[6 * k:6 * k + 6, 6 * k:6 * k + 6] += Hcc[k] + lam * eye6
        try:
            Ls = np.linalg.cholesky(S)
        except np.linalg.LinAlgError:
            return None
        diag = np.diag(Ls).reshape(nf, 6)
        if not _determinate(diag[:, 4], diag[:, 5]):
            return None
        dc = scipy.linalg.cho_solve((Ls, True), rhs - gc.ravel(), check_finite=False).reshape(nf, 6)
    back = _sum_blocks(np.sum(Hxc * dc[slot[oi[cx]], None, :], 2), oj[cx], M)
    dx = -np.einsum("mij,mj->mi", Hxx_inv, gx + back)
    dx[~movable] = 0.0
    if not (np.all(np.isfinite(dc)) and np.all(np.isfinite(dx))):
        return None
    return dc, dx


def _determinate(second_last: np.ndarray, last: np.ndarray) -> bool:
    """gtsam's test on the Cholesky factor of each eliminated variable: the binary exponent of its second-last
    diagonal entry exceeds the last one's by less than 14 (gtsam's `choleskyPartial` names 12; 14 reproduces its
    decisions on every recorded local BA, 12 missed five: BENCHMARKS.md, `bench/ba_regression.py`)."""
    return bool(np.all(np.frexp(second_last)[1] - np.frexp(last)[1] < 14))


def _reduced_camera_system(Hxc, point, slot, Hxx_inv, gx, nf, max_elements: int = 2_000_000):
    """The Schur terms sum_j H_cj H_jj^-1 H_jc [6 nf, 6 nf] and sum_j H_cj H_jj^-1 g_j [6 nf] from the coupling
    blocks Hxc [C, 3, 6] (point x pose) of observations sorted by `point`, one dense [points, 3, 6 nf] chunk at a
    time (bounded memory for a global BA over many keyframes)."""
    S, rhs = np.zeros((6 * nf, 6 * nf)), np.zeros(6 * nf)
    chunk = max(1, max_elements // (18 * nf))
    for m0 in range(0, len(Hxx_inv), chunk):
        m1 = min(m0 + chunk, len(Hxx_inv))
        o0, o1 = np.searchsorted(point, [m0, m1])
        if o0 == o1:
            continue
        row = (point[o0:o1] - m0)[:, None, None] * 3 + np.arange(3)[None, :, None]
        flat = (row * nf + slot[o0:o1, None, None]) * 6 + np.arange(6)[None, None, :]
        B = np.bincount(flat.ravel(), Hxc[o0:o1].ravel(), (m1 - m0) * 18 * nf).reshape(m1 - m0, 3, 6 * nf)
        Y = (Hxx_inv[m0:m1] @ B).reshape(-1, 6 * nf)  # H_jj^-1 H_jc, stacked over points
        S += Y.T @ B.reshape(-1, 6 * nf)
        rhs += Y.T @ gx[m0:m1].ravel()
    return S, rhs


def _outer(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-row a_n^T b_n for a [N, 2, I], b [N, 2, J] -> [N, I, J] (broadcast products: faster than batched matmul
    on 2-row matrices)."""
    return np.sum(a[:, :, :, None] * b[:, :, None, :], axis=1)


def _sum_blocks(values: np.ndarray, index: np.ndarray, n: int) -> np.ndarray:
    """out[k] = sum of values[index == k] for blocks values [N, ...] (np.bincount per element)."""
    shape = values.shape[1:]
    size = int(np.prod(shape))
    flat = (index[:, None] * size + np.arange(size)).ravel()
    return np.bincount(flat, weights=values.reshape(len(values), size).ravel(), minlength=n * size).reshape(n, *shape)


def _gtsam_levenberg_marquardt(T, fixed, Xw, obs, use, K, K_right, T_c0_c1, iterations, sigma, should_stop=None):
    """The same pass as a gtsam factor graph (held poses and depth-less points as tight priors: gtsam eliminates
    NonlinearEquality's constrained noise model by QR, 3.4x slower, bench/bundle_adjustment.py).

    The projection factors are made in C++ (`utilities.insertProjectionFactors`, one call per run of a pose's
    observations, in the observations' order), 15k Python constructions per pass before. Its bindings pass the
    landmark keys as floats, so points are keyed by their plain index (exact below 2^53; a symbol key is not),
    which keeps gtsam's variable order: points before the poses' X keys, the elimination order given to it."""
    oi, oj, uv, right = obs
    cal, cal_r = _cal(K), _cal(K_right) if K_right is not None else None
    body_r = _pose3(T_c0_c1) if T_c0_c1 is not None else None
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(HUBER_DELTA), gtsam.noiseModel.Isotropic.Sigma(2, sigma))
    hold6, hold3 = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
    values = gtsam.Values()
    graph = gtsam.NonlinearFactorGraph()
    for i, Ti in enumerate(T):
        values.insert(X(i), _pose3(inverse_pose(Ti)))
        if fixed[i]:
            graph.add(gtsam.PriorFactorPose3(X(i), values.atPose3(X(i)), hold6))
    counts = np.bincount(oj[use], minlength=len(Xw))
    for j, p in enumerate(Xw):
        values.insert(j, p)
        if counts[j] < 2:
            graph.add(gtsam.PriorFactorPoint3(j, p, hold3))
    sel = np.nonzero(use)[0]
    runs = np.nonzero((np.diff(oi[sel]) != 0) | (np.diff(right[sel]) != 0))[0] + 1  # same pose and camera
    for run in np.split(sel, runs) if len(sel) else []:
        camera = (cal_r, body_r) if right[run[0]] else (cal,)
        gtsam.utilities.insertProjectionFactors(graph, X(int(oi[run[0]])), oj[run].astype(float),
                                                np.ascontiguousarray(uv[run].T), noise, *camera)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    # the points first, then the poses (the keys' order): the Schur complement's elimination, which gtsam's COLAMD
    # does not find by itself; sequential Cholesky on it is 1.3x faster per pass (BENCHMARKS.md)
    params.setOrdering(gtsam.Ordering(sorted(values.keys())))
    params.setLinearSolverType("SEQUENTIAL_CHOLESKY")
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    if should_stop is None:
        values = opt.optimize()
    else:  # one iteration at a time, with gtsam's own convergence test, so a stop request is seen between them
        while opt.iterations() < iterations and not should_stop():
            before = opt.error()
            opt.iterate()
            if gtsam.checkConvergence(params.getRelativeErrorTol(), params.getAbsoluteErrorTol(), params.getErrorTol(),
                                      before, opt.error()):
                break
        values = opt.values()
    rows = gtsam.utilities.extractPose3(values)  # [P, 12]: R row-major, then t (T_wc)
    T_wc = np.tile(np.eye(4), (len(T), 1, 1))
    T_wc[:, :3, :3], T_wc[:, :3, 3] = rows[:, :9].reshape(-1, 3, 3), rows[:, 9:]
    return np.stack([inverse_pose(t) for t in T_wc]), gtsam.utilities.extractPoint3(values) if len(Xw) else Xw
