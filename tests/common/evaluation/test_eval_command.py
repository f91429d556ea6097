"""``recslam eval`` on a result folder with a multi-robot EuRoC-layout ground truth."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from common.evaluation.alignment import AlignMode
from common.evaluation.errors import EvaluationError
from common.evaluation.metrics import AteConfig, compute_joint_ate
from common.evaluation.report import EvalConfig, evaluate_run
from common.evaluation.results import (
    load_groundtruth,
    read_result_trajectories,
    write_result_trajectories,
)
from common.evaluation.trajectory import Trajectory
from common.evaluation.tum import write_tum
from recslam.commands import evaluate

EUROC_GT_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
    "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], "
    "b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], "
    "b_a_RS_S_z [m s^-2]"
)


def _write_euroc_gt(path, traj: Trajectory) -> None:
    """A 17-column EuRoC ground-truth CSV (velocities and biases zero)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [EUROC_GT_HEADER]
    for t, p, q in zip(traj.timestamps_ns, traj.p_world_body, traj.q_wxyz, strict=True):
        rows.append(",".join([str(int(t)), *(repr(float(v)) for v in (*p, *q)), *["0"] * 9]))
    path.write_text("\n".join(rows) + "\n")


@pytest.fixture
def run_setup(tools, rng, tmp_path):
    """Dataset with agents A, B (EuRoC CSV) and C (TUM); estimates in one map frame."""
    R_map_world = tools.random_rotation(rng)
    t_map_world = rng.normal(size=3)
    dataset = tmp_path / "dataset"
    refs, ests = {}, {}
    for k, agent in enumerate(("A", "B", "C")):
        ref = tools.smooth(rng, n=400, t0_ns=tools.T0_NS + k * 2 * 10**9, name=agent)
        refs[agent] = ref
        if agent == "C":
            write_tum(dataset / "C.tum", ref)
        else:
            _write_euroc_gt(dataset / agent / "mav0/state_groundtruth_estimate0/data.csv", ref)
        sub = tools.perturbed(rng, ref.select(np.arange(0, len(ref), 10)), 0.01, 0.005)
        ests[agent] = sub.transformed(R_map_world, t_map_world)
    result = tmp_path / "run"
    write_result_trajectories(result, ests)
    return result, dataset, refs, ests


def _parse(argv):
    parser = argparse.ArgumentParser()
    evaluate.register(parser.add_subparsers())
    return parser.parse_args(argv)


