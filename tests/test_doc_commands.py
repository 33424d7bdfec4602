"""The example commands of README.md and docs/bring-up.md work as written.

Every command of their fenced ``bash`` blocks is parsed as a shell would (continuation
lines joined, comments, quotes, ``&&``/``;``/``|`` and redirections; a here-document is the
input of its command, not commands): its program is a ``scripts/`` front door that exists
and is executable, or one of a few shell utilities; each ``--option`` it uses is one its
``--help`` lists (``scripts/demo`` passes its options to run_graph); a file of the
repository it names (``scenarios/...``, ``tests/...``) exists. A command that needs a
robot (hardware mode, ``check_base``) or a ROS 2 install (``ros2``) cannot run here: its
block must carry the marker :data:`NEEDS_A_ROBOT` on the line before the fence, or start
the stand-in base in the same block.

Also: the README's params file describes the shipped stand-in base (its defaults).
"""

import os
import pathlib
import re
import shlex
import subprocess

import pytest
import yaml

REPO_ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCS = ('README.md', 'docs/bring-up.md')
NEEDS_A_ROBOT = '<!-- example: needs a robot -->'
SEPARATORS = {'&&', '||', ';', '|', '&'}
REDIRECTIONS = {'>', '>>', '<', '2>', '&>'}
#: Programs that are not front doors: the shell's own, and the venv's Python.
SHELL = {'printf', 'echo', 'export', 'source', 'cd', 'mkdir', 'cat', 'python', 'kill'}
#: The front doors whose options go on to another one.
PASSES_ON = {'demo': 'run_graph'}


def blocks(text: str):
    """Yield (line before the fence, [(line number, line), ...]) of each bash block."""
    lines = text.split('\n')
    i = 0
    while i < len(lines):
        if lines[i].strip() == '```bash':
            before = next((line.strip() for line in reversed(lines[:i]) if line.strip()), '')
            j, body = i + 1, []
            while lines[j].strip() != '```':
                body.append((j + 1, lines[j]))
                j += 1
            yield before, body
            i = j
        i += 1


def commands(body):
    """Yield (line number, tokens) of each simple command of a block."""
    joined, start, heredoc = '', None, None
    for number, line in body:
        if heredoc is not None:
            heredoc = None if line.strip() == heredoc else heredoc
            continue
        match = re.search(r"<<-?\s*'?(\w+)'?", line)
        if match:
            heredoc, line = match.group(1), line[:match.start()]
        start = number if start is None else start
        if line.rstrip().endswith('\\'):
            joined += line.rstrip()[:-1] + ' '
            continue
        lexer = shlex.shlex(joined + line, posix=True, punctuation_chars=True)
        lexer.whitespace_split, lexer.commenters = True, '#'
        current, skip = [], False
        for token in [*lexer, ';']:
            if skip:
                skip = False
            elif token in SEPARATORS:
                if current:
                    yield start, current
                current = []
            elif token in REDIRECTIONS:
                skip = True
            else:
                current.append(token)
        joined, start = '', None


def documented_commands():
    """[(doc, line, marked, tokens)] of every command of the documents' bash blocks.

    ``marked``: the block carries :data:`NEEDS_A_ROBOT`, or starts the stand-in base
    (``scripts/ros2_run wip_sim standin_base``), which is a robot for hardware mode.
    """
    found = []
    for doc in DOCS:
        for before, body in blocks((REPO_ROOT / doc).read_text(encoding='utf-8')):
            block = []
            for number, tokens in commands(body):
                while tokens and re.fullmatch(r'\w+=.*', tokens[0]):
                    tokens = tokens[1:]     # VAR=value before the program
                if tokens:
                    block.append((number, tokens))
            standin = any(tokens[:3] == ['scripts/ros2_run', 'wip_sim', 'standin_base']
                          for _, tokens in block)
            found += [(doc, number, before == NEEDS_A_ROBOT or standin, tokens)
                      for number, tokens in block]
    return found


COMMANDS = documented_commands()


def front_door(tokens) -> str | None:
    match = re.fullmatch(r'scripts/(\w+)', tokens[0])
    return match.group(1) if match else None


@pytest.fixture(scope='module')
def helps(script_helps):
    """``scripts/NAME --help`` of every front door the documents use (the session's runs)."""
    names = {front_door(tokens) for _, _, _, tokens in COMMANDS} - {None}
    names |= {PASSES_ON[name] for name in names if name in PASSES_ON}
    return {name: script_helps[name][:2] for name in sorted(names) if name in script_helps}


def test_the_documents_have_commands_to_check():
    programs = {tokens[0] for _, _, _, tokens in COMMANDS}
    assert {'scripts/demo', 'scripts/run_graph', 'scripts/check_base'} <= programs
    assert len(COMMANDS) >= 25


