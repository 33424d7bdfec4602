"""Console scripts of wip_tools.

What ``ros2 run wip_tools <tool>`` starts: each tool's ``main`` through the exit-code table and
last-resort error handler of wip_runtime.cli, as ``python -m <module>`` (the scripts/ front
doors) runs it.
"""

from wip_runtime.cli import console_script

simulate = console_script('wip_tools.simulate', 'simulate')
report = console_script('wip_tools.report', 'report')
rerun = console_script('wip_tools.rerun', 'rerun')
bench = console_script('wip_tools.bench', 'bench')
campaign = console_script('wip_tools.campaign', 'campaign')
soak = console_script('wip_tools.soak', 'soak')
parameters = console_script('wip_tools.parameters', 'parameters')
identify = console_script('wip_tools.identify', 'identify')
results_table = console_script('wip_tools.results_table', 'results_table')
