"""collision_node: impulse collisions between spherical particles.

``collision_node.physics`` is the core: pure numpy and numba, no ROS
module; its public names are re-exported here (docs/api.md). ``collision_node.ros``
holds the ROS 2 front ends (the node and the viewer), ``collision_node.simulate``
the offline runner, and ``collision_node.bench`` the benchmarks.
"""

from .physics import (IMPACT_DTYPE, PRESETS, AccuracySettings, Drag, Effects, Gas,
                      NonFiniteStateError, Particle, ParticleState, Scene, SceneError,
                      StageTime, StepProfile, StepStats, Walls, World, build_scene, load_scene,
                      parse_scene, parse_scene_text, parse_spawn, scene_mapping, walls_box)

__all__ = ['IMPACT_DTYPE', 'PRESETS', 'AccuracySettings', 'Drag', 'Effects', 'Gas',
           'NonFiniteStateError', 'Particle', 'ParticleState', 'Scene', 'SceneError',
           'StageTime', 'StepProfile', 'StepStats', 'Walls', 'World', 'build_scene',
           'load_scene', 'parse_scene', 'parse_scene_text', 'parse_spawn', 'scene_mapping',
           'walls_box']
