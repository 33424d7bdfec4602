"""Console scripts of wip_viewer's tools.

What ``ros2 run wip_viewer <tool>`` starts: each tool's ``main`` through the exit-code table and
last-resort error handler of wip_runtime.cli, as ``python -m <module>`` (the scripts/ front
doors) runs it.
"""

from wip_runtime.cli import console_script

foxglove_layout = console_script('wip_viewer.foxglove_layout', 'foxglove_layout')
