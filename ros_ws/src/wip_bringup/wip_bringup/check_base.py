"""``scripts/check_base``: check a real base's signs, joint names and IMU mounting by hand.

The guided session (:class:`Session`) and the command line; the checks are
:mod:`wip_bringup.base_checks`, the listener :mod:`wip_bringup.base_listener`. The steps, the
modes and what each check compares: docs/check_base.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import signal
import sys
import threading
import time
from typing import Any, Callable, TextIO

from wip_runtime.config import ParamError
from wip_control.core.controller_settings import load_controller_settings
from wip_runtime.cli import add_exit_codes

from .base_checks import (AUTO_STILL_TIME, Check, check_connection, check_tilt, check_turn,
                          check_upright, check_wheel, Conventions, FAIL, OK, Reading, SKIP,
                          STILL_CHANGE, TILT_EXPECTED, TWO_PI, WARN)
from .base_listener import BaseListener, LISTENED_TOPICS
from .hardware_params import (hardware_parameters, load_params_file, node_parameters,
                              parse_remap)
from .launcher import GraphError, use_user_ros_environment
from .params_check import check_run_inputs, unmatched_remaps
from .params_files import CONTROLLER_NODES


# The exit-code table of every tool (wip_runtime.cli); no data from the base is a
# failed check (the connection check).
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_NO_DATA = EXIT_FAILED


def eso_parameters(scenario_path: str | None, params_files: list[str]) -> dict[str, Any]:
    """Return the eso node's parameters in hardware mode: the scenario's, then the files'."""
    try:
        scenario = load_controller_settings(scenario_path)
    except ParamError as err:
        raise GraphError(str(err), EXIT_USAGE) from err
    extra = [load_params_file(path) for path in params_files]
    generated = hardware_parameters(scenario)
    # The same files run_graph --mode hardware takes: checked against every controller.
    for line in check_run_inputs(params_files, extra, CONTROLLER_NODES, generated, []):
        print(f'check_base: warning: {line}', file=sys.stderr)
    return node_parameters('eso', generated, extra)


# ----------------------------------------------------------------------------- the session

STEPS = (
    ('upright', 'Hold the robot upright (balanced, wheels on the ground) and still.', None),
    ('tilt', 'Tilt the robot FORWARD (its top toward the direction it drives) by about '
             '10 degrees and hold it there.', 'pitch'),
    ('left_wheel', 'Lift the robot so that the wheels turn freely. Roll the LEFT wheel '
                   'FORWARD (the way that drives the robot forward) by one full turn.',
     'left'),
    ('right_wheel', 'Still lifted: roll the RIGHT wheel FORWARD by one full turn.', 'right'),
    ('turn', 'Put the robot on the ground and turn it COUNTER-CLOCKWISE (seen from above) '
             'by about 90 degrees on the spot.', 'yaw'),
)
#: --auto: the motion is seen when its quantity changed by this much [rad].
AUTO_MOTION = {'pitch': TILT_EXPECTED / 3, 'left': TWO_PI / 3, 'right': TWO_PI / 3,
               'yaw': math.pi / 6}


class Aborted(Exception):
    pass