def test_eval_command_writes_tables_json_and_plots(run_setup, capsys):
    result, dataset, refs, ests = run_setup
    args = _parse(["eval", str(result), "--groundtruth", str(dataset), "--align", "sim3"])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "| **joint** |" in out and "| B |" in out
    report = json.loads((result / "eval/ate.json").read_text())
    expected = compute_joint_ate(refs, ests, AteConfig(align=AlignMode.SIM3))
    assert report["align"] == "sim3"
    assert report["joint"]["agents"] == ["A", "B", "C"]
    assert report["joint"]["stats_m"]["rmse"] == pytest.approx(expected.stats.rmse, rel=1e-12)
    assert report["joint"]["stats_m"]["count"] == 120
    assert abs(report["joint"]["scale_error"]) < 0.01
    for agent in "ABC":
        block = report["agents"][agent]
        assert block["n_est"] == 40 and block["n_ref"] == 400 and block["n_matched"] == 40
        assert block["individual"]["stats_m"]["rmse"] < 0.03
        assert block["rpe"]["trans_stats_m"]["count"] > 0
    assert report["sources"]["A"].endswith("A/mav0/state_groundtruth_estimate0/data.csv")
    assert report["sources"]["C"].endswith("C.tum")
    md = (result / "eval/ate.md").read_text()
    assert md.count("\n| ") == 5  # header row, A, B, C, joint
    for name in ("trajectories_joint.png", "trajectories_individual.png", "ate_over_time.png"):
        data = (result / "eval" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_map_merge_error_shows_in_joint_only(run_setup, tmp_path):
    result, dataset, _, ests = run_setup
    broken = dict(ests)
    broken["B"] = ests["B"].transformed(np.eye(3), np.array([0.0, 1.0, 0.0]))
    write_result_trajectories(result, broken)
    report = evaluate_run(result, dataset, tmp_path / "out", EvalConfig(plots=False))
    assert report.joint.stats.rmse > 0.3
    assert max(r.stats.rmse for r in report.joint.individual.values()) < 0.03
    assert [f.name for f in report.files] == ["ate.json", "ate.md"]


def test_default_groundtruth_folder_and_single_file(tools, rng, tmp_path):
    ref = tools.smooth(rng, n=300, name="solo")
    est = ref.select(np.arange(0, 300, 5))
    result = tmp_path / "run"
    write_result_trajectories(result, {"solo": est})
    write_tum(result / "groundtruth" / "solo.tum", ref)
    rep = evaluate_run(result, None, None, EvalConfig(plots=False))
    assert rep.joint.stats.rmse < 1e-9
    assert rep.out_dir == result / "eval" and (result / "eval/ate.json").is_file()
    csv = tmp_path / "seq" / "mav0/state_groundtruth_estimate0/data.csv"
    _write_euroc_gt(csv, ref)
    refs, files = load_groundtruth(["solo"], tmp_path / "seq")
    assert files["solo"] == csv
    np.testing.assert_array_equal(refs["solo"].timestamps_ns, ref.timestamps_ns)
    refs, _ = load_groundtruth(["solo"], csv)
    np.testing.assert_allclose(refs["solo"].p_world_body, ref.p_world_body, rtol=1e-15)


def _fails(argv, match):
    """The handler raises an EvaluationError (``recslam`` turns it into exit code 2)."""
    args = _parse(argv)
    with pytest.raises(EvaluationError, match=match):
        args.func(args)


def test_cli_reports_missing_groundtruth_and_bad_folders(run_setup, tmp_path):
    result, dataset, _, _ = run_setup
    (dataset / "C.tum").unlink()
    _fails(["eval", str(result), "-g", str(dataset)], r"no ground truth for agent\(s\) \['C'\]")
    _fails(["eval", str(tmp_path / "nowhere")], "result folder does not exist")
    empty = tmp_path / "empty_run"
    (empty / "trajectories").mkdir(parents=True)
    _fails(["eval", str(empty)], r"no <agent>\.tum trajectory files")
    _fails(["eval", str(result)], "pass --groundtruth")
    single = tmp_path / "one.tum"
    write_tum(single, next(iter(read_result_trajectories(result).values())))
    _fails(["eval", str(result), "-g", str(single)], "holds one ground truth but the result has 3")
    _fails(["eval", str(result), "-g", str(dataset), "--n-align", "0"], "--n-align must be >= 1")


def test_cli_no_time_overlap_is_a_clear_error(run_setup):
    result, dataset, _, ests = run_setup
    late = ests["A"]
    shifted = Trajectory(late.timestamps_ns + 10**12, late.p_world_body, late.q_wxyz)
    write_tum(result / "trajectories" / "A.tum", shifted)
    _fails(["eval", str(result), "-g", str(dataset)], "found 0 matching timestamps")


@pytest.mark.parametrize("merged", [True, False], ids=["one-map", "not-merged"])
def test_cloud_report_has_a_joint_row_only_for_one_map(run_setup, merged, capsys):
    """The cloud's writer (trajectories, cloud_maps.json, report) and ``recslam eval`` on its
    folder: a joint ATE row only when every robot is in one map."""
    from services.cloud.store.output import OutputWriter

    result, dataset, _, ests = run_setup
    maps = {"A": 0, "B": 0, "C": 0} if merged else {"A": 0, "B": 3, "C": 3}
    OutputWriter(result, dataset).write(ests, maps)
    md = (result / "eval/ate.md").read_text()
    report = json.loads((result / "eval/ate.json").read_text())
    assert report["joint_frame"] is merged
    assert ("| **joint** |" in md) is merged
    assert ("Maps did not merge" in md) is not merged
    if not merged:
        assert "2 maps: map 0: A; map 3: B, C" in md
        assert md.count("\n| ") == 4  # header row, A, B, C: no joint row
    args = _parse(["eval", str(result), "--groundtruth", str(dataset), "--no-plots"])
    assert args.func(args) == 0
    assert ("| **joint** |" in capsys.readouterr().out) is merged
