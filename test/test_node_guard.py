"""The node refuses what it cannot take in one line: a bad scene file, argument or setting.

A scene file that is not a scene: exit 2, one line, nothing echoed. An
argument rcl rejects, a setting past its bound: exit 2, one line. A step
that runs out of memory: a refusal or an ERROR diagnostic, never a traceback.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
import tempfile

import node_harness
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter
from std_msgs.msg import Empty, String
from std_srvs.srv import SetBool

from collision_node.physics.model.scene import load_scene
from collision_node.physics.step.world import World
from collision_node.ros.commands import CommandInterface, LogBudget
from msg_adapters.strings import string_bytes, string_text
from node_harness import executable, InProcessNode, NodeUnderTest, ros_env, unique_domain_id

# Starts ROS processes or tests a ROS front end: `-m "not ros"` leaves it out.
pytestmark = pytest.mark.ros

SECRET = 'root:$6$saltsalt$0123456789abcdef:19000:0:99999:7:::'


@pytest.mark.parametrize('content, says', [
    ('[' * 5000, 'nested deeper than 32 levels (line 1, column 33)'),
    (SECRET + '\ndaemon:*:19000:0:99999:7:::\n', 'a key that is not a field name'),
    ('root:x:0:0:root:/root:/bin/bash\n', 'expected a mapping, got str'),
    (b'\x7fELF\x02\x01\x01\x00' + SECRET.encode() + b'\xff', 'not UTF-8 text'),
    ('particles: [{position: &p [0, 0, 0], radius: 1, mass: 1}, '
     '{position: *p, radius: 1, mass: 1}]\n', 'YAML aliases (*name) are not accepted'),
], ids=['deep', 'shadow', 'passwd', 'binary', 'alias'])
def test_scene_file_that_is_not_a_scene_stops_the_node_with_one_line(tmp_path, content, says):
    path = tmp_path / 'scene.yaml'
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    result = subprocess.run(
        [executable('collision_node'), '--ros-args', '-p', f'scene:={path}'],
        env=ros_env(unique_domain_id()), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr[-2000:]
    assert 'Traceback' not in result.stderr and len(result.stderr) < 1000
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and '[ERROR]' in lines[0], lines
    assert f'[collision_node]: {path}: ' in lines[0]
    reason = lines[0].split(f'{path}: ', 1)[1]
    assert says in reason
    for word in ('root', 'salt', '0123', 'daemon', 'ELF', '[['):
        assert word not in reason, reason


# -- arguments rcl rejects: one line naming the argument, exit 2 ----------------------

def run_node(*args: str) -> subprocess.CompletedProcess:
    """Run the installed node with ``args`` until it exits."""
    return subprocess.run([executable('collision_node'), *args], capture_output=True,
                          text=True, timeout=60, env=ros_env(unique_domain_id()))


def refusal_of(result: subprocess.CompletedProcess) -> str:
    """Return the one stderr line of a node that refused its command line."""
    assert result.returncode == 2, result.stderr[-2000:]
    assert 'Traceback' not in result.stderr and 'RCLError' not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith('collision_node: error: ')
    return lines[0][len('collision_node: error: '):]


SHELL_WORD = ("write -p NAME:=VALUE as one shell word; the value is YAML, so a mapping or "
              """text with spaces is quoted: -p "accuracy:='{preset: fast, substeps: 2}'\"""")


@pytest.mark.parametrize('args, says', [
    # The mapping unquoted, as a shell splits it, and quoted for the shell only.
    (['-p', 'accuracy:={preset:', 'fast,', 'substeps:', '2}'],
     "bad ROS argument '-p accuracy:={preset:': not a valid parameter override rule "
     f'(Unknown YAML event); {SHELL_WORD}'),
    (['-p', 'accuracy:={preset: fast, substeps: 2}'],
     "bad ROS argument '-p accuracy:={preset: fast, substeps: 2}': not a valid parameter "
     f'override rule (Unknown YAML event); {SHELL_WORD}'),
    (['-p', 'scene:=[unclosed'],
     "bad ROS argument '-p scene:=[unclosed': not a valid parameter override rule "
     f'(Error parsing an event); {SHELL_WORD}'),
    (['-p'], "bad ROS argument: Couldn't parse trailing -p flag. No parameter override rule "
             'found (see --help)'),
    (['--params-file', '/nonexistent.yaml'], '--params-file /nonexistent.yaml: no such file'),
    (['--params-file', 'TMP'], '--params-file TMP: is a directory, not a parameters file'),
    (['--params-file', 'TMP/bad.yaml'],
     '--params-file TMP/bad.yaml: not a valid parameters file (Sequences can only be values '
     'and not keys in params. Error at line 1)'),
    (['-r', 'foo'], "bad ROS argument '-r foo': not a valid remap rule (Expected lexeme type "
                    '(19) not found, search ended at index 3); a remap is -r FROM:=TO, e.g. '
                    '-r __ns:=/table'),
    (['-r', '__ns:=relative'],
     "bad ROS argument '-r __ns:=relative': not a valid remap rule (Namespace not remapped "
     'to a fully qualified name (found: relative)); a remap is -r FROM:=TO, e.g. '
     '-r __ns:=/table'),
    (['--log-level', 'loud'],
     "bad ROS argument '--log-level loud': not a valid log level (Argument does not use a "
     'valid severity level); see --help'),
    (['--frobnicate', '-x'],
     'unknown ROS arguments: --frobnicate -x (after --ros-args: -p NAME:=VALUE, -r FROM:=TO, '
     '--params-file FILE; see --help)'),
], ids=['accuracy-split', 'accuracy-mapping', 'unclosed', 'trailing-p', 'no-params-file',
        'params-dir', 'params-malformed', 'remap', 'remap-ns', 'log-level', 'unknown'])
