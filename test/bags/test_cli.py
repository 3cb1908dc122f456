"""bags.cli: negative number lists as option values, the shared one-line parser."""

from __future__ import annotations

import pytest

from bags.cli import OneLineErrorParser, make_bag
from owl_ros import process


def test_negative_number_lists_are_option_values() -> None:
    p = OneLineErrorParser(prog="t")
    p.add_argument("--v")
    p.add_argument("-p", action="append", default=[])
    p.add_argument("pos", nargs="?")
    args = p.parse_args(["--v", "-0.5,0.5,-1e-3,.5", "-p", "a:=-1", "x"])
    assert (args.v, args.p, args.pos) == ("-0.5,0.5,-1e-3,.5", ["a:=-1"], "x")
    assert p.parse_args(["--v=-0.5,1"]).v == "-0.5,1"  # the = form still works
    assert p.parse_args(["--", "-1"]).pos == "-1"  # after --: a positional


def test_readme_extrinsic_and_make_bag_vectors_parse() -> None:
    args = process.build_parser().parse_args(
        ["in", "-o", "out", "--camera-to-imu-rotation-xyzw", "-0.5,0.5,-0.5,0.5"]
    )
    opts = process.options_from_args(args)
    assert opts.node.engine.camera_to_imu_rotation_xyzw == (-0.5, 0.5, -0.5, 0.5)
    assert not opts.rotation_from_tf
    ns = make_bag.build_parser().parse_args(
        ["street", "b", "--distortion", "-0.1,0.01,0,0,0", "--gyro-bias", "-0.01,0,0"]
    )
    assert ns.distortion == pytest.approx((-0.1, 0.01, 0.0, 0.0, 0.0))
    assert tuple(ns.gyro_bias) == pytest.approx((-0.01, 0.0, 0.0))
