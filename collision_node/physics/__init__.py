"""The physics of collision_node: everything that computes, and no ROS module.

State, scene and validation, effects, accuracy presets, the world, the
step's framework (``step``), its plan (``plan``) and stages (``stages/``),
and energy. Nothing in this package imports a module outside it (the
layout test in ``test/test_core_imports.py`` checks both rules).
"""

from .model.scene import Scene, load_scene, parse_scene, parse_scene_text, parse_spawn
from .model.state import ParticleState
from .model.validation import SceneError
from .step.world import NonFiniteStateError, World

__all__ = ['NonFiniteStateError', 'ParticleState', 'Scene', 'SceneError', 'World',
           'load_scene', 'parse_scene', 'parse_scene_text', 'parse_spawn']
