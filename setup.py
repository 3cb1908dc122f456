"""ament_python packaging for owl_ros (laid out as ros2/demos demo_nodes_py does it)."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "owl_ros"

# Each executable is registered once it is real; `ros2 run owl_ros <name>` finds
# it under lib/owl_ros (setup.cfg), a pip/venv install puts it on PATH.
CONSOLE_SCRIPTS = [
    "owl_node = owl_ros.node:main",
    "owl_process = owl_ros.process:main",
    "owl_eval = owl_ros.tools.evaluate:main",
    "owl_bench = owl_ros.tools.bench:main",
    "owl_latency = owl_ros.tools.latency:main",
    "owl_soak = owl_ros.tools.soak:main",
    "owl_batch = owl_ros.tools.batch:main",
    "owl_calibrate = owl_ros.calibrate:main",
    "owl_diag = owl_ros.tools.diag:main",
    "owl_make_bag = bags.cli.make_bag:main",
    "owl_replay = bags.cli.replay:main",
    "owl_record = bags.cli.record:main",
    "owl_import = bags.cli.importers.cli:main",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["owl_core*", "msg_adapters*", "owl_ros*", "bags*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="OWL maintainers",
    maintainer_email="owl-maintainers@example.com",
    description="OWL: looming and perceived rotation from a moving camera and gyro (ROS 2).",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={"console_scripts": CONSOLE_SCRIPTS},
)
