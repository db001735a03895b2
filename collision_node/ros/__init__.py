"""The ROS 2 front ends: the node, the viewer, and what they share (QoS, pacing, status)."""
