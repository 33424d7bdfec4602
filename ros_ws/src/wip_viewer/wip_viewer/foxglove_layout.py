"""Foxglove layouts of wip-ros, built with foxglove-sdk's ``foxglove.layouts`` types.

``foxglove/wip_bag.json`` opens a recorded bag as it is (every topic it names is in a bag
of ``scripts/run_graph --record``); ``foxglove/wip_live.json`` is the same view plus
e-stop buttons (Service Call panels on the bridge's ``/wip/estop/*`` services) for
``scripts/run_graph --foxglove``. In Foxglove: Layouts, Import from file.

Regenerate the files after a change here (a test checks that they match)::

    python -m wip_viewer.foxglove_layout foxglove/

Panels: a 3-D view in ``map`` (the robot model from ``/robot_description`` and /tf, or the
boxes of the vehicle tilted by θ, hidden by default; the MPC's prediction, the reference,
travelled and estimated paths, both Odometry arrows); plots of θ (true, estimated, the
limit in the label and the axis range), wheel torques, speed against its limit, yaw rate;
the /diagnostics summary.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

from wip_runtime.cli import add_exit_codes

#: Written by :func:`main`: file name -> whether it carries the live-only e-stop panels.
LAYOUT_FILES = {'wip_bag.json': False, 'wip_live.json': True}


@dataclasses.dataclass(frozen=True)
class PlotLimits:
    """The limits the plots show in their labels and axis ranges.

    The controllers' defaults (the paper's Section V), written here because the viewer
    imports nothing of the controllers; ``tests/test_packages.py`` compares them.
    """

    max_tilt: float = 0.1   # [rad] mpc.max_tilt
    max_speed: float = 1.5   # [m/s] trajectory_generator.max_speed
    max_yaw_rate: float = 0.3   # [rad/s] trajectory_generator.max_yaw_rate
    max_wheel_torque: float = 15.0   # [N m] mixer.max_wheel_torque


def _series(value: str, label: str, color: str | None = None, dashed: bool = False):
    import foxglove.layouts as fl
    return fl.PlotSeries(value=value, label=label, color=color, enabled=True,
                         timestamp_method='headerStamp',
                         line_style='dashed' if dashed else None)


def build_layout(limits: PlotLimits | None = None, live: bool = False):
    """Return the layout; ``limits`` in the plots' labels and axes (default: the paper's)."""
    import foxglove.layouts as fl
    limits = limits or PlotLimits()
    diagnostics = fl.DiagnosticsSummaryPanel(
        title='Diagnostics', config=fl.DiagnosticsSummaryConfig(topic_to_render='/diagnostics'))
    left = [fl.SplitItem(proportion=3, content=_three_d_panel(fl)),
            fl.SplitItem(proportion=1, content=diagnostics)]
    if live:
        left.append(fl.SplitItem(proportion=0.5, content=_estop_buttons(fl)))
    return fl.Layout(content=fl.SplitContainer(direction='row', items=[
        fl.SplitItem(proportion=3, content=fl.SplitContainer(direction='column', items=left)),
        fl.SplitItem(proportion=2, content=_plots(fl, limits))]))


def _three_d_panel(fl):
    """Return the vehicle in the map frame: robot model, prediction, paths and poses."""
    marker = fl.BaseRendererRosMarkerTopicSettings
    return fl.ThreeDeePanel(title='Vehicle in map', config=fl.ThreeDeeConfig(
        follow_tf='map', fixed_frame='map', follow_mode='follow-none',
        topics={
            # The robot model (URDF on /robot_description, placed by /tf); the boxes of
            # /wip/markers/vehicle stay in the list, hidden: one click shows them instead.
            '/robot_description': fl.BaseRendererUrdfTopicSettings(
                visible=True, control_mode='transforms'),
            '/wip/markers/vehicle': marker(visible=False),
            '/wip/markers/prediction': marker(visible=True),
            '/wip/path/reference': fl.BaseRendererPosesTopicSettings(
                visible=True, type='line', line_width=0.03, gradient=('#1f77b4', '#1f77b4')),
            '/wip/path/travelled': fl.BaseRendererPosesTopicSettings(
                visible=True, type='line', line_width=0.02, gradient=('#000000', '#000000')),
            '/wip/path/estimated': fl.BaseRendererPosesTopicSettings(
                visible=True, type='line', line_width=0.015, gradient=('#d62728', '#d62728')),
            '/wip/odom/truth': fl.BaseRendererPoseTopicSettings(
                visible=True, type='arrow', color='#000000'),
            '/wip/odom/estimate': fl.BaseRendererPoseTopicSettings(
                visible=True, type='arrow', color='#d62728'),
        }))


def _plots(fl, limits: PlotLimits):
    """Return tilt, torques, speed and yaw rate, one above the other, with the limits."""
    max_tilt = limits.max_tilt
    max_speed = limits.max_speed
    max_yaw_rate = limits.max_yaw_rate
    max_torque = limits.max_wheel_torque
    tilt = fl.PlotPanel(title='Tilt θ [rad]', config=fl.PlotConfig(
        min_y_value=-1.25 * max_tilt, max_y_value=1.25 * max_tilt, show_legend=True,
        paths=[_series('/wip/ground_truth.theta', f'θ true (limit ±{max_tilt:g} rad)',
                       '#000000'),
               _series('/wip/state_estimate.theta', 'θ estimate', '#d62728', dashed=True)]))
    torques = fl.PlotPanel(title='Torques [N·m]', config=fl.PlotConfig(
        min_y_value=-1.1 * max_torque, max_y_value=1.1 * max_torque, show_legend=True,
        paths=[_series('/wip/wheel_torques.left', f'τ_l (limit ±{max_torque:g} N·m)'),
               _series('/wip/wheel_torques.right', 'τ_r'),
               _series('/wip/drive_torque.tau_v', 'τ_υ (MPC)', dashed=True)]))
    speed = fl.PlotPanel(title='Speed υ [m/s]', config=fl.PlotConfig(
        min_y_value=-1.2 * max_speed, max_y_value=1.2 * max_speed, show_legend=True,
        paths=[_series('/wip/ground_truth.v', f'υ true (limit ±{max_speed:g} m/s)',
                       '#000000'),
               _series('/wip/velocity_command.v_d', 'υ_d', '#2ca02c'),
               _series('/wip/reference.v', 'υ_r', '#1f77b4', dashed=True)]))
    yaw = fl.PlotPanel(title='Yaw rate ω [rad/s]', config=fl.PlotConfig(
        min_y_value=-1.2 * max_yaw_rate, max_y_value=1.2 * max_yaw_rate, show_legend=True,
        paths=[_series('/wip/ground_truth.omega', f'ω true (ω_d limit ±{max_yaw_rate:g})',
                       '#000000'),
               _series('/wip/velocity_command.omega_d', 'ω_d', '#2ca02c'),
               _series('/wip/reference.omega', 'ω_r', '#1f77b4', dashed=True)]))
    return fl.SplitContainer(direction='column', items=[
        fl.SplitItem(content=tilt), fl.SplitItem(content=torques),
        fl.SplitItem(content=speed), fl.SplitItem(content=yaw)])


def _estop_buttons(fl):
    """Return the live view's e-stop buttons: engage, release, reset (the viewer's services)."""
    buttons = [
        fl.ServiceCallPanel(title=text, config=fl.ServiceCallConfig(
            service_name=name, request_payload='{}', button_text=text,
            button_color=color, editing_mode=False, timeout_seconds=5))
        for name, text, color in (
            ('/wip/estop/engage', 'E-STOP', '#d62728'),
            ('/wip/estop/release', 'Release e-stop', '#7f7f7f'),
            ('/wip/estop/reset', 'Reset e-stop', '#2ca02c'))]
    return fl.SplitContainer(direction='row', items=[fl.SplitItem(content=b) for b in buttons])


def layout_json(live: bool) -> str:
    """Return the layout file's text (indented JSON, a final newline)."""
    import json
    return json.dumps(json.loads(build_layout(live=live).to_json()), indent=2,
                      ensure_ascii=False) + '\n'


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m wip_viewer.foxglove_layout',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('out', help='directory of the layout files (foxglove/)')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, live in LAYOUT_FILES.items():
        (out / name).write_text(layout_json(live), encoding='utf-8')
        print(f'wrote {out / name}')
    return 0


if __name__ == '__main__':
    from wip_runtime.cli import exit_with
    exit_with(main, 'foxglove_layout')
