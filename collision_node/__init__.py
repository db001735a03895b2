"""collision_node: impulse collisions between spherical particles.

The core (everything importable from here) is pure numpy and imports no
ROS module; ``collision_node.node`` is the ROS 2 node built on top of it.
"""

from .scene import Scene, load_scene, parse_scene, parse_scene_text, parse_spawn
from .state import ParticleState
from .validation import SceneError
from .world import NonFiniteStateError, World

__all__ = ['NonFiniteStateError', 'ParticleState', 'Scene', 'SceneError', 'World',
           'load_scene', 'parse_scene', 'parse_scene_text', 'parse_spawn']
