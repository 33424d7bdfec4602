"""Install the wip_bringup ament_python package.

Console scripts go to ``lib/wip_bringup`` (see setup.cfg), where ``ros2 run`` looks for them.
Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_bringup'

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
    description=('Bring-up: run_graph (simulation or hardware mode), parameter files, estop, '
                 'check_base.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'run_graph = wip_bringup.console:run_graph',
            'check_base = wip_bringup.console:check_base',
            'estop = wip_bringup.console:estop',
        ],
    },
)