@pytest.mark.parametrize('doc, line, marked, tokens', COMMANDS,
                         ids=[f'{doc}:{line}' for doc, line, _, _ in COMMANDS])
def test_each_example_command_is_accepted_as_written(doc, line, marked, tokens, helps):
    where = f'{doc}:{line}: {shlex.join(tokens)}'
    name = front_door(tokens)
    needs_robot = (tokens[0] == 'ros2' or name == 'check_base'
                   or any(a == '--mode' and b == 'hardware' for a, b in zip(tokens, tokens[1:])))
    if needs_robot:
        assert marked, f'{where}: needs a robot; put {NEEDS_A_ROBOT} before its block'
    if name is None:
        assert tokens[0] in SHELL or (marked and tokens[0] == 'ros2'), \
            f'{where}: {tokens[0]} is no scripts/ front door'
        return
    status, text = helps.get(name, (None, ''))
    assert status == 0, f'{where}: scripts/{name} does not exist or its --help failed:\n{text}'
    if name in PASSES_ON:
        text += helps[PASSES_ON[name]][1]
    options = {token.split('=', 1)[0] for token in tokens[1:] if token.startswith('--')}
    accepted = set(re.findall(r'(?<![\w-])--[\w-]+', text))
    assert options <= accepted, f'{where}: {sorted(options - accepted)} not in its --help'
    for token in tokens[1:]:
        if re.match(r'(scenarios|tests|campaigns)/[\w./-]+$', token) and token.upper() != token \
                and 'FILE' not in token:
            assert (REPO_ROOT / token).exists(), f'{where}: {token} does not exist'


def test_the_readme_params_file_is_the_shipped_standin_base():
    # What the stand-in base uses unless told otherwise: its wiring parameters' defaults,
    # the scenario's sensors (GPS datum, encoders) and its plant's wheel radius and track.
    import dataclasses
    from wip_description.wiring import EffortCommand, ImuMounting, WheelJoints, WheelSigns
    from wip_sim.core.scenario import Scenario
    readme = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    block = next(b for b in re.findall(r'```yaml\n(.*?)```', readme, re.S)
                 if 'right_wheel_sign' in b)
    params = yaml.safe_load(block)['/**']['ros__parameters']
    scenario = Scenario()
    expected = {**dataclasses.asdict(WheelJoints()), **dataclasses.asdict(EffortCommand()),
                **dataclasses.asdict(WheelSigns()), **dataclasses.asdict(ImuMounting()),
                'encoders_relative_to_body': scenario.sensors.encoders_relative_to_body,
                'position_source': 'gps',
                'datum.latitude': scenario.sensors.gps_datum_latitude,
                'datum.longitude': scenario.sensors.gps_datum_longitude,
                'datum.altitude': scenario.sensors.gps_datum_altitude,
                'model.wheel_radius': scenario.plant.parameters.wheel_radius,
                'model.track_width': scenario.plant.parameters.track_width}
    assert set(params) == set(expected)
    for key, value in expected.items():
        got = params[key]
        assert (list(got) == list(value) if isinstance(value, (list, tuple))
                else got == pytest.approx(value)), key


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.wallclock
def test_the_readme_standin_example_runs_as_written(tmp_path):
    # The README's params file saved as my_base.yaml and its stand-in block run by bash,
    # as a newcomer would paste them (scripts/ made absolute: the folder is a scratch one),
    # in a domain of its own on localhost: run_graph's exit 0 says the controllers engaged
    # and nothing faulted (no fall, no wiring fault) for the 20 s.
    pytest.importorskip('rclpy')
    from wip_bringup.private_domain import release_private_domain, reserve_private_domain
    readme = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    (tmp_path / 'my_base.yaml').write_text(next(
        b for b in re.findall(r'```yaml\n(.*?)```', readme, re.S) if 'right_wheel_sign' in b))
    block = next('\n'.join(line for _, line in body) for _, body in blocks(readme)
                 if any('standin_base' in line for _, line in body))
    script = re.sub(r'(?<![\w/])scripts/', f'{REPO_ROOT}/scripts/', block)
    domain, descriptor = reserve_private_domain()
    env = {k: v for k, v in os.environ.items() if not k.startswith(('ROS_', 'WIP_ROS'))}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    try:
        # set -e: the block's status is run_graph's; the trap stops a stand-in left over.
        done = subprocess.run(['bash', '-c', 'set -e; trap "kill %1 2>/dev/null || true" '
                               'EXIT\n' + script], cwd=tmp_path, env=env, text=True,
                              capture_output=True, timeout=300)
    finally:
        release_private_domain(descriptor)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert 'OK: the duration of 20 s was reached' in done.stdout + done.stderr
