"""No exception in a callback ends the node: the executor's callbacks are contained (counted
under ``errors`` in /diagnostics, logged throttled, input skipped)."""

from __future__ import annotations

import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402
from ros_helpers import free_domain_id  # noqa: E402

from bev_mapper_ros.mapper_node import MapperNode  # noqa: E402


class _Exploding:
    """A message whose every field access fails in a way no adapter anticipates."""

    def __getattr__(self, name):
        raise RuntimeError(f"driver bug reading {name}")


@pytest.fixture()
def node():
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=free_domain_id(21))
    n = MapperNode(context=ctx, parameter_overrides=[Parameter("rig", value="front1"),
                                                     Parameter("method", value="ipm")])
    try:
        yield n
    finally:
        n.stop()
        n.destroy_node()
        rclpy.shutdown(context=ctx)


def test_unexpected_exceptions_in_callbacks_are_contained(node):
    image_cb = node._contained("front image", node._image_cb("front"))
    info_cb = node._contained("front camera_info", node._info_cb("front"))
    for _ in range(3):
        assert image_cb(_Exploding()) is None
        assert info_cb(_Exploding()) is None
    assert node.stats.errors + node.stats.bad_input == 6
    # a failing timer callback (here: diagnostics with a broken publisher) is contained as well
    node._diag_pub = _Exploding()
    node._contained("diagnostics", node._publish_diagnostics)()
    assert node.stats.errors + node.stats.bad_input == 7


def test_the_subscriptions_and_timers_are_the_contained_ones(node):
    """Every callback the executor runs is wrapped (a new callback cannot skip the wrapper)."""
    for sub in node.subscriptions:
        if sub.topic_name.startswith("/cameras/"):
            assert sub.callback.__qualname__.endswith("_contained.<locals>.wrapper"), sub.topic_name
    for timer in node.timers:
        assert timer.callback.__qualname__.endswith("_contained.<locals>.wrapper")
