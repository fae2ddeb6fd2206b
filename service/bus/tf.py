"""The grids' /tf and /tf_static subscriptions (tf2_msgs/TFMessage CDR), with the QoS tf2 and rmw_zenoh give them.

/tf is volatile: a plain subscriber. /tf_static is transient local (tf2_ros StaticBroadcasterQoS, depth 1 per
publisher; StaticListenerQoS, depth 100): rmw_zenoh (rmw_publisher_data.cpp) and zenoh-bridge-ros2dds
(route_publisher.rs) publish it through an AdvancedPublisher with a cache and publisher detection, so a
subscriber started after the robot gets each static broadcaster's last message by querying those caches. This
subscriber is declared as rmw_zenoh declares a transient-local one (rmw_subscription_data.cpp): history with
late-publisher detection up to the listener's depth, recovery on the publishers' heartbeats, and detectable.
Their graph tokens (rmw_zenoh layout only) come from ros_graph.py, as the cameras' do: tf publishers send
whether or not they count subscribers, but ``ros2 topic info`` should list the service among them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import zenoh
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.service.bus.ros_graph import TF_STATIC_QOS
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.stats import ServiceStats
from zenoh import ext

STATIC_LISTENER_DEPTH = TF_STATIC_QOS.depth  # tf2_ros StaticListenerQoS: the samples asked of each publisher's cache


def declare_tf_inputs(session: zenoh.Session, grids: GridOutputs, stats: ServiceStats) -> list[Any]:
    """Subscribe every grid with tf settings to its /tf and /tf_static keys; the entities, to undeclare."""
    declared: list[Any] = []
    for key, grid, static, handle in grids.tf_inputs():
        callback = _counting(grid, handle, stats)
        if not static:
            declared.append(session.declare_subscriber(key, callback))
            continue
        declared.append(
            ext.declare_advanced_subscriber(
                session,
                key,
                callback,
                history=ext.HistoryConfig(detect_late_publishers=True, max_samples=STATIC_LISTENER_DEPTH),
                recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True,
            )
        )
    return declared


def _counting(
    grid: str, handle: Callable[[bytes], list[RejectedInput]], stats: ServiceStats
) -> Callable[[zenoh.Sample], None]:
    """A sample's payload to the grid's tree; a message or a transform refused is counted under the grid, by
    reason, and never stops the subscription."""

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            refused = handle(sample.payload.to_bytes())
        except RejectedInput as bad_message:
            refused = [bad_message]
        for problem in refused:
            stats.rejected(grid, problem.reason, f"{sample.key_expr}: {problem.detail}"[:300])

    return on_sample
