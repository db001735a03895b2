"""collision_node: impulse collisions between spherical particles.

``collision_node.physics`` is the core: pure numpy, no ROS module; its
public names are re-exported here. ``collision_node.ros`` holds the ROS 2
front ends (the node and the viewer), ``collision_node.simulate`` the
offline runner, and ``collision_node.bench`` the benchmarks.
"""

from .physics import (NonFiniteStateError, ParticleState, Scene, SceneError, World, load_scene,
                      parse_scene, parse_scene_text, parse_spawn)

__all__ = ['NonFiniteStateError', 'ParticleState', 'Scene', 'SceneError', 'World',
           'load_scene', 'parse_scene', 'parse_scene_text', 'parse_spawn']