def test_ros_argument_rcl_rejects_is_one_line_naming_it_and_exit_2(tmp_path, args, says):
    (tmp_path / 'bad.yaml').write_text('a: [\n')
    args = [a.replace('TMP', str(tmp_path)) for a in args]
    assert refusal_of(run_node('--ros-args', *args)) == says.replace('TMP', str(tmp_path))


def test_the_accuracy_form_help_suggests_reaches_the_node():
    """The help's own example starts the node with its settings; past a bound it is refused."""
    help_text = run_node('--help').stdout
    example = """-p "accuracy:='{preset: fast, substeps: 2}'\""""
    assert example in help_text
    node = NodeUnderTest(shlex.split(example))
    try:
        assert node.status()['error'] is None
    finally:
        code, _, err = node.stop()
    assert code == 0, err
    assert 'up to 8 sweeps' in err                # fast's solver, not the scene's balanced
    too_many = example.replace('substeps: 2', 'substeps: 1000000000')
    result = subprocess.run([executable('collision_node'), '--ros-args', *shlex.split(too_many)],
                            env=ros_env(unique_domain_id()), capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2 and 'Traceback' not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].endswith(
        '[collision_node]: parameter accuracy.substeps: must be <= 1000, got 1000000000')


@pytest.mark.parametrize('parameter, says', [
    ("accuracy:='{preset: exact, event_budget: 9223372036854775807}'",
     'parameter accuracy.event_budget: must be <= 10000, got 9223372036854775807'),
    ("accuracy:='{preset: exact, event_budget: 1e300}'",
     'parameter accuracy.event_budget: must be <= 10000, got 1e+300'),
    ('max_particles:=10000001', 'Parameter max_particles out of range. Min: 1, Max: 10000000'),
])
def test_oversized_node_setting_stops_the_node_with_one_line(parameter, says):
    result = run_node('--ros-args', '-p', parameter)
    assert result.returncode == 2 and 'Traceback' not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and '[ERROR]' in lines[0] and says in lines[0], lines


# -- MemoryError in a step: a refusal or an ERROR diagnostic, never a traceback ----------

# The node's main with World.step out of memory once the world holds more than the
# default scene's 16 particles (one spawn makes it so, a reset undoes it).
OUT_OF_MEMORY_NODE = '''
import sys
from collision_node.physics.step.world import World
real_step = World.step
def step(self, *args, **kwargs):
    if len(self.state) > 16:
        raise MemoryError('Allocation failed (probably too large).')
    return real_step(self, *args, **kwargs)
World.step = step
from collision_node.ros.node import main
sys.exit(main(['collision_node', *sys.argv[1:]]))
'''
NO_MEMORY = '(MemoryError: Allocation failed (probably too large).)'


def start_out_of_memory(name: str, args: list[str], domain_id: int,
                        preexec=None) -> subprocess.Popen:
    """Start the node's main with the World.step above (as node_harness.start does)."""
    out, err = tempfile.TemporaryFile('w+'), tempfile.TemporaryFile('w+')
    process = subprocess.Popen([sys.executable, '-c', OUT_OF_MEMORY_NODE, *args],
                               env=ros_env(domain_id), stdout=out, stderr=err, text=True,
                               preexec_fn=preexec)
    process.output_files = (out, err)
    return process


