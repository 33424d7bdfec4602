"""Install the wip_tools ament_python package.

Console scripts go to ``lib/wip_tools`` (see setup.cfg), where ``ros2 run`` looks for them.
Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_tools'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='wip-ros maintainers',
    maintainer_email='wip-ros@example.com',
    description='Offline tools: simulate, report, rerun, bench, campaign, soak.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'simulate = wip_tools.console:simulate',
            'report = wip_tools.console:report',
            'rerun = wip_tools.console:rerun',
            'bench = wip_tools.console:bench',
            'campaign = wip_tools.console:campaign',
            'soak = wip_tools.console:soak',
            'parameters = wip_tools.console:parameters',
            'identify = wip_tools.console:identify',
            'results_table = wip_tools.console:results_table',
        ],
    },
)
