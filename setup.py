import ast
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "egovib_ros"


def _nodes() -> tuple[str, ...]:
    """egovib_ros.nodes.NODES, read from the source (setup.py must not import the package)."""
    source = Path(__file__).resolve().parent / PACKAGE / "nodes" / "__init__.py"
    for node in ast.parse(source.read_text()).body:
        if isinstance(node, ast.Assign) and [t.id for t in node.targets] == ["NODES"]:
            return ast.literal_eval(node.value)
    raise RuntimeError(f"{source}: no NODES = (...) assignment")


NODES = _nodes()

setup(
    name=PACKAGE,
    version="0.1.0",
    # the robot package alone: not test/, not the repository's research tools (research/)
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")),
        (f"share/{PACKAGE}/config/robots", glob("config/robots/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    # ROS client libraries (rclpy, message packages) come from apt on a ROS
    # install, or from requirements-ros.txt in the project venv: not listed here.
    install_requires=[
        "numpy",
        "scipy",
        "rosbags>=0.10",
        "mcap",
        "matplotlib",
        "tqdm",
        "pyyaml",
        # bags: zstd MCAP chunks
        "zstandard",
        # per-sample loops of the low-latency methods (cancel, hybrid) at kHz
        "numba",
    ],
    # many bags at once (--jobs N, --scheduler): a Dask cluster, local or remote
    extras_require={"cluster": ["dask", "distributed"]},
    zip_safe=True,
    maintainer="egovib_ros developers",
    maintainer_email="egovib@example.com",
    description="Ego-vibration removal for robot accelerometers by spectral subtraction",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [f"egovib = {PACKAGE}.cli:main"]
        + [f"{node} = {PACKAGE}.nodes.{node}:main" for node in NODES],
    },
)
