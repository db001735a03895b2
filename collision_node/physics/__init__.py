"""The physics of collision_node: everything that computes, and no ROS module.

``model`` holds the data and settings (state, scene and validation,
effects, accuracy presets, energy, impacts), ``law`` the contact law's
compiled primitives, ``step`` the step's framework, plan, world and
profile, and ``stages`` one folder per stage beside its kernels. Nothing
in this package imports a module outside it (``test/test_core_imports.py``
checks both rules). The names below are the public API for offline use.
"""

from .model.accuracy import PRESETS, AccuracySettings
from .model.builder import Gas, Particle, build_scene, scene_mapping, walls_box
from .model.effects import Drag, Effects, Walls
from .model.impacts import IMPACT_DTYPE
from .model.scene import Scene, load_scene, parse_scene, parse_scene_text, parse_spawn
from .model.state import ParticleState
from .model.validation import SceneError
from .step.pipeline import StepStats
from .step.timing import StageTime, StepProfile
from .step.world import NonFiniteStateError, World

__all__ = ['IMPACT_DTYPE', 'PRESETS', 'AccuracySettings', 'Drag', 'Effects', 'Gas',
           'NonFiniteStateError', 'Particle', 'ParticleState', 'Scene', 'SceneError',
           'StageTime', 'StepProfile', 'StepStats', 'Walls', 'World', 'build_scene',
           'load_scene', 'parse_scene', 'parse_scene_text', 'parse_spawn', 'scene_mapping',
           'walls_box']
