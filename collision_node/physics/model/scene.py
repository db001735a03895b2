"""Scene files (YAML): the one format for the runner, the node and the benchmarks.

``load_scene`` reads a file or a shipped scene name, ``parse_scene`` checks
a mapping, ``parse_spawn`` checks a spawn request against the same particle
schema. All of them raise :class:`SceneError` with one line naming the
source, the particle index and the field.
"""

from __future__ import annotations

import os
import stat
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Union

from .accuracy import AccuracySettings, check_event_mode, parse_accuracy
from .effects import Effects, check_particles_for_effects, parse_effects
from .generate import generate_state, parse_generate
from .particles import PARTICLE_KEYS, build_state, parse_particle
from .state import ParticleState
from .guard import parse_text, read_text_file
from .validation import SceneError, fail, number, quote, reject_unknown_keys, require_mapping

SCENE_KEYS = ('name', 'dimensions', 'dt', 'duration', 'accuracy', 'effects', 'particles',
              'generate')
DEFAULT_DT = 1.0 / 240.0
DEFAULT_DURATION = 1.0
# Longest step, s: a coarser step tunnels through anything (ccd aside) and is
# almost surely a unit error.
MAX_DT = 1.0
# Shortest step, s (1 ns): a micrometre pile steps at 4 us, so less is a unit
# error, and as dt goes to 0 the node's steps per tick (wall x factor / dt)
# and the runner's duration / dt overflow.
MIN_DT = 1e-9
MAX_NAME = 100
# Most particles one scene, or one spawn request, may hold (its particles and
# generate entries together; the node's max_particles bounds the world too):
# at about 200 bytes of state and step buffers each, 10^7 is 2 GB, and a
# 1 MiB scene of generate entries could otherwise ask for 10^11.
MAX_SCENE_PARTICLES = 10_000_000


@dataclass(frozen=True)
class Scene:
    """A validated scene: settings plus the initial particle state."""

    name: str
    dimensions: int
    dt: float
    duration: float
    accuracy: AccuracySettings
    effects: Effects
    initial: ParticleState
    source: str

    def with_accuracy(self, accuracy: AccuracySettings) -> 'Scene':
        """Return the same scene under other accuracy settings (checked against it)."""
        check_event_mode(accuracy, self.effects, f'{self.source}: accuracy')
        return Scene(self.name, self.dimensions, self.dt, self.duration, accuracy,
                     self.effects, self.initial, self.source)


def shipped_scene_dirs() -> list[Path]:
    """Directories that may hold the scenes shipped with the package.

    In a source checkout (or an editable install) they sit beside the
    package; in a colcon or pip install they live under the prefix's
    ``share/collision_node/scenes``.
    """
    here = Path(__file__).resolve().parent
    # The package's own prefix first: a colcon install beside a venv that has
    # the package registered too must read its own scenes.
    candidates = [here.parents[1] / 'scenes']
    candidates += [parent / 'share' / 'collision_node' / 'scenes' for parent in here.parents]
    candidates.append(Path(sys.prefix) / 'share' / 'collision_node' / 'scenes')
    return [c for c in candidates if c.is_dir()]


def shipped_scene_names() -> list[str]:
    """Names of the shipped scenes (file names without ``.yaml``)."""
    names: set[str] = set()
    for directory in shipped_scene_dirs():
        names.update(p.stem for p in directory.glob('*.yaml'))
    return sorted(names)


# What a path is when it is not a regular file, by its stat mode.
_FILE_KINDS = ((stat.S_ISDIR, 'a directory'), (stat.S_ISCHR, 'a character device'),
               (stat.S_ISBLK, 'a block device'), (stat.S_ISFIFO, 'a named pipe (FIFO)'),
               (stat.S_ISSOCK, 'a socket'))


def resolve_scene_path(path_or_name: Union[str, Path]) -> Path:
    """Find a scene by file path, or by the name of a shipped scene.

    A path that exists but is not a regular file (a directory, a device, a
    pipe) is refused saying what it is, before it is opened: reading a FIFO
    would block and a device may never end.
    """
    path = Path(path_or_name)
    mode: Optional[int] = None
    missing, reason = True, ''
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError) as error:        # ValueError: a NUL in the path
        mode, reason = None, getattr(error, 'strerror', None) or 'not a valid path'
        missing = isinstance(error, FileNotFoundError)
    if mode is not None and stat.S_ISREG(mode):
        return path
    for directory in shipped_scene_dirs():
        candidate = directory / f'{path_or_name}.yaml'
        if candidate.is_file():
            return candidate
    if mode is not None:
        kind = next((name for test, name in _FILE_KINDS if test(mode)), 'not a regular file')
        raise SceneError(f'{path_or_name}: is {kind}, not a scene file (a scene is a regular '
                         'YAML file)')
    if not missing:
        raise SceneError(f'{path_or_name}: cannot read: {reason}')
    raise SceneError(f'{path_or_name}: no such scene file or shipped scene '
                     f'(shipped: {", ".join(shipped_scene_names()) or "none found"})')


def load_scene(path_or_name: Union[str, Path]) -> Scene:
    """Read and validate a scene file (or a shipped scene by name)."""
    path = resolve_scene_path(path_or_name)
    text = read_text_file(path, str(path))
    return parse_scene_text(text, str(path), default_name=path.stem)


def parse_scene_text(text: str, source: str, default_name: str = 'scene') -> Scene:
    """Parse YAML (or JSON, a subset of YAML) text into a scene."""
    return parse_scene(parse_text(text, source, 'YAML'), source, default_name)


