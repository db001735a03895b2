"""Recordings of a run as rosbag2 bags (MCAP storage), for ``ros2 bag`` and the usual tools.

``bag`` writes the bag (the MCAP file and ``metadata.yaml``) from CDR
bytes, ``definitions`` reads the message definitions it embeds from the
installed interface packages, ``recorder`` holds the recorded topics and
writes the node's messages (built by :mod:`msg_adapters`), and ``offline``
schedules the offline runner's frames. The physics knows nothing of it.
"""