def test_memory_error_in_a_step_request_and_in_a_tick_is_reported_in_one_line(monkeypatch):
    monkeypatch.setattr(node_harness, 'start', start_out_of_memory)
    node = NodeUnderTest(['-p', 'paused:=true'])
    try:
        diagnostics = node.probe.collect(DiagnosticArray, '/diagnostics', 10)
        spawn = String(data='{position: [0, 0.5], radius: 0.01, mass: 0.1, request_id: a}')
        assert node.request(String, 'spawn', spawn)['particles'] == 17
        # A step request: refused with the reason; stepping stops until a reset.
        answer = node.request(String, 'step', String(data='{steps: 3}'))
        assert not answer['accepted'] and answer['reason'] == (
            f'step: out of memory in step 1 of 3 {NO_MEMORY}; reset to go on')
        status = node.next_status(lambda s: s['error'] is not None)
        assert status['error'] == f'out of memory in step 1 of 3 {NO_MEMORY}'
        assert node.request(Empty, 'reset', Empty())['particles'] == 16
        assert node.next_status(lambda s: s['error'] is None)['particles'] == 16
        # A tick's step: the node stops stepping, says so once, and reports an ERROR.
        assert node.request(String, 'spawn', spawn)['particles'] == 17
        pause = node.probe.node.create_client(SetBool, 'pause')
        assert node.probe.call(pause, SetBool.Request(data=False)).success
        status = node.next_status(lambda s: s['error'] is not None)
        assert status['error'].startswith('out of memory in step ')
        assert status['error'].endswith(NO_MEMORY) and status['particles'] == 17
        report = node.probe.next_message(
            diagnostics, timeout=15.0,
            where=lambda m: m.status[0].level == DiagnosticStatus.ERROR).status[0]
        assert report.message == f'stopped: {status["error"]}'
    finally:
        code, _, err = node.stop()
    assert code == 0, err[-2000:]
    assert 'Traceback' not in err
    errors = [line for line in err.splitlines() if '[ERROR]' in line]
    assert len(errors) == 2, errors
    assert errors[0].endswith(f'stopped stepping: out of memory in step 1 of 3 {NO_MEMORY}; '
                              'reset to go on')
    assert errors[1].endswith(f'stopped stepping: {status["error"]}; reset to go on')


class _Logger:
    """Collects what the command interface logs, by level."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def warning(self, text: str) -> None:
        self.lines.append(('warning', text))

    def error(self, text: str) -> None:
        self.lines.append(('error', text))

    def info(self, text: str) -> None:
        self.lines.append(('info', text))


class _Node:
    """What CommandInterface.handle reads of the node: world, logger, pause state."""

    def __init__(self) -> None:
        self.world = World(load_scene('oblique_pair'))
        self.logger = _Logger()
        self.paused, self.failed = True, None
        self.reports = type('Reports', (), {'follow_listeners': lambda self, world: None})()

    def get_logger(self) -> _Logger:
        return self.logger


def command_interface() -> tuple[CommandInterface, _Node, list]:
    """Return a CommandInterface without ROS interfaces, its node, and its answers."""
    node, answers = _Node(), []
    commands = CommandInterface.__new__(CommandInterface)
    commands.node, commands.seq, commands._logged = node, 0, {}
    commands.log_budget = LogBudget(node.logger)
    commands.pub_events = type('Publisher', (), {
        'publish': lambda self, data: answers.append(json.loads(string_text(data)))})()
    return commands, node, answers


def test_memory_error_in_a_spawn_is_a_refusal_and_the_world_is_unchanged(monkeypatch):
    def no_memory(*args, **kwargs):
        raise MemoryError()
    commands, node, answers = command_interface()
    monkeypatch.setattr(World, 'spawn', no_memory)
    commands.handle('spawn', '{position: [0, 3, 0], radius: 0.1, mass: 1, request_id: 7}',
                    commands._spawn)
    assert answers == [{'seq': 1, 'request': 'spawn', 'request_id': 7, 'accepted': False,
                        'reason': 'spawn: out of memory handling the request (MemoryError)',
                        'particles': 2}]
    assert node.logger.lines == [
        ('warning', 'rejected spawn: out of memory handling the request (MemoryError)')]
    assert node.failed is None                   # nothing was stepped: stepping goes on


def test_memory_error_in_a_step_request_stops_stepping_with_one_error_line(monkeypatch):
    real_step = World.step

    def step(self, *args, **kwargs):
        if self.steps == 1:
            raise MemoryError('Allocation failed (probably too large).')
        return real_step(self, *args, **kwargs)
    monkeypatch.setattr(World, 'step', step)       # the stepping thread's steps too
    harness = InProcessNode([Parameter('paused', Parameter.Type.BOOL, True)])
    try:
        node, answers, logger = harness.node, [], _Logger()
        node.commands.pub_events = type('Publisher', (), {
            'publish': lambda self, data: answers.append(json.loads(string_text(data)))})()
        node.get_logger = lambda: logger
        node.commands.log_budget = LogBudget(logger)
        harness.deliver('step', string_bytes('{steps: 5}'))
        harness.spin_until(lambda: answers)
        assert node.world.steps == 1
        reason = f'out of memory in step 2 of 5 {NO_MEMORY}'
        assert answers[0]['accepted'] is False
        assert answers[0]['reason'] == f'step: {reason}; reset to go on'
        assert node.failed == reason
        assert logger.lines == [('error', f'stopped stepping: {reason}; reset to go on'),
                                ('warning', f'rejected step: {reason}; reset to go on')]
    finally:
        harness.close()
