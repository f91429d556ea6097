"""Motion-only tracking: the numpy-linearised optimiser against gtsam's projection factors."""

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from common.geometry import make_T, so3_exp
from services.edge.vio.state import PinholeUndistorter, project
from services.edge.vio.tracking import _optimise, track_frame
from services.edge.vio.types import TrackingConfig
from sim.vio import SimConfig, simulate

_UNIT_K = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)


def _scene(seed: int, n: int = 200):
    rng = np.random.default_rng(seed)
    camera = PinholeUndistorter(simulate(SimConfig(duration_s=0.2, seed=seed)).camera)
    T_true = make_T(so3_exp(rng.normal(0, 0.3, 3)), rng.normal(0, 0.5, 3))
    T_world_cam = T_true @ camera.T_body_cam
    p_cam = np.column_stack(
        [rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(2, 8, n)]
    )
    P = p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    sigma = np.full(n, 1.0 / camera.focal) * 1.2 ** rng.integers(0, 4, n)
    xy, _ = project(T_true, camera.T_body_cam, P)
    xy = xy + rng.normal(0, 1, (n, 2)) * sigma[:, None]
    xy[: n // 10] += rng.uniform(-40, 40, (n // 10, 2)) / camera.focal  # gross outliers
    return camera, T_true, P, xy, sigma


def _gtsam_reference(T0, P, xy, sigma, camera, options):
    """The textbook graph: pose + landmarks held by tight priors, Cauchy projection factors."""
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    values.insert(X(0), gtsam.Pose3(T0))
    cauchy = gtsam.noiseModel.mEstimator.Cauchy.Create(np.sqrt(options.chi2_threshold))
    tight3 = gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)
    body_P_cam = gtsam.Pose3(camera.T_body_cam)
    for i in range(len(P)):
        noise = gtsam.noiseModel.Robust.Create(
            cauchy, gtsam.noiseModel.Isotropic.Sigma(2, sigma[i])
        )
        values.insert(L(i), P[i])
        graph.add(gtsam.PriorFactorPoint3(L(i), P[i], tight3))
        graph.add(
            gtsam.GenericProjectionFactorCal3_S2(
                gtsam.Point2(*xy[i]), noise, X(0), L(i), _UNIT_K, body_P_cam
            )
        )
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(50)
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    return (
        gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize().atPose3(X(0)).matrix()
    )


def test_motion_only_optimum_matches_gtsam_projection_factors():
    options = TrackingConfig(max_iterations=30)
    for seed in range(3):
        camera, T_true, P, xy, sigma = _scene(seed)
        T0 = T_true @ make_T(so3_exp(np.array([0.02, -0.03, 0.01])), [0.05, -0.04, 0.03])
        T_ref = _gtsam_reference(T0, P, xy, sigma, camera, options)
        T_fast, v, bias = _optimise(T0, P, xy, sigma, camera, None, None, options)
        assert v is None and bias is None
        # Both converge to the same optimum (0.1 mm, 1e-4 rad).
        assert np.linalg.norm(T_fast[:3, 3] - T_ref[:3, 3]) < 1e-4
        assert np.linalg.norm(T_fast[:3, :3] - T_ref[:3, :3]) < 1e-4
        assert np.linalg.norm(T_fast[:3, 3] - T_true[:3, 3]) < 0.02  # and it is the right pose


def test_track_frame_recovers_pose_and_rejects_outliers():
    camera, T_true, P, xy, sigma = _scene(7)
    ids = np.arange(len(P))
    T_pred = T_true @ make_T(so3_exp(np.array([0.05, 0.0, -0.04])), [0.2, 0.1, -0.1])
    result, reason = track_frame(P, xy, sigma, ids, camera, TrackingConfig(), T_pred)
    assert result is not None, reason
    assert np.linalg.norm(result.T_world_body[:3, 3] - T_true[:3, 3]) < 0.02
    outliers = set(range(len(P) // 10))
    assert len(outliers & set(result.inlier_ids.tolist())) <= 2
    assert len(result.inlier_ids) > 0.8 * len(P)
