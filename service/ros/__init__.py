"""ROS 2 message formats (CDR), topic names and rmw_zenoh key layouts, without middleware."""
