"""KITTI odometry import of a folder written from a rendered scenario."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bags.cli.importers.common import ImportOptions, write_dataset
from bags.cli.importers.kitti import read_kitti
from bags.io import BagReader


@pytest.fixture(scope="module")
def kitti_bag(kitti_folder: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("kitti_bag") / "bag"
    q = kitti_folder.sim.camera_to_imu_xyzw
    write_dataset(read_kitti(kitti_folder.root, camera_to_imu_xyzw=q), out, ImportOptions())
    return out


def test_twist_from_10_hz_poses_matches_the_renderer(
    kitti_folder: Any, kitti_bag: Path, bound: Any
) -> None:
    sim = kitti_folder.sim
    t0 = int(sim.frame_stamps_ns[0])
    with BagReader(kitti_bag) as bag:
        twists = [bag.deserialize(r) for r in bag.messages(["/ground_truth/twist"])]
        assert bag.topics["/camera/image_raw"].count == kitti_folder.stamps_ns.size
    # interior poses only: the first and last image have one neighbour
    assert len(twists) == kitti_folder.stamps_ns.size - 2
    lin_bound, ang_bound = bound(sim, kitti_folder.gt_spacing_s, False)
    lin_err, ang_err = [], []
    for msg in twists:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        v, w = sim.twist(sim.time_of(ns + t0))
        tw = msg.twist
        lin_err.append(np.linalg.norm(np.array([tw.linear.x, tw.linear.y, tw.linear.z]) - v))
        ang_err.append(np.linalg.norm(np.array([tw.angular.x, tw.angular.y, tw.angular.z]) - w))
    assert max(lin_err) <= lin_bound + 1e-6, (max(lin_err), lin_bound)  # poses: 13 digits
    assert max(ang_err) <= ang_bound + 1e-6, (max(ang_err), ang_bound)
    assert ang_bound < 0.03  # 10 Hz: h^2/6 |w''| of the street's yaw and pitch


def test_calibration_times_and_imu(kitti_folder: Any, kitti_bag: Path) -> None:
    sim = kitti_folder.sim
    with BagReader(kitti_bag) as bag:
        info = bag.deserialize(next(iter(bag.messages(["/camera/camera_info"]))))
        stamps = [
            bag.deserialize(r).header.stamp.nanosec for r in bag.messages(["/camera/image_raw"])
        ]
        imu = bag.topics["/imu/data"].count
    assert np.asarray(info.k).reshape(3, 3) == pytest.approx(sim.camera.K, abs=1e-9)
    assert not np.any(info.d)
    assert stamps[:3] == [0, 100_000_000, 200_000_000]
    assert imu >= 400 * 1.4  # the IMU CSV from 0 s on (samples before 0 dropped)


def test_process_and_eval_on_the_import(kitti_bag: Path, tmp_path: Path) -> None:
    from owl_ros.process import ProcessOptions, process_bag
    from owl_ros.tools.evaluate import evaluate

    out = tmp_path / "result"
    process_bag(kitti_bag, out, ProcessOptions())
    ev = evaluate(out, kitti_bag)
    s = ev.summary
    assert s["frames"] == 14 and s["heading_frames"] >= 5
    assert s["heading_deg_median"] < 5.0
    assert s["range_scored"] is False and s["bias_scored"] is False
    assert s["bias_error_final_rad_s"] is None
    assert any("bias error not scored" in n for n in ev.notes)


def test_colour_folder_uses_p2_and_its_baseline(kitti_folder: Any, tmp_path: Path) -> None:
    import shutil

    import cv2

    root = tmp_path / "00"
    shutil.copytree(kitti_folder.root, root)
    (root / "image_0").rename(root / "image_2")
    for png in (root / "image_2").iterdir():  # a colour image, as KITTI's image_2
        grey = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(png), cv2.merge([grey, grey, grey]))
    k = kitti_folder.sim.camera.K
    lines = (root / "calib.txt").read_text().splitlines()
    p2 = np.c_[k, k @ np.array([0.06, 0.0, 0.0])]  # camera 2 sits 6 cm to the left of 0
    lines[2] = "P2: " + " ".join(f"{v:.12e}" for v in p2.ravel())
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    ds = read_kitti(root, colour=True)
    assert ds.t_xc == pytest.approx([-0.06, 0.0, 0.0])
    out = tmp_path / "bag"
    write_dataset(ds, out, ImportOptions(seconds=0.3))
    with BagReader(out) as bag:
        img = bag.deserialize(next(iter(bag.messages(["/camera/image_raw"]))))
    assert img.encoding == "mono8" and (img.width, img.height) == (320, 240)
