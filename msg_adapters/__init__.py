"""Pure conversions between numpy particle state and ROS 2 messages (no node logic)."""
