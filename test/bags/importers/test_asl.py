"""ASL import of a folder written from a rendered scenario: ground truth, calibration, eval."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bags.cli.importers.asl import read_asl
from bags.cli.importers.cli import main
from bags.cli.importers.common import ImportOptions, write_dataset
from bags.io import BagReader
from owl_core.geometry import quat_xyzw_to_matrix


def _by_stamp(bag_path: Path, topic: str) -> dict[int, Any]:
    with BagReader(bag_path) as bag:
        out = {}
        for raw in bag.messages([topic]):
            msg = bag.deserialize(raw)
            out[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = msg
        return out


@pytest.fixture(scope="module")
def asl_bag(asl_folder: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("asl_bag") / "bag"
    write_dataset(read_asl(asl_folder.root), out, ImportOptions())
    return out


def test_twist_matches_the_renderer_within_the_differentiation_error(
    asl_folder: Any, asl_bag: Path, bound: Any
) -> None:
    sim = asl_folder.sim
    twists = _by_stamp(asl_bag, "/ground_truth/twist")
    # every image lies inside the 200 Hz ground truth (it starts 50 ms before the first)
    assert sorted(twists) == [int(s) for s in asl_folder.stamps_ns]
    lin_bound, ang_bound = bound(sim, asl_folder.gt_spacing_s, True)
    lin_err, ang_err = [], []
    for ns, msg in twists.items():
        v, w = sim.twist(sim.time_of(ns))
        tw = msg.twist
        lin_err.append(
            np.linalg.norm([tw.linear.x - v[0], tw.linear.y - v[1], tw.linear.z - v[2]])
        )
        ang_err.append(
            np.linalg.norm([tw.angular.x - w[0], tw.angular.y - w[1], tw.angular.z - w[2]])
        )
    assert max(lin_err) <= lin_bound, (max(lin_err), lin_bound)
    assert max(ang_err) <= ang_bound, (max(ang_err), ang_bound)
    assert ang_bound < 1e-3  # the bound itself is small: 200 Hz poses


def test_bias_calibration_and_extrinsic(asl_folder: Any, asl_bag: Path) -> None:
    sim = asl_folder.sim
    biases = _by_stamp(asl_bag, "/ground_truth/gyro_bias")
    assert len(biases) == asl_folder.stamps_ns.size
    for msg in biases.values():
        assert msg.header.frame_id == "imu_link"
        assert [msg.vector.x, msg.vector.y, msg.vector.z] == pytest.approx(
            asl_folder.bias, abs=1e-12
        )
    info = next(iter(_by_stamp(asl_bag, "/camera/camera_info").values()))
    assert info.distortion_model == "plumb_bob"
    assert list(info.d) == pytest.approx([*sim.camera.D[:4], 0.0], abs=1e-15)
    assert np.asarray(info.k).reshape(3, 3) == pytest.approx(sim.camera.K, abs=1e-12)
    with BagReader(asl_bag) as bag:
        (raw,) = list(bag.messages(["/tf_static"]))
        (tf,) = bag.deserialize(raw).transforms
        assert bag.topics["/imu/data"].count > 0
        assert bag.topics["/camera/image_raw"].qos_kind == "sensor"
        assert bag.topics["/tf_static"].qos_kind == "latched"
    assert (tf.header.frame_id, tf.child_frame_id) == ("imu_link", "camera_optical_frame")
    q = tf.transform.rotation
    assert quat_xyzw_to_matrix([q.x, q.y, q.z, q.w]) == pytest.approx(sim.R_bc, abs=1e-9)
    tr = tf.transform.translation
    assert [tr.x, tr.y, tr.z] == pytest.approx([0.05, -0.02, 0.01], abs=1e-12)


def test_equidistant_sensor_yaml_becomes_equidistant(asl_folder: Any, tmp_path: Path) -> None:
    import shutil

    root = tmp_path / "equi"
    shutil.copytree(asl_folder.root, root)
    yaml = root / "mav0" / "cam0" / "sensor.yaml"
    text = yaml.read_text().replace("radial-tangential", "equidistant")
    yaml.write_text(text)
    ds = read_asl(root)
    assert ds.camera.distortion_model == "equidistant"
    assert ds.camera.D == pytest.approx(asl_folder.sim.camera.D[:4])


def test_process_and_eval_on_the_import(
    asl_folder: Any, asl_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from owl_ros.process import ProcessOptions, process_bag
    from owl_ros.tools.evaluate import evaluate

    out = tmp_path / "result"
    summary = process_bag(asl_bag, out, ProcessOptions())
    assert summary.extrinsic_source == "tf_static"
    ev = evaluate(out, asl_bag)
    s = ev.summary
    assert s["frames"] == 21 and s["heading_frames"] >= 10
    assert s["heading_deg_median"] < 5.0  # scored against the imported twist
    assert s["range_scored"] is False and s["range_rel_median"] is None
    assert any("not scored: no range ground truth" in n for n in ev.notes)
    assert s["bias_scored"] is True
    assert s["truth_gyro_bias_rad_s"] == pytest.approx(asl_folder.bias)
    assert s["bias_error_final_rad_s"] is not None
    from owl_ros.tools.evaluate import main as eval_main

    assert eval_main([str(out), "--truth", str(asl_bag)]) == 0
    text = capsys.readouterr().out
    assert "not scored: no range ground truth" in text


def test_cli_prints_the_rotation_line(
    asl_folder: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "bag"
    assert main([str(asl_folder.root), str(out), "--seconds", "0.5", "--every", "2"]) == 0
    said = capsys.readouterr()
    line = said.out.strip()
    assert line.startswith("camera_to_imu_rotation_xyzw: [")
    q = [float(v) for v in line.split("[")[1].rstrip("]").split(",")]
    assert quat_xyzw_to_matrix(q) == pytest.approx(asl_folder.sim.R_bc, abs=1e-8)
    # and ready to paste for a live node (progress and hints on stderr)
    paste = said.err.split('-p "camera_to_imu_rotation_xyzw:=[')[1].split("]")[0]
    assert [float(v) for v in paste.split(",")] == pytest.approx(q, abs=1e-9)
    with BagReader(out) as bag:
        assert bag.topics["/camera/image_raw"].count == 6  # 0, 0.1, ... 0.5 s


def test_tum_vi_mocap_poses_are_differentiated(
    asl_folder: Any, tmp_path: Path, bound: Any
) -> None:
    """TUM-VI: mocap0 poses only (no velocity, no bias): velocity from the 3-point rule."""
    import shutil

    from bags.cli.importers.common import read_yaml, transform
    from owl_core.geometry import matrix_to_quat_xyzw

    sim = asl_folder.sim
    root = tmp_path / "tumvi"
    shutil.copytree(asl_folder.root, root)
    shutil.rmtree(root / "mav0" / "state_groundtruth_estimate0")
    _, lever = transform(read_yaml(root / "mav0" / "cam0" / "sensor.yaml")["T_BS"], root)
    h = 1.0 / 120.0
    t = np.arange(-0.05 + 0.0021, sim.options.seconds + 0.05, h)
    st = sim.trajectory.state(t)
    p_wb = st.position - np.einsum("kij,j->ki", st.R_wb, lever)
    q = matrix_to_quat_xyzw(st.R_wb)
    (root / "mav0" / "mocap0").mkdir()
    rows = ["#timestamp [ns],p_RS_R_x,p_RS_R_y,p_RS_R_z,q_RS_w,q_RS_x,q_RS_y,q_RS_z"]
    for i, ti in enumerate(t):
        vals = (*p_wb[i], q[i, 3], q[i, 0], q[i, 1], q[i, 2])
        stamp = int(sim.options.start_ns) + round(ti * 1e9)
        rows.append(f"{stamp}," + ",".join(f"{v:.17g}" for v in vals))
    (root / "mav0" / "mocap0" / "data.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "bag"
    write_dataset(read_asl(root), out, ImportOptions())
    twists = _by_stamp(out, "/ground_truth/twist")
    assert len(twists) == asl_folder.stamps_ns.size
    with BagReader(out) as bag:
        assert "/ground_truth/gyro_bias" not in bag.topics
    lin_bound, ang_bound = bound(sim, h, True)
    for ns, msg in twists.items():
        v, w = sim.twist(sim.time_of(ns))
        tw = msg.twist
        lin = np.array([tw.linear.x, tw.linear.y, tw.linear.z])
        ang = np.array([tw.angular.x, tw.angular.y, tw.angular.z])
        assert np.linalg.norm(lin - v) <= lin_bound + 1e-9
        assert np.linalg.norm(ang - w) <= ang_bound + 1e-9


def test_scale_resizes_images_and_adjusts_the_intrinsics(asl_folder: Any, tmp_path: Path) -> None:
    out = tmp_path / "half"
    assert main([str(asl_folder.root), str(out), "--scale", "0.5", "--seconds", "0.2", "-q"]) == 0
    k = asl_folder.sim.camera.K
    with BagReader(out) as bag:
        info = bag.deserialize(next(iter(bag.messages(["/camera/camera_info"]))))
        img = bag.deserialize(next(iter(bag.messages(["/camera/image_raw"]))))
    assert (img.width, img.height, info.width, info.height) == (160, 120, 160, 120)
    k2 = np.asarray(info.k).reshape(3, 3)
    assert k2[0, 0] == pytest.approx(0.5 * k[0, 0]) and k2[1, 1] == pytest.approx(0.5 * k[1, 1])
    # pixel centres: u' = (u + 0.5) s - 0.5
    assert k2[0, 2] == pytest.approx((k[0, 2] + 0.5) * 0.5 - 0.5)
    assert k2[1, 2] == pytest.approx((k[1, 2] + 0.5) * 0.5 - 0.5)
    assert list(info.d) == pytest.approx([*asl_folder.sim.camera.D[:4], 0.0])
