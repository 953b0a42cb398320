"""ROS 2 nodes: thin adapters that wire parameters, topics and messages to the core."""