class Session:
    """One check of a base, step by step (docs/check_base.md)."""

    def __init__(self, listener: BaseListener, conventions: Conventions, mode: str,
                 window: float, timeout: float, stdin: TextIO, stdout: TextIO) -> None:
        self.listener = listener
        self.c = conventions
        self.mode = mode
        self.window = window
        self.timeout = timeout
        self.stdin = stdin
        self.stdout = stdout
        self.checks: list[Check] = []
        self.upright_pitch: float | None = None

    def say(self, text: str) -> None:
        print(text, file=self.stdout, flush=True)

    def confirm(self, step: str, phase: str, prompt: str) -> bool:
        """Wait for the user; False: skip the step."""
        if self.mode == 'script':
            self.say(f'CHECK_BASE WAIT {step} {phase}')
        else:
            self.say(f'  -> {prompt} [Enter; s = skip, q = quit]')
        line = self.stdin.readline()
        if not line:
            raise Aborted('end of input')
        answer = line.strip().lower()
        if answer == 'q':
            raise Aborted('quit')
        return answer != 's'

    def wait_for(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            time.sleep(0.05)
        return False

    @staticmethod
    def quantity(reading: Reading, name: str) -> float | None:
        if name == 'pitch':
            return reading.pitch
        if name == 'yaw':
            return reading.yaw
        if name == 'left':
            return reading.left
        return reading.right

    def upright_and_still(self) -> bool:
        """--auto: the start pose of a motion: still, and as level as in step 1."""
        if not self.listener.still(AUTO_STILL_TIME):
            return False
        level = self.upright_pitch if self.upright_pitch is not None else 0.0
        return abs(self.listener.reading(self.window).pitch - level) < STILL_CHANGE

    def auto_motion(self, quantity: str) -> tuple[Reading, Reading] | None:
        """--auto: upright and still -> before; the quantity moves; still again -> after."""
        if not self.wait_for(self.upright_and_still, self.timeout):
            return None
        before = self.listener.reading(self.window)
        start = self.quantity(before, quantity)
        if start is None:
            return before, before

        def moved() -> bool:
            now = self.quantity(self.listener.reading(0.1), quantity)
            if now is None:
                return False
            change = (math.remainder(now - start, TWO_PI) if quantity == 'yaw'
                      else now - start)
            return abs(change) >= AUTO_MOTION[quantity]
        if not self.wait_for(moved, self.timeout):
            return None
        if not self.wait_for(lambda: self.listener.still(AUTO_STILL_TIME), self.timeout):
            return None
        return before, self.listener.reading(self.window)

    def run(self) -> int:
        c = self.c
        self.say(f'check_base: {c.left_joint!r} (sign {int(c.left_sign):+d}) and '
                 f'{c.right_joint!r} (sign {int(c.right_sign):+d}) on '
                 f'{self.listener.topics[0]}, IMU on {self.listener.topics[1]} mounted '
                 f'{list(c.mounting)} rad; wheel radius {c.wheel_radius:g} m, track width '
                 f'{c.track_width:g} m')
        if not self.wait_for(self.listener.have_data, self.timeout):
            self.say(f'FAIL connect: no JointState on {self.listener.topics[0]} and Imu on '
                     f'{self.listener.topics[1]} within {self.timeout:g} s (is the base '
                     'running, on this ROS_DOMAIN_ID? remap the topics with --remap)')
            return EXIT_NO_DATA
        time.sleep(self.window)
        self.add(check_connection(self.listener.reading(self.window), c))
        for number, (step, prompt, quantity) in enumerate(STEPS, start=1):
            self.say(f'\nstep {number}/{len(STEPS)} ({step}): {prompt}')
            if quantity is None:           # a pose, not a motion
                if self.mode == 'auto':
                    if not self.wait_for(lambda: self.listener.still(AUTO_STILL_TIME),
                                         self.timeout):
                        self.add([Check(step, 'timeout', FAIL, None, None,
                                        'the readings never stood still')])
                        continue
                elif not self.confirm(step, 'done', 'when it is upright and still'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                upright = self.listener.reading(self.window)
                self.upright_pitch = upright.pitch
                self.add(check_upright(upright, c))
                continue
            if self.mode == 'auto':
                pair = self.auto_motion(quantity)
                if pair is None:
                    self.add([Check(step, 'timeout', FAIL, None, None,
                                    f'no motion seen within {self.timeout:g} s')])
                    continue
                before, after = pair
            else:
                if not self.confirm(step, 'ready', 'when ready, before the motion'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                before = self.listener.reading(self.window)
                if not self.confirm(step, 'done', 'when done, holding still'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                after = self.listener.reading(self.window)
            if step == 'tilt':
                self.add(check_tilt(before, after, c))
            elif step == 'turn':
                self.add(check_turn(before, after, c))
            else:
                self.add(check_wheel(step.split('_')[0], before, after, c))
        failed = [k for k in self.checks if k.status == FAIL]
        self.say(f'\n{"ALL OK" if not failed else f"{len(failed)} CHECK(S) FAILED"}: '
                 f'{sum(k.status == OK for k in self.checks)} OK, '
                 f'{sum(k.status == WARN for k in self.checks)} WARN, {len(failed)} FAIL, '
                 f'{sum(k.status == SKIP for k in self.checks)} SKIP')
        return EXIT_FAILED if failed else EXIT_OK

    def add(self, checks: list[Check]) -> None:
        for check in checks:
            self.checks.append(check)
            self.say(check.line())


def split_ros_arguments(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split a command line into the tool's own arguments and remappings.

    (the tool's own arguments, 'FROM:=TO' remappings) of a command line that may hold
    ``--ros-args ... [--]`` blocks, as ``ros2 run`` passes them.
    """
    own: list[str] = []
    remaps: list[str] = []
    in_ros = False
    words = iter(argv)
    for word in words:
        if word == '--ros-args':
            in_ros = True
        elif in_ros and word == '--':
            in_ros = False
        elif in_ros and word in ('-r', '--remap'):
            remaps.append(next(words, ''))
        elif not in_ros:
            own.append(word)
    return own, remaps


DESCRIPTION = """\
Check a real base's wheel signs, joint names and IMU mounting against the parameters the
controllers will use, by moving the robot by hand: the base's JointState and Imu are read
with the eso node's parameters (the same --scenario, --params-file and --remap as
scripts/run_graph --mode hardware) through five motions (upright, tilt forward, left
wheel, right wheel, turn), and each reading is reported, as numbers, against what the
parameters predict. It never commands the wheels.

Modes: interactive (default: Enter twice per step, s skips, q quits); --script (the same
from a pipe, with prompt lines CHECK_BASE WAIT <step> <ready|done> on stdout); --auto (no
input: each motion is detected). One line per check (OK, WARN, FAIL, SKIP); --json FILE
for all of it. The steps and what each check compares: docs/check_base.md."""

EPILOG = """\
Examples
  scripts/check_base --params-file my_base.yaml              # guided, by hand
  scripts/check_base --params-file my_base.yaml --remap /imu/data:=/imu/filtered
  scripts/check_base --params-file my_base.yaml --json checks.json

Exit status: 0 every check OK (warnings allowed), 1 a check failed (also: no data from the
base within the timeout), 2 bad arguments, 3 internal error, 130 interrupted."""


def build_parser() -> argparse.ArgumentParser:
    """``scripts/check_base``'s options."""
    parser = argparse.ArgumentParser(prog='scripts/check_base', description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=EPILOG)
    parser.add_argument('--scenario', help='scenario YAML whose controller_model gives '
                        'wheel_radius and track_width (default: paper Section V)')
    parser.add_argument('--params-file', action='append', default=[], dest='params_files',
                        metavar='FILE', help="the base's params file(s), as for run_graph "
                        '--mode hardware (repeatable; later wins)')
    parser.add_argument('--remap', action='append', default=[], dest='remaps',
                        metavar='FROM:=TO', help='topic remapping, as for run_graph')
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument('--script', action='store_true',
                      help='machine-readable prompts; confirmations are lines on stdin')
    mode.add_argument('--auto', action='store_true',
                      help='no confirmations: wait for stillness and motion (timeouts)')
    parser.add_argument('--timeout', type=float, default=60.0, metavar='S',
                        help='wait for data and, with --auto, for each motion [s]')
    parser.add_argument('--window', type=float, default=0.3, metavar='S',
                        help='averaging window of a reading [s]')
    parser.add_argument('--json', metavar='FILE', help='write the checks as JSON')
    add_exit_codes(parser)
    return parser


def checked_inputs(args: argparse.Namespace):
    """Return the eso conventions, the remaps and the user's ROS network; GraphError if bad."""
    conventions = Conventions.from_parameters(eso_parameters(args.scenario,
                                                             args.params_files))
    remaps = [parse_remap(text) for text in args.remaps]
    for line in unmatched_remaps(remaps, LISTENED_TOPICS):
        print(f'check_base: warning: {line}', file=sys.stderr)
    if not (args.timeout > 0.0 and args.window > 0.0):
        raise GraphError('--timeout and --window must be > 0', EXIT_USAGE)
    # The base is on the user's domain and network: not on scripts/_env.sh's private
    # defaults for simulations (ROS's defaults where the user set nothing).
    network = use_user_ros_environment()
    return conventions, remaps, network


def run_session(conventions: Conventions, remaps: list[tuple[str, str]], mode_name: str,
                args: argparse.Namespace, stdin: TextIO,
                stdout: TextIO) -> tuple[int, Session | None]:
    """Listen to the base and run the steps; the exit status and the session (if it began)."""
    listener = session = None
    try:
        # Inside the try: an interrupt while the listener starts (its subscriptions are
        # visible before its thread runs) still closes it before the interpreter exits.
        listener = BaseListener(conventions, remaps)
        session = Session(listener, conventions, mode_name, args.window, args.timeout,
                          stdin, stdout)
        status = session.run()
    except Aborted as err:
        print(f'check_base: stopped ({err})', file=stdout, flush=True)
        status = EXIT_INTERRUPTED
    except KeyboardInterrupt:
        status = EXIT_INTERRUPTED
    finally:
        if listener is not None:
            listener.close()
    return status, session


def write_report(path: str, status: int, conventions: Conventions, domain_id: int,
                 session: Session | None) -> None:
    """``--json FILE``: the status, the conventions, the domain and every check."""
    report = {'status': status, 'conventions': dataclasses.asdict(conventions),
              'domain_id': domain_id,
              'checks': [dataclasses.asdict(k) for k in session.checks] if session
              else []}
    with open(path, 'w', encoding='utf-8') as stream:
        json.dump(report, stream, indent=2, default=str)
        stream.write('\n')


def main(argv: list[str] | None = None, stdin: TextIO | None = None,
         stdout: TextIO | None = None) -> int:
    parser = build_parser()
    # ``ros2 run wip_bringup check_base [options] --ros-args -r a:=b`` passes ROS arguments
    # after the tool's own: remappings among them are honoured like --remap, the rest
    # (log levels, parameters) do not concern a listener and are ignored.
    own, ros_remaps = split_ros_arguments(sys.argv[1:] if argv is None else list(argv))
    args = parser.parse_args(own)
    args.remaps = [*args.remaps, *ros_remaps]
    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout
    try:
        conventions, remaps, network = checked_inputs(args)
    except GraphError as err:
        print(f'check_base: error: {err}', file=sys.stderr)
        return err.exit_code
    mode_name = 'auto' if args.auto else 'script' if args.script else 'interactive'
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C / SIGINT stops the check (exit 130) however the process was started: a
        # program started in the background by a non-interactive shell inherits SIGINT
        # ignored, and Python then never raises KeyboardInterrupt (the check waited for
        # data forever). rclpy's nodes install their own handler for the same reason.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # Once Ctrl-C is handled: whoever reads this line may interrupt the check.
    print(f'check_base: ROS network: {network.describe()}', file=sys.stderr, flush=True)
    status, session = run_session(conventions, remaps, mode_name, args, stdin, stdout)
    if args.json:
        write_report(args.json, status, conventions, network.domain_id, session)
    return status


if __name__ == '__main__':
    from wip_runtime.cli import exit_with
    exit_with(main, 'check_base')
