"""The live path as a ROS 2 user walks it, with the real ``ros2`` CLI (ros2cli from ../shared/ros2cli).

``scripts/setup_venv.sh`` installs the CLI into the venv when its sources are beside the checkout
(CI always has them) and lays out the ament index (``python -m bev_mapper_ros.ament_layout``).
Without the CLI these tests are skipped, and say why.
"""

from __future__ import annotations

import importlib.util
import os
import pathlib
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest
from ros_helpers import REPO, free_domain_id

BIN = pathlib.Path(sys.executable).parent
ROS2 = BIN / "ros2"
pytestmark = [pytest.mark.skipif(
    not ROS2.exists(),
    reason=f"the ros2 CLI is not installed in {BIN.parent} (bash ../shared/ros2cli/install.sh .venv installs it)",
)]


def cli_env(domain: int) -> dict:
    """Environment of a shell in which the venv is activated (as the README's live section does)."""
    env = dict(os.environ)
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(BIN.parent)
    env["AMENT_PREFIX_PATH"] = str(BIN.parent)
    env["ROS_DOMAIN_ID"] = str(domain)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def ros2(args: list[str], env: dict, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """Run ``ros2 ARGS`` and return the completed process (text output)."""
    return subprocess.run([str(ROS2), *args], env=env, capture_output=True, text=True, timeout=timeout, cwd=REPO)


@pytest.fixture(scope="module")
def layout():
    """The ament layout in this venv (what the set-up writes), pointing at this checkout."""
    from bev_mapper_ros.ament_layout import write_layout

    write_layout(BIN.parent)
    return BIN.parent


@pytest.fixture(scope="module")
def front_bag(tmp_path_factory):
    """A short synthetic front1 drive as a rosbag2."""
    from bags.cli.main import main as bev_bag

    path = tmp_path_factory.mktemp("live") / "front1_drive"
    assert bev_bag(["synth", str(path), "--rig", "front1", "--frames", "6", "--seed", "950000001"]) == 0
    return path


def test_ament_layout_matches_the_console_scripts(layout):
    """``ros2 run`` executables are the setup.py console scripts of the node, nothing retyped."""
    from bev_mapper_ros.ament_layout import EXECUTABLES

    setup_py = (REPO / "setup.py").read_text()
    for name, target in EXECUTABLES.items():
        assert f'"{name} = {target}"' in setup_py, f"{name} is not a console script {target} in setup.py"
    env = cli_env(free_domain_id(5))
    share = ros2(["pkg", "prefix", "--share", "bev_mapper_ros"], env)
    assert share.returncode == 0, share.stderr
    share_dir = pathlib.Path(share.stdout.strip())
    for rig in ("surround6", "cam2bev4", "front1"):
        assert (share_dir / "config" / f"{rig}.yaml").is_file()
    assert (share_dir / "package.xml").is_file() and (share_dir / "launch" / "mapper.launch.py").is_file()
    exe = ros2(["pkg", "executables", "bev_mapper_ros"], env)
    assert exe.returncode == 0 and "bev_mapper_ros mapper_node" in exe.stdout, exe.stdout + exe.stderr


def test_ament_layout_command_reports_errors(tmp_path, capsys):
    from bev_mapper_ros.ament_layout import main, write_layout

    (tmp_path / "prefix").write_text("a file, not a directory")
    assert main([str(tmp_path / "prefix")]) == 1
    assert capsys.readouterr().err.startswith("error: ")
    # an install without a checkout needs the package.xml pip put into share/
    with pytest.raises(Exception, match="package.xml"):
        write_layout(tmp_path / "venv", source=tmp_path / "nowhere")


def readme_block(name: str) -> list[str]:
    """The command lines of the README's ``<!-- NAME:begin -->`` ... ``<!-- NAME:end -->`` block."""
    text = (REPO / "README.md").read_text()
    m = re.search(rf"<!-- {name}:begin[^>]*-->\s*```bash\n(.*?)```\s*<!-- {name}:end -->", text, re.S)
    assert m, f"README.md has no {name} block"
    return [ln for ln in m.group(1).splitlines() if ln.strip()]


def _wait_output(proc_log: pathlib.Path, pattern: str, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if re.search(pattern, proc_log.read_text(errors="replace")):
            return True
        time.sleep(0.1)
    return False


def test_ros2_run_param_node_info_and_topic_echo(layout, front_bag, tmp_path):
    """``ros2 run`` with the installed config, ``ros2 param describe``, ``ros2 node info``,
    ``bev-bag play --clock`` into it, and ``ros2 topic echo --once`` of a grid."""
    env = cli_env(free_domain_id(7))
    share = pathlib.Path(ros2(["pkg", "prefix", "--share", "bev_mapper_ros"], env).stdout.strip())
    node_log = tmp_path / "node.log"
    with open(node_log, "w") as log:
        node = subprocess.Popen(
            [str(ROS2), "run", "bev_mapper_ros", "mapper_node", "--ros-args",
             "--params-file", str(share / "config" / "front1.yaml"), "-p", "method:=ipm", "-p", "use_sim_time:=true"],
            env=env, stdout=log, stderr=subprocess.STDOUT, cwd=tmp_path, start_new_session=True)
    play = None
    try:
        assert _wait_output(node_log, r"mapping \['front'\] with ipm", 60), node_log.read_text()
        desc = ros2(["param", "describe", "/mapper_node", "method"], env)
        assert desc.returncode == 0, desc.stderr
        assert "Type: string" in desc.stdout and "ipm" in desc.stdout and "bimapper" in desc.stdout, desc.stdout
        with open(tmp_path / "play.log", "w") as plog:
            play = subprocess.Popen([str(BIN / "bev-bag"), "play", str(front_bag), "--clock", "--loop"],
                                    env=env, stdout=plog, stderr=subprocess.STDOUT, cwd=tmp_path)
        echo = ros2(["topic", "echo", "--once", "/bev/drivable", "nav_msgs/msg/OccupancyGrid", "--field", "info"], env, timeout=90)
        assert echo.returncode == 0, echo.stderr + node_log.read_text()
        assert "width: 400" in echo.stdout and "height: 200" in echo.stdout and "resolution: 0.15" in echo.stdout, \
            echo.stdout
        info = ros2(["node", "info", "/mapper_node"], env)  # output publishers exist once calibrated
        assert info.returncode == 0, info.stderr
        assert "/bev/drivable: nav_msgs/msg/OccupancyGrid" in info.stdout, info.stdout
        assert "/cameras/front/labels: sensor_msgs/msg/Image" in info.stdout, info.stdout
    finally:
        _stop_daemon(env)  # `param describe` / `topic echo` / `node info` spawned one
        if play is not None:
            play.send_signal(signal.SIGINT)
            play.wait(20)
        if node.poll() is None:
            os.killpg(node.pid, signal.SIGINT)
        try:
            node.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait(5)
    assert node.returncode == 0, node_log.read_text()


@pytest.mark.skipif(shutil.which("colcon", path=str(BIN)) is None, reason="colcon is not installed in this venv")
def test_colcon_build_then_ros2_run(tmp_path):
    """The README's colcon section: build the package in a workspace, source it, ``ros2 run`` it."""
    ws = tmp_path / "ws"
    (ws / "src").mkdir(parents=True)
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    for f in filter(None, files):
        src = REPO / f.decode()
        if src.is_file() and not f.startswith(b"tests/"):
            dst = ws / "src" / "bev_mapper" / f.decode()
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
    env = cli_env(free_domain_id(9))
    env.pop("AMENT_PREFIX_PATH")
    lines = readme_block("colcon")
    build = [ln for ln in lines if ln.startswith(("colcon build", "source install/"))]
    run = [ln for ln in lines if ln.startswith("ros2 run ")]
    assert len(build) == 2 and len(run) == 1, lines
    script = (
        "set -e\n"
        f"{build[0]} --event-handlers console_direct- >colcon.log 2>&1\n"
        f"{build[1]}\n"
        "ros2 pkg prefix bev_mapper_ros\n"
        f"timeout -s INT 30 {run[0]} >node.log 2>&1 &\n"
        "for i in $(seq 300); do grep -q 'mapping' node.log && break; sleep 0.1; done\n"
        "cat node.log\n"
        "kill -INT %1; wait %1 || true\n"
    )
    res = subprocess.run(["bash", "-c", script], cwd=ws, env=env, capture_output=True, text=True, timeout=240)
    assert res.returncode == 0, res.stdout + res.stderr + (ws / "colcon.log").read_text(errors="replace")
    assert str(ws / "install" / "bev_mapper_ros") in res.stdout
    assert "mapping ['front'] with ipm" in res.stdout, res.stdout
    # the workspace's copy of the package, not the checkout's, ran
    assert (ws / "install" / "bev_mapper_ros" / "lib" / "bev_mapper_ros" / "mapper_node").is_file()
    # with the two C kernels built (setup.py's ext_modules; optional, so a failed build is silent)
    built = {p.name.split(".")[0] for p in (ws / "install").rglob("*.so")}
    assert {"_chamfer", "_counts"} <= built, sorted(built)


def test_readme_live_commands_verbatim(layout, tmp_path):
    """After ``bash scripts/demo.sh``, the README's live section, line for line: ``ros2 run`` the
    node, play the demo drive, and ``ros2 topic echo --once`` prints a grid."""
    shells: list[list[str]] = []
    for ln in readme_block("live"):
        if re.match(r"# shell \d", ln):
            shells.append([])
        elif not ln.startswith("#"):
            shells[-1].append(ln)
    assert len(shells) == 3 and all(sh[0] == "source .venv/bin/activate" for sh in shells), shells
    env = cli_env(free_domain_id(11))
    for k in ("VIRTUAL_ENV", "AMENT_PREFIX_PATH"):
        env.pop(k)  # the README's `source .venv/bin/activate` sets them
    env["PATH"] = os.environ.get("PATH", "")
    if not (REPO / "data" / "demo_drive" / "metadata.yaml").is_file():  # what the README's first command does
        demo = subprocess.run(["bash", "scripts/demo.sh", "--no-pictures", "--max-frames", "1"], cwd=REPO,
                              env={**env, "BEV_DEMO_OUT": str(tmp_path / "demo")}, capture_output=True, text=True,
                              timeout=300)
        assert demo.returncode == 0, demo.stderr
    logs = [tmp_path / f"shell{i + 1}.log" for i in range(3)]
    procs = []
    try:
        for i in (0, 1):
            with open(logs[i], "w") as log:
                procs.append(subprocess.Popen(["bash", "-c", "\n".join(shells[i])], cwd=REPO, env=env, stdout=log,
                                              stderr=subprocess.STDOUT, start_new_session=True))
            if i == 0:
                assert _wait_output(logs[0], r"mapping \[", 60), logs[0].read_text()
        echo = subprocess.run(["bash", "-c", "\n".join(shells[2])], cwd=REPO, env=env, capture_output=True,
                              text=True, timeout=120)
        assert echo.returncode == 0, echo.stderr + logs[0].read_text() + logs[1].read_text()
        assert "width: 400" in echo.stdout and "height: 200" in echo.stdout, echo.stdout
    finally:
        _stop_daemon(env)  # the README's `ros2 topic echo` spawned one
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
    node_log = logs[0].read_text()
    assert procs[0].returncode == 0, node_log
    assert "[ERROR]" not in node_log and "Traceback" not in node_log, node_log
    if importlib.util.find_spec("tf2_ros") or os.environ.get("CI"):  # scripts/setup_venv.sh builds it
        assert "extrinsics: front: TF (base_link <- front_optical_frame)" in node_log, node_log  # play's /tf_static


def _stop_daemon(env: dict) -> None:
    """Stop the ros2 daemon a CLI call of this test may have started (on the test's domain)."""
    ros2(["daemon", "stop"], env, timeout=30)


def test_launch_file_arguments(layout):
    """The launch file's arguments, and the parameter file it picks for each rig, is installed."""
    import ast

    from bev_mapper_core.geometry.rig import PRESETS

    tree = ast.parse((REPO / "launch" / "mapper.launch.py").read_text())
    table = next(n.value for n in tree.body if isinstance(n, ast.Assign) and n.targets[0].id == "ARGUMENTS")
    args = {name: default for name, default, _ in ast.literal_eval(table)}
    assert set(args) == {"rig", "params_file", "use_sim_time", "namespace", "method", "input_kind"}, args
    assert args["rig"] in PRESETS and args["use_sim_time"] == "false"
    env = cli_env(free_domain_id(13))
    share = pathlib.Path(ros2(["pkg", "prefix", "--share", "bev_mapper_ros"], env).stdout.strip())
    for rig in PRESETS:
        assert (share / "config" / f"{rig}.yaml").is_file(), rig


def test_launch_then_topic_echo(layout, front_bag, tmp_path):
    """``ros2 launch bev_mapper_ros mapper.launch.py rig:=front1 use_sim_time:=true``, the drive
    played with ``--clock`` (its ``/tf_static`` too: the node logs extrinsics from TF) and
    ``ros2 topic echo --once /bev/drivable`` receives a grid; a launch that cannot start says
    why in one line."""
    if importlib.util.find_spec("composition_interfaces") is None and not os.environ.get("CI"):
        pytest.skip("composition_interfaces is not built into this venv (bash scripts/setup_venv.sh builds it)")
    env = cli_env(free_domain_id(13))
    bad = ros2(["launch", "bev_mapper_ros", "mapper.launch.py", "rig:=nowhere"], env, timeout=60)
    errors = [ln for ln in (bad.stdout + bad.stderr).splitlines() if "[ERROR]" in ln]
    assert bad.returncode != 0 and len(errors) == 1 and "rig 'nowhere' has no installed parameter file" in errors[0], \
        bad.stdout + bad.stderr
    log = tmp_path / "launch.log"
    with open(log, "w") as f:
        proc = subprocess.Popen([str(ROS2), "launch", "bev_mapper_ros", "mapper.launch.py", "rig:=front1",
                                 "method:=ipm", "use_sim_time:=true"], env=env, stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True)
    play = None
    try:
        assert _wait_output(log, r"mapping \['front'\] with ipm", 60), log.read_text()
        with open(tmp_path / "play.log", "w") as plog:
            play = subprocess.Popen([str(BIN / "bev-bag"), "play", str(front_bag), "--clock", "--loop"],
                                    env=env, stdout=plog, stderr=subprocess.STDOUT, cwd=tmp_path, start_new_session=True)
        echo = ros2(["topic", "echo", "--once", "/bev/drivable", "nav_msgs/msg/OccupancyGrid", "--field", "info"], env,
                    timeout=90)
        assert echo.returncode == 0, echo.stderr + log.read_text()
        assert "width: 400" in echo.stdout and "resolution: 0.15" in echo.stdout, echo.stdout
        assert _wait_output(log, r"extrinsics: front: TF \(base_link <- front_optical_frame\)", 30), log.read_text()
        assert "skipping topics" not in (tmp_path / "play.log").read_text()  # /tf and /tf_static are played
    finally:
        for p in (play, proc):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in (play, proc):
            if p is None:
                continue
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        _stop_daemon(env)
    assert "Traceback" not in log.read_text(), log.read_text()
