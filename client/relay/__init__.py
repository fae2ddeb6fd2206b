"""The robot's side of a slow link: `gcdtrav relay` (credits, compact maps, freshness, the ROS camera)."""
