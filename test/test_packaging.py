"""The package as ROS users get it: owl_core purity and a real colcon build.

The colcon check is exactly what `ros2 run owl_ros <exe>` needs on a robot: the
executables under install/owl_ros/lib/owl_ros, package.xml under share/owl_ros, and
the ament index marker.
"""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bags.io import BagReader
from owl_ros.tools.live import LiveNode

REPO = Path(__file__).resolve().parents[1]
BUILD_IGNORE = shutil.ignore_patterns(
    ".venv",
    ".git",
    "build",
    "install",
    "log",
    "results",
    "__pycache__",
    "*.egg-info",
    ".pytest_cache",
    ".ruff_cache",
    ".mypy_cache",
)


def console_scripts() -> list[str]:
    """Names of the console scripts registered in setup.py (parsed, not imported)."""
    tree = ast.parse((REPO / "setup.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "CONSOLE_SCRIPTS" for t in node.targets
        ):
            entries = ast.literal_eval(node.value)
            return [entry.split("=")[0].strip() for entry in entries]
    raise AssertionError("setup.py defines no CONSOLE_SCRIPTS list")


def test_owl_core_imports_no_ros_or_bag_module() -> None:
    """Import every owl_core module with ROS and bag modules made unimportable."""
    code = textwrap.dedent(
        """
        import importlib, pkgutil, sys
        BLOCKED = ("rclpy", "rosbags", "mcap", "mcap_ros2", "builtin_interfaces",
                   "rosidl_runtime_py", "rosgraph_msgs")

        class Block:
            def find_spec(self, name, path=None, target=None):
                root = name.split(".")[0]
                if root in BLOCKED or root.endswith("_msgs"):
                    raise ImportError(f"owl_core imported blocked module {name!r}")
                return None

        sys.meta_path.insert(0, Block())
        import owl_core
        names = [m.name for m in pkgutil.walk_packages(owl_core.__path__, "owl_core.")]
        for name in names:
            importlib.import_module(name)
        leaked = sorted(m for m in sys.modules
                        if m.split(".")[0] in BLOCKED or m.split(".")[0].endswith("_msgs"))
        print(len(names), leaked)
        sys.exit(1 if leaked else 0)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr + done.stdout
    count = int(done.stdout.split()[0])
    assert count >= 1, "owl_core has no modules to check"


def test_blocker_catches_a_ros_import(tmp_path: Path) -> None:
    """The purity check itself can fail: a module importing rclpy is caught."""
    pkg = tmp_path / "impure"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("import rclpy\n")
    code = textwrap.dedent(
        """
        import sys
        class Block:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "rclpy":
                    raise ImportError("blocked rclpy")
                return None
        sys.meta_path.insert(0, Block())
        import impure
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert done.returncode != 0
    assert "blocked rclpy" in done.stderr


def test_product_imports_no_tool_and_no_module_changes_the_environment() -> None:
    """The product (owl_ros without owl_ros.tools) and the bags library and simulator never
    import a tool module; importing any module of the four packages leaves os.environ as
    it was (no process-wide setting at import: owl_bench sets its thread counts in main)."""
    code = textwrap.dedent(
        """
        import importlib, os, pkgutil, sys
        import cv2  # OpenCV's own import sets LD_LIBRARY_PATH: not ours to check
        import threadpoolctl  # its own import sets KMP_DUPLICATE_LIB_OK: not ours either
        before = dict(os.environ)
        import bags, msg_adapters, owl_core, owl_ros
        product = ["owl_ros.node", "owl_ros.pipeline", "owl_ros.params", "owl_ros.process",
                   "bags.io", "bags.errors", "bags.sim.render", "bags.sim.scenarios",
                   "bags.sim.sensors"]
        for name in product:
            importlib.import_module(name)
        tools = sorted(m for m in sys.modules
                       if m.startswith(("owl_ros.tools", "bags.cli.")))
        names = [m.name for pkg in (bags, msg_adapters, owl_core, owl_ros)
                 for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + ".")]
        for name in names:
            importlib.import_module(name)
        changed = sorted(k for k in set(before) | set(os.environ)
                         if before.get(k) != os.environ.get(k))
        print(len(names), tools, changed)
        sys.exit(1 if tools or changed else 0)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr + done.stdout
    assert int(done.stdout.split()[0]) >= 30, done.stdout


#: import name -> package.xml key, for third-party modules whose key differs from the name.
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "cv2": "python3-opencv",
    "scipy": "python3-scipy",
    "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib",
    "tf2_ros": "tf2_ros_py",
}
#: pip-only (no rosdep key): these must be pinned in requirements/python.txt instead. The
#: zstd codecs bags.io catches errors of are the ones rosbags (``backports.zstd``, the
#: standard library's ``compression.zstd`` from Python 3.14) and mcap (``zstandard``)
#: install and use for MCAP chunks: they come with those pins.
PIP_ONLY = {
    "rosbags": "rosbags",
    "mcap": "mcap",
    "ray": "ray",
    "threadpoolctl": "threadpoolctl",
    "backports": "rosbags",
    "compression": "rosbags",
    "zstandard": "mcap",
}


def test_every_imported_third_party_package_is_declared() -> None:
    """Every top-level module imported by the package or its launch file is the standard
    library, the project's own, a package.xml exec_depend, or pinned pip-only."""
    own = {"owl_core", "msg_adapters", "owl_ros", "bags"}
    found: dict[str, str] = {}
    files = [*REPO.glob("launch/*.py")]
    for pkg in own:
        files += (REPO / pkg).rglob("*.py")
    for path in files:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                root = name.split(".")[0]
                if (
                    root not in sys.stdlib_module_names
                    and root not in own
                    and root != "__future__"
                ):
                    found.setdefault(root, str(path.relative_to(REPO)))
    declared = set(
        re.findall(r"<exec_depend>([^<]+)</exec_depend>", (REPO / "package.xml").read_text())
    )
    pinned = {
        line.split("==")[0].strip().lower()
        for line in (REPO / "requirements" / "python.txt").read_text().splitlines()
        if "==" in line and not line.startswith("#")
    }
    missing = []
    for root, where in sorted(found.items()):
        if root in PIP_ONLY:
            ok = PIP_ONLY[root] in pinned
        else:
            ok = ROSDEP_KEYS.get(root, root) in declared
        if not ok:
            missing.append(f"{root} (imported in {where})")
    assert not missing, f"undeclared third-party imports: {missing}"
    assert {"numpy", "rclpy", "yaml", "matplotlib"} <= set(found)  # the scan sees imports


@pytest.mark.slow
@pytest.mark.dds
def test_colcon_build_installs_what_ros2_run_needs(
    tmp_path: Path, ros_domain_env: dict[str, str]
) -> None:
    """Build with colcon into a temporary workspace, inspect the install, run owl_node live.

    The live run is what `ros2 run owl_ros owl_node` does on a robot: the installed
    lib/owl_ros/owl_node starts, publishes /diagnostics over real DDS (recorded by the
    installed owl_record in a second process) and exits 0 on SIGINT.
    """
    colcon = Path(sys.executable).with_name("colcon")
    if not colcon.exists():
        pytest.fail(f"colcon is not installed next to {sys.executable}; run `make venv`")
    src = tmp_path / "src" / "owl_ros"
    shutil.copytree(REPO, src, ignore=BUILD_IGNORE)
    env = dict(ros_domain_env)
    done = subprocess.run(
        [
            str(colcon),
            "build",
            "--base-paths",
            "src",
            "--build-base",
            "build",
            "--install-base",
            "install",
            "--event-handlers",
            "console_direct-",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    prefix = tmp_path / "install" / "owl_ros"
    assert (prefix / "share" / "owl_ros" / "package.xml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "owl_ros").is_file()
    scripts = console_scripts()
    missing = [name for name in scripts if not (prefix / "lib" / "owl_ros" / name).is_file()]
    assert not missing, f"colcon did not install {missing} under lib/owl_ros"
    for name in scripts:
        done = subprocess.run(
            [str(prefix / "lib" / "owl_ros" / name), "--help"],
            capture_output=True,
            text=True,
            timeout=120,
            env={**env, "PYTHONPATH": str(next((prefix / "lib").glob("python3*/site-packages")))},
        )
        assert done.returncode == 0, f"{name} --help failed: {done.stderr[-2000:]}"
        assert "usage" in done.stdout.lower(), f"{name} --help printed no usage"

    # `source install/setup.bash` puts the install's site-packages first on PYTHONPATH
    site = next((prefix / "lib").glob("python3*/site-packages"))
    run_env = {**env, "PYTHONPATH": os.pathsep.join([str(site), env.get("PYTHONPATH", "")])}
    lib = prefix / "lib" / "owl_ros"
    node = LiveNode(
        ["-p", "diagnostics_period_s:=0.2"],
        env=run_env,
        command=[str(lib / "owl_node")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    ).start()
    try:
        recorded = subprocess.run(
            [str(lib / "owl_record"), str(tmp_path / "diag"), "/diagnostics", "--duration", "6"],
            env=run_env,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert recorded.returncode == 0, recorded.stderr[-2000:]
    finally:
        code, node_out = node.stop(timeout_s=30)
    assert code == 0, f"owl_node exited {code}: {node_out[-2000:]}"
    with BagReader(tmp_path / "diag") as bag:
        assert bag.topics["/diagnostics"].count >= 3, node_out[-2000:]
        first = bag.deserialize(next(bag.messages(["/diagnostics"])))
    names = {status.name for status in first.status}
    assert any(name.startswith("owl") for name in names), names
    # with no camera_info/image yet the node must say what is missing
    messages = " ".join(status.message for status in first.status).lower()
    assert "camera_info" in messages or "image" in messages, messages


#: import name -> package.xml exec_depend (rosdep key); None: pip only (requirements).
ROSDEP = {
    "ament_index_python": "ament_index_python", "builtin_interfaces": "builtin_interfaces",
    "cv2": "python3-opencv", "diagnostic_msgs": "diagnostic_msgs",
    "geometry_msgs": "geometry_msgs", "launch": "launch", "launch_ros": "launch_ros",
    "matplotlib": "python3-matplotlib", "nav_msgs": "nav_msgs", "numpy": "python3-numpy",
    "rcl_interfaces": "rcl_interfaces", "rclpy": "rclpy", "rosgraph_msgs": "rosgraph_msgs",
    "scipy": "python3-scipy", "sensor_msgs": "sensor_msgs", "std_msgs": "std_msgs",
    "tf2_ros": "tf2_ros_py", "visualization_msgs": "visualization_msgs",
    "yaml": "python3-yaml", "rosbags": None, "mcap": None, "mcap_ros2": None,
    "zstandard": None, "backports": None, "compression": None, "ray": None,
    "threadpoolctl": "python3-threadpoolctl",
}  # fmt: skip


def test_package_xml_declares_what_the_code_imports() -> None:
    import xml.etree.ElementTree as ET

    ours = {"owl_core", "msg_adapters", "owl_ros", "bags"}
    imported: set[str] = set()
    for folder in ("owl_core", "msg_adapters", "owl_ros", "bags", "launch"):
        for path in (REPO / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    imported |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    imported.add(node.module.split(".")[0])
    third = imported - ours - set(sys.stdlib_module_names)
    unknown = sorted(third - set(ROSDEP))
    assert not unknown, f"imports without a known rosdep key: {unknown}"
    deps = {e.text for e in ET.parse(REPO / "package.xml").getroot().iter("exec_depend")}
    wanted = {ROSDEP[m] for m in third if ROSDEP[m] is not None}
    launch = (REPO / "launch" / "owl.launch.py").read_text()
    if 'package="rviz2"' in launch:
        wanted.add("rviz2")
    assert sorted(wanted - deps) == []


def test_launch_arguments_and_rviz_frame() -> None:
    from owl_ros.launch_args import node_parameters

    text = (REPO / "launch" / "owl.launch.py").read_text()
    declared = {
        node.args[0].value
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.Call)
        and getattr(node.func, "id", "") == "DeclareLaunchArgument"
        and isinstance(node.args[0], ast.Constant)
    }
    assert {"camera_to_imu_rotation_xyzw", "imu_time_offset", "namespace", "frame"} <= declared
    assert '"-f", value("frame")' in text  # RViz's fixed frame is the launch argument
    assert node_parameters("", "") == {}
    assert node_parameters("-0.5,0.5,-0.5,0.5", "0.004") == {
        "camera_to_imu_rotation_xyzw": [-0.5, 0.5, -0.5, 0.5],
        "imu_time_offset": 0.004,
    }
    assert node_parameters("[0, 0, 0, 1]", "")["camera_to_imu_rotation_xyzw"] == [0, 0, 0, 1.0]
    with pytest.raises(ValueError, match="camera_to_imu_rotation_xyzw: expected 4 numbers"):
        node_parameters("1,2", "")
    rviz = (REPO / "config" / "owl.rviz").read_text()
    assert "coloured by r/|t|" in rviz and "quality" not in rviz.split("Panels:")[0]


def test_readme_names_every_tool_and_where_it_lives() -> None:
    readme = (REPO / "README.md").read_text()
    missing = [name for name in console_scripts() if f"`{name}" not in readme]
    assert not missing, f"README does not name {missing}"
    first = readme.split("## What it is")[0]
    assert ". .venv/bin/activate" in first and "install/setup.bash" in first
    assert "--break-system-packages" in first and "--system-site-packages" in first
