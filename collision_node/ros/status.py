"""The node's status: one JSON-ready mapping of the world and the node's settings."""

from __future__ import annotations

from typing import Any, Optional

from ..physics.step.world import World


def status_report(world: World, scene_name: str, rates: tuple[float, float], *,
                  paused: bool, real_time_factor: float, keeping_up: bool,
                  publish_rate: float, frame_id: str, error: Optional[str]) -> dict[str, Any]:
    """Return the status: ``rates`` is (measured real-time factor, collisions per second)."""
    rtf, collision_rate = rates
    stats = world.stats
    return {
        'scene': scene_name,
        'particles': len(world.state),
        'time': world.time,
        'steps': world.steps,
        'dt': world.dt,
        'paused': paused,
        'real_time_factor': real_time_factor,
        'measured_real_time_factor': rtf,
        'keeping_up': keeping_up,
        'collisions': stats.collisions,
        'wall_collisions': stats.wall_collisions,
        'fallback_steps': stats.fallback_steps,
        # Particles asleep now (sleeping islands, accuracy sleep_time).
        'asleep': world.asleep_count,
        # True while particles/collisions has a subscriber and impacts are recorded.
        'recording_impacts': world.impact_log is not None,
        'collisions_per_second': collision_rate,
        'kinetic_energy': world.kinetic_energy(),
        # Energy balance (docs/api.md): terms, losses per effect, error.
        'energy': world.energy(),
        'momentum': world.momentum().tolist(),
        'publish_rate': publish_rate,
        'frame_id': frame_id,
        'error': error,
    }
