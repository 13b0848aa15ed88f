"""bev_mapper_core must stay framework-free: no rclpy, no *_msgs, no rosbags, and nothing from
the packages above it (bags, msg_adapters, bev_mapper_ros): the entry points hand things down."""

import ast
import pathlib
import re

import pytest
from import_check import ros_modules_loaded_by

CORE = pathlib.Path(__file__).resolve().parents[2] / "bev_mapper_core"
FORBIDDEN = ("rclpy", "rosbags", "mcap", "tf2_ros", "launch", "launch_ros", "rosidl_runtime_py")
#: The project's packages that build on the core; the core imports none of them.
UPPER = ("bags", "msg_adapters", "bev_mapper_ros")


def imported_modules(path: pathlib.Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, node.lineno


def test_core_sources_import_no_ros():
    offenders = []
    files = sorted(CORE.rglob("*.py"))
    assert len(files) > 5
    for f in files:
        for mod, line in imported_modules(f):
            top = mod.split(".")[0]
            if top in FORBIDDEN or top.endswith("_msgs") or top.endswith("_interfaces"):
                offenders.append(f"{f.relative_to(CORE.parent)}:{line} imports {mod}")
    assert not offenders, "\n".join(offenders)


def test_core_imports_nothing_from_the_packages_above_it():
    """Not at module level, not lazily inside a function, not as a ``"module:Class"`` registry string."""
    offenders = []
    target = re.compile(rf"^({'|'.join(UPPER)})([.:]|$)")
    for f in sorted(CORE.rglob("*.py")):
        for mod, line in imported_modules(f):
            if mod.split(".")[0] in UPPER:
                offenders.append(f"{f.relative_to(CORE.parent)}:{line} imports {mod}")
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and target.match(node.value):
                offenders.append(f"{f.relative_to(CORE.parent)}:{node.lineno} names {node.value!r}")
    assert not offenders, "\n".join(offenders)


@pytest.mark.slow  # a fresh interpreter imports every core module (torch among them)
def test_importing_core_loads_no_ros_module():
    """Importing every core module in a fresh interpreter loads no ROS module and nothing from the
    layers above (one interpreter for both checks: each start imports torch)."""
    statements = (
        "import pkgutil, importlib, sys, bev_mapper_core\n"
        "for m in pkgutil.walk_packages(bev_mapper_core.__path__, 'bev_mapper_core.'):\n"
        "    if not m.name.endswith('__main__'): importlib.import_module(m.name)\n"
        f"upper = sorted(k for k in sys.modules if k.split('.')[0] in {UPPER!r})\n"
        "assert not upper, f'core loaded {upper}'"
    )
    assert ros_modules_loaded_by(statements) == []


@pytest.mark.ros  # imports sensor_msgs
def test_the_import_check_sees_ros_modules():
    """The check above is not vacuous: importing a message package is caught."""
    pytest.importorskip("sensor_msgs")
    assert "sensor_msgs" in ros_modules_loaded_by("import sensor_msgs.msg")
