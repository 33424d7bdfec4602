"""Console scripts of wip_bringup's tools.

What ``ros2 run wip_bringup <tool>`` starts: each tool's ``main`` through the exit-code table and
last-resort error handler of wip_runtime.cli, as ``python -m <module>`` (the scripts/ front
doors) runs it.
"""

from wip_runtime.cli import console_script

run_graph = console_script('wip_bringup.graph', 'run_graph')
check_base = console_script('wip_bringup.check_base', 'check_base')
estop = console_script('wip_bringup.estop', 'estop')
