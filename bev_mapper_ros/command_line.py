"""What ``mapper_node`` checks on its command line before ROS starts (no rclpy import).

``-h`` / ``--help`` print the usage and the parameter table; a params file that is missing,
unreadable or not YAML is an ``error: ...`` line, not an rcl traceback.
"""

from __future__ import annotations

import os
import re

import yaml

from bev_mapper_core.errors import ConfigError


class CommandLineError(ConfigError):
    """The node's command line cannot work (unknown argument, bad params file)."""


def _split(argv: list[str]) -> tuple[list[str], list[str]]:
    """(arguments outside, inside) the ``--ros-args ... [--]`` sections; program name excluded."""
    outside, inside, in_ros = [], [], False
    for arg in argv[1:]:
        if arg == "--ros-args":
            in_ros = True
        elif arg == "--" and in_ros:
            in_ros = False
        else:
            (inside if in_ros else outside).append(arg)
    return outside, inside


def ros_arguments(argv: list[str]) -> list[str]:
    """The arguments inside ``--ros-args ... [--]`` sections (every section, in order)."""
    return _split(argv)[1]


def user_arguments(argv: list[str]) -> list[str]:
    """The arguments outside ``--ros-args`` sections, program name excluded."""
    return _split(argv)[0]


def params_files(argv: list[str]) -> list[str]:
    """The files given with ``--params-file`` in the ROS arguments."""
    args = ros_arguments(argv)
    return [args[i + 1] for i, a in enumerate(args[:-1]) if a == "--params-file"]


def check_params_file(path: str) -> None:
    """Raise :class:`CommandLineError` unless ``path`` is a readable YAML mapping."""
    if not os.path.exists(path):
        raise CommandLineError(f"params file {path!r} does not exist")
    if not os.path.isfile(path):
        raise CommandLineError(f"params file {path!r} is not a file")
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise CommandLineError(f"params file {path!r} cannot be read: {exc.strerror}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise CommandLineError(f"params file {path!r} is not valid YAML: {' '.join(str(exc).split())}") from None
    if not isinstance(doc, dict):
        raise CommandLineError(f"params file {path!r} must map node names to ros__parameters")


def wants_help(argv: list[str]) -> bool:
    """True when ``-h`` or ``--help`` is given outside the ROS arguments."""
    return any(a in ("-h", "--help") for a in user_arguments(argv))


def check_command_line(argv: list[str]) -> None:
    """Refuse unexpected arguments and bad params files before ROS parses them.

    Raises:
        CommandLineError: with the reason.
    """
    extra = user_arguments(argv)
    if extra:
        raise CommandLineError(f"unexpected argument(s) {extra}: parameters go after --ros-args "
                               "(-p NAME:=VALUE, --params-file FILE); see --help")
    for path in params_files(argv):
        check_params_file(path)


def rcl_message(exc: BaseException) -> str:
    """An rcl error without its C source locations (``, at /project/src/...c:123``)."""
    return re.sub(r",? at /\S+:\d+", "", " ".join(str(exc).split())).strip()
