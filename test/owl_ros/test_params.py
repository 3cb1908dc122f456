"""owl_ros.params: the one parameter table, its validation, descriptors and shipped files."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
import yaml
from rcl_interfaces.msg import ParameterDescriptor

from msg_adapters.pointcloud import OWL_FIELDS
from owl_core.engine import EngineOptions
from owl_ros import params as P


def test_defaults_build_engine_defaults_and_round_trip() -> None:
    opts = P.build_options()
    assert opts.engine == EngineOptions()
    assert opts == P.NodeOptions()
    assert P.to_values(opts) == P.defaults()
    changed = opts.with_values({"max_features": 300, "tracker_lk_levels": 2, "queue_size": 4})
    assert changed.engine.max_features == 300
    assert changed.engine.tracker.lk_levels == 2
    assert changed.queue_size == 4
    assert P.to_values(changed) == {
        **P.defaults(),
        "max_features": 300,
        "tracker_lk_levels": 2,
        "queue_size": 4,
    }


def test_every_table_entry_is_consistent() -> None:
    names = [p.name for p in P.PARAMS]
    assert len(names) == len(set(names))
    for p in P.PARAMS:
        assert p.kind in P.KINDS
        assert p.description
        assert P.validate({p.name: p.default}) == [], p.name
        if p.kind in ("int", "double"):
            assert p.low is not None and p.high is not None and p.low <= p.default <= p.high
        if p.kind == "double_array":
            assert p.length == len(p.default)
    # contract names
    assert "camera_to_imu_rotation_xyzw" in names and "imu_time_offset" in names


@pytest.mark.parametrize(
    ("values", "expect"),
    [
        ({"max_features": -5}, "parameter max_features: must be in [1, 20000], got -5"),
        ({"queue_size": 0}, "parameter queue_size: must be in [1, 100], got 0"),
        ({"imu_wait_s": math.nan}, "parameter imu_wait_s: must be finite, got nan"),
        ({"imu_time_offset": math.inf}, "parameter imu_time_offset: must be finite, got inf"),
        (
            {"camera_to_imu_rotation_xyzw": [0.0, 0.0, 1.0]},
            "parameter camera_to_imu_rotation_xyzw: must have 4 elements, got 3: [0.0, 0.0, 1.0]",
        ),
        (
            {"camera_to_imu_rotation_xyzw": [0.0, 0.0, math.nan, 1.0]},
            "parameter camera_to_imu_rotation_xyzw: must hold finite numbers",
        ),
        (
            {"camera_to_imu_rotation_xyzw": [0.0, 0.0, 0.0, 2.0]},
            "parameter camera_to_imu_rotation_xyzw: must be a unit quaternion",
        ),
        ({"image_transport": "theora"}, "parameter image_transport: must be one of raw, "),
        ({"max_features": 1.5}, "parameter max_features: must be an integer, got 1.5"),
        ({"require_gyro": "yes"}, "parameter require_gyro: must be true or false, got 'yes'"),
        ({"min_track_frames": 11}, "parameter min_track_frames: min_track_frames (11) must not"),
        ({"tracker_lk_window_px": 8}, "parameter tracker_lk_window_px: TrackerOptions."),
        ({"no_such_thing": 1}, "parameter no_such_thing: unknown parameter"),
        ({"speed_topic": "wheel odom"}, "parameter speed_topic: must be a valid topic name ("),
        ({"speed_topic": "odom/"}, "parameter speed_topic: must be a valid topic name ("),
    ],
)
def test_one_line_per_bad_value_naming_parameter_and_value(
    values: dict[str, object], expect: str
) -> None:
    lines = P.validate(values)
    assert len(lines) == 1
    assert lines[0].startswith(expect), lines[0]
    assert "\n" not in lines[0]
    if "unknown" in expect:
        return  # build_options ignores names it does not know (use_sim_time...)
    with pytest.raises(P.ParameterError) as info:
        P.build_options(values)
    assert info.value.lines == tuple(lines)


def test_several_bad_values_give_several_lines() -> None:
    lines = P.validate({"max_features": -1, "neighbours": 0, "imu_wait_s": -1.0})
    assert [line.split(":")[0] for line in lines] == [
        "parameter max_features",
        "parameter neighbours",
        "parameter imu_wait_s",
    ]


def test_descriptors_carry_ranges_and_read_only() -> None:
    for p in P.PARAMS:
        d = P.descriptor(p)
        assert isinstance(d, ParameterDescriptor)
        assert d.name == p.name and d.read_only == p.read_only
        assert d.description == p.description
        if p.kind == "int":
            (r,) = d.integer_range
            assert (r.from_value, r.to_value, r.step) == (p.low, p.high, 1)
        elif p.kind == "double":
            (r,) = d.floating_point_range
            assert (r.from_value, r.to_value) == (p.low, p.high)
        else:
            assert not d.integer_range and not d.floating_point_range
    read_only = {p.name for p in P.PARAMS if p.read_only}
    assert read_only == {
        "image_transport",
        "queue_size",
        "speed_source",
        "speed_topic",
        "publish_debug_image",
        "dense",
        "dense_process",
        "rectified",
    }


def test_parse_value_like_ros2_param_set() -> None:
    assert P.parse_value("max_features", "500") == 500
    assert P.parse_value("imu_wait_s", "1") == 1.0
    assert isinstance(P.parse_value("imu_wait_s", "1"), float)
    assert math.isnan(P.parse_value("imu_wait_s", "nan"))
    assert P.parse_value("require_gyro", "false") is False
    assert P.parse_value("camera_to_imu_rotation_xyzw", "[0, 0, 0, 1]") == [0.0, 0.0, 0.0, 1.0]
    assert P.parse_value("image_transport", "compressed") == "compressed"
    with pytest.raises(P.ParameterError, match="parameter bogus: unknown parameter"):
        P.parse_value("bogus", "1")


def test_config_yaml_lists_every_parameter_with_its_default(repo_root: Path) -> None:
    text = (repo_root / "config" / "owl.yaml").read_text()
    data = yaml.safe_load(text)
    # '/**': the node in any namespace (a key 'owl' is ignored under -r __ns:=/robot1)
    assert list(data) == ["/**"]
    values = data["/**"]["ros__parameters"]
    # the rotation is listed commented out: set, it would stop the node taking it from TF
    assert set(P.UNSET_IN_FILE) == {"camera_to_imu_rotation_xyzw"}
    assert set(values) == {p.name for p in P.PARAMS} - set(P.UNSET_IN_FILE)
    lines = text.splitlines()
    for p in P.PARAMS:
        default = list(p.default) if p.kind == "double_array" else p.default
        if p.name in P.UNSET_IN_FILE:
            at = lines.index(f"    # {p.name}: {list(default)}")
            assert yaml.safe_load(lines[at].replace("#", "", 1))[p.name] == default
            continue
        assert values[p.name] == default, p.name
        if p.kind == "double":  # ROS types are strict: a double must be written as one
            assert isinstance(values[p.name], float), p.name
        # documented: a comment line right above the value
        at = next(i for i, line in enumerate(lines) if line.strip().startswith(f"{p.name}:"))
        assert lines[at - 1].strip().startswith("#"), p.name
    assert P.build_options(values) == P.NodeOptions()


def test_launch_file_is_valid_python_with_the_standard_entry_point(repo_root: Path) -> None:
    source = (repo_root / "launch" / "owl.launch.py").read_text()
    tree = ast.parse(source)
    funcs = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "generate_launch_description" in funcs
    assert "'owl_node'" in source or '"owl_node"' in source
    assert "owl.yaml" in source and "use_sim_time" in source


def test_rviz_config_shows_cloud_by_intensity_field_and_heading(repo_root: Path) -> None:
    cfg = yaml.safe_load((repo_root / "config" / "owl.rviz").read_text())
    displays = cfg["Visualization Manager"]["Displays"]
    clouds = [d for d in displays if d["Class"] == "rviz_default_plugins/PointCloud2"]
    assert len(clouds) == 1
    cloud = clouds[0]
    assert cloud["Topic"]["Value"] == "owl/points"
    assert cloud["Color Transformer"] == "Intensity"
    assert cloud["Channel Name"] in {name for name, _, _ in OWL_FIELDS}
    topics = {d.get("Topic", {}).get("Value") for d in displays}
    assert "owl/heading_marker" in topics and "owl/debug_image" in topics


def test_config_yaml_is_generated_from_the_table(repo_root: Path) -> None:
    assert (repo_root / "config" / "owl.yaml").read_text() == P.config_yaml()


def test_process_help() -> None:
    from owl_ros import process

    with pytest.raises(SystemExit) as info:
        process.main(["--help"])
    assert info.value.code == 0


def test_one_parser_for_every_tool_s_dash_p() -> None:
    """owl_process, owl_bench, owl_batch and the agreement tool read -p items alike."""
    assert P.parse_assignment("max_features:=400") == ("max_features", 400)
    assert P.parse_assignment("pixel_noise_px=1") == ("pixel_noise_px", 1.0)
    assert P.parse_assignment(" require_gyro := false") == ("require_gyro", False)
    for item in ("max_features", ":=400", ""):
        with pytest.raises(P.ParameterError, match="-p expects NAME:=VALUE, got"):
            P.parse_assignment(item)
    with pytest.raises(P.ParameterError, match="did you mean max_features"):
        P.parse_assignment("max_feature:=400")
    assert P.find("max_features") is not None and P.find("nope") is None
