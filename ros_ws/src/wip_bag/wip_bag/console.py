"""Console scripts of wip_bag's tools.

What ``ros2 run wip_bag <tool>`` starts: each tool's ``main`` through the exit-code table and
last-resort error handler of wip_runtime.cli, as ``python -m <module>`` (the scripts/ front
doors) runs it.
"""

from wip_runtime.cli import console_script

bag_info = console_script('wip_bag.bag_info', 'bag_info')
bag_repair = console_script('wip_bag.bag_repair', 'bag_repair')