def parse_scene(data: Any, source: str, default_name: str = 'scene') -> Scene:
    """Validate a scene mapping; ``source`` prefixes every error message."""
    data = require_mapping(data, source)
    reject_unknown_keys(data, SCENE_KEYS, source, separator=': ')
    name = data.get('name', default_name)
    if not isinstance(name, str) or not name:
        fail(f'{source}: name', f'expected a non-empty string, got {quote(name)}')
    if len(name) > MAX_NAME or not name.isprintable():
        # The name goes into every summary, log line and status message.
        fail(f'{source}: name', f'expected at most {MAX_NAME} printable characters on one '
                                f'line, got {quote(name)}')
    dimensions = data.get('dimensions', 3)
    if dimensions not in (2, 3) or isinstance(dimensions, bool):
        fail(f'{source}: dimensions', f'must be 2 or 3, got {quote(dimensions)}')
    dt = number(data.get('dt', DEFAULT_DT), f'{source}: dt', minimum=0.0,
                exclusive_minimum=True, maximum=MAX_DT)
    if dt < MIN_DT:
        fail(f'{source}: dt', f'must be >= {MIN_DT:g} s, got {dt:g}')
    duration = number(data.get('duration', DEFAULT_DURATION), f'{source}: duration',
                      minimum=0.0)
    accuracy = parse_accuracy(data.get('accuracy'), f'{source}: accuracy')
    effects = parse_effects(data.get('effects'), f'{source}: effects', dimensions)
    check_event_mode(accuracy, effects, f'{source}: accuracy')
    state = parse_particle_section(data.get('particles'), data.get('generate'), source,
                                   dimensions, first_id=0)
    check_particles_for_effects(state, effects, f'{source}: ')
    return Scene(name=name, dimensions=dimensions, dt=dt, duration=duration,
                 accuracy=accuracy, effects=effects, initial=state, source=source)


def parse_particle_section(particles: Any, generate: Any, source: str, dimensions: int,
                           first_id: int, max_particles: Optional[int] = None
                           ) -> ParticleState:
    """Validate ``particles`` and ``generate`` lists and build their state.

    A section of more than ``MAX_SCENE_PARTICLES``, or one that would take
    the world past ``max_particles``, is refused after validation but before
    any particle is generated, so a huge ``generate`` count costs no memory.
    """
    if particles is None:
        particles = []
    if not isinstance(particles, list):
        fail(f'{source}: particles', f'expected a list, got {type(particles).__name__}')
    records = [parse_particle(spec, f'{source}: particles[{index}]', dimensions, PARTICLE_KEYS)
               for index, spec in enumerate(particles)]
    state = build_state(records, first_id)
    if generate is None:
        generate = []
    if not isinstance(generate, list):
        fail(f'{source}: generate', f'expected a list, got {type(generate).__name__}')
    specs = [parse_generate(spec, f'{source}: generate[{index}]', dimensions)
             for index, spec in enumerate(generate)]
    requested = len(records) + sum(spec['count'] for spec in specs)
    if requested > MAX_SCENE_PARTICLES:
        fail(source, f'{requested} particles are over the limit of {MAX_SCENE_PARTICLES} '
                     'one scene or request may hold')
    if max_particles is not None and first_id + requested > max_particles:
        fail(source, f'{requested} particles would make {first_id + requested}, '
                     f'over max_particles = {max_particles}')
    for spec in specs:
        state = state.concatenate(generate_state(spec, dimensions, first_id + len(state)))
    return state


def parse_request(text: str, source: str) -> Any:
    """Parse a request's text (YAML or JSON) into plain data: every command goes through here.

    Spawn, delete, teleport, impulse and step requests all use this one
    function, so every text a user sends meets the same bounded gate
    (:func:`guard.parse_text`: size, depth, aliases; JSON through the C
    parser first, then libyaml) and the same one-line errors.
    """
    return parse_text(text, source, 'YAML or JSON')


def parse_spawn(text: str, dimensions: int, first_id: int, source: str = 'spawn',
                max_particles: Optional[int] = None) -> ParticleState:
    """Validate a spawn request (YAML or JSON) with the scene's particle schema.

    Accepted: one particle mapping, a list of them, one ``generate`` entry
    (a mapping with ``kind``), or ``{particles: [...], generate: [...]}``.
    ``max_particles`` bounds the world's size after the spawn; ``first_id``
    is the world's particle count (the new ids and the bound count from it).
    """
    return parse_spawn_data(parse_request(text, source), dimensions, first_id, source,
                            max_particles)


def parse_spawn_data(data: Any, dimensions: int, first_id: int, source: str = 'spawn',
                     max_particles: Optional[int] = None) -> ParticleState:
    """Validate already parsed spawn data (see :func:`parse_spawn`)."""
    if isinstance(data, list):
        return parse_particle_section(data, None, source, dimensions, first_id, max_particles)
    data = require_mapping(data, source)
    if 'kind' in data:
        return parse_particle_section(None, [data], source, dimensions, first_id,
                                      max_particles)
    if 'particles' in data or 'generate' in data:
        reject_unknown_keys(data, ('particles', 'generate'), source, separator=': ')
        return parse_particle_section(data.get('particles'), data.get('generate'), source,
                                      dimensions, first_id, max_particles)
    return parse_particle_section([data], None, source, dimensions, first_id, max_particles)


__all__ = ['Scene', 'SceneError', 'load_scene', 'parse_request', 'parse_scene',
           'parse_scene_text', 'parse_spawn', 'parse_spawn_data', 'shipped_scene_names']
