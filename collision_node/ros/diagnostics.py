"""The node's health on ``/diagnostics``: its status as a diagnostic_msgs/DiagnosticStatus.

A pure conversion of the JSON-ready status mapping (``status.status_report``)
so monitoring tools (rqt_runtime_monitor, diagnostic_aggregator) see the
node's health beside the JSON ``status`` topic. Level:

- ERROR when the world stopped on a non-finite state (``error`` set) or the
  energy balance error exceeds ``BALANCE_TOLERANCE`` of the energies
  involved (or is not finite);
- WARN when the physics does not keep up with the requested real-time factor;
- OK otherwise (also while paused).

The message names every reason, most severe first; the values carry the
numbers a monitor plots.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

# Relative energy-balance error beyond which the world is reported broken: the
# tests hold it below 1e-9, so 1e-6 is far past rounding.
BALANCE_TOLERANCE = 1e-6


def energy_scale(energy: Mapping[str, Any]) -> float:
    """Return the size of the energies in a balance (J): start, spawned, now, dissipated."""
    now = sum(abs(energy.get(k, 0.0)) for k in ('kinetic_linear', 'kinetic_rotational',
                                                'potential'))
    brought = abs(energy.get('start', 0.0)) + abs(energy.get('spawned', 0.0))
    lost = sum(abs(v) for v in energy.get('dissipated', {}).values())
    return max(now, brought, lost)


def relative_balance_error(energy: Mapping[str, Any]) -> float:
    """Return |balance_error| over the energies involved (0 for an empty, still world)."""
    error = abs(energy['balance_error'])
    scale = energy_scale(energy)
    if scale > 0.0:
        return error / scale
    return 0.0 if error == 0.0 else math.inf


def _text(value: Any) -> str:
    """Format a value for a KeyValue: full float precision, lower-case booleans."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float):
        return repr(value)
    return str(value)


def diagnostic_status(status: Mapping[str, Any], name: str) -> DiagnosticStatus:
    """Return the DiagnosticStatus of a node status mapping; ``name`` names the node."""
    relative = relative_balance_error(status['energy'])
    errors, warnings = [], []
    if status.get('error'):
        errors.append(f'stopped: {status["error"]}')
    if not relative <= BALANCE_TOLERANCE:   # also catches NaN
        errors.append(f'energy balance error {relative:.3g} of the energy '
                      f'(limit {BALANCE_TOLERANCE:g})')
    if not status.get('keeping_up', True):
        warnings.append(f'not keeping up with real-time factor '
                        f'{status["real_time_factor"]:g} (measured '
                        f'{status["measured_real_time_factor"]:.3g})')
    if errors:
        level = DiagnosticStatus.ERROR
    elif warnings:
        level = DiagnosticStatus.WARN
    else:
        level = DiagnosticStatus.OK
    reasons = errors + warnings
    if not reasons:
        reasons = ['paused' if status.get('paused') else 'running']
    values = {
        'scene': status['scene'],
        'particles': status['particles'],
        'time': status['time'],
        'steps': status['steps'],
        'paused': bool(status.get('paused', False)),
        'real_time_factor': status['real_time_factor'],
        'measured_real_time_factor': status['measured_real_time_factor'],
        'keeping_up': bool(status.get('keeping_up', True)),
        # Wall seconds of backlog given up while behind (0 when the node never dropped any).
        'dropped_backlog_s': float(status.get('dropped_backlog_s', 0.0)),
        'fallback_steps': status['fallback_steps'],
        'collisions_per_second': status['collisions_per_second'],
        'energy_balance_error': float(status['energy']['balance_error']),
        'energy_balance_relative_error': relative,
        'error': status.get('error') or '',
    }
    return DiagnosticStatus(
        level=level, name=name, message='; '.join(reasons), hardware_id=status['scene'],
        values=[KeyValue(key=key, value=_text(value)) for key, value in values.items()])


def diagnostic_array(status: Mapping[str, Any], name: str, stamp: Time) -> DiagnosticArray:
    """Return the DiagnosticArray holding the node's one DiagnosticStatus, stamped ``stamp``."""
    array = DiagnosticArray(status=[diagnostic_status(status, name)])
    array.header.stamp = stamp
    return array
