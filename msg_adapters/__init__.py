"""Pure conversions between numpy particle state and ROS 2 messages (no node logic).

Outputs are serialised CDR ``bytes`` written straight from the numpy
arrays (``rclpy`` publishes bytes as an already serialised message);
the decoders read received message objects back into numpy arrays.
"""

from .cloud import point_cloud_bytes, records_from_point_cloud, state_from_point_cloud
from .collisions import impact_cloud_bytes, impacts_from_point_cloud
from .markers import marker_array_bytes
from .poses import pose_array_bytes, poses_from_pose_array
from .stamp import (clock_bytes, clock_message, nanoseconds_from_seconds, seconds_from_stamp,
                    stamp_from_seconds, time_message)
from .velocities import body_frame_id, particle_id_from_frame, velocities_bytes

__all__ = ['body_frame_id', 'clock_bytes', 'clock_message', 'impact_cloud_bytes',
           'impacts_from_point_cloud', 'marker_array_bytes', 'nanoseconds_from_seconds',
           'particle_id_from_frame', 'point_cloud_bytes', 'pose_array_bytes',
           'poses_from_pose_array', 'records_from_point_cloud', 'seconds_from_stamp',
           'stamp_from_seconds', 'state_from_point_cloud', 'time_message', 'velocities_bytes']
