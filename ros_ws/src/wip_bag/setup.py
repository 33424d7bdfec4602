"""Install the wip_bag ament_python package.

Console scripts go to ``lib/wip_bag`` (see setup.cfg), where ``ros2 run`` looks for them.
Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_bag'

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
    description='rosbag2-compatible MCAP bag tools: recorder, replayer, info, repair.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'recorder = wip_bag.recorder_node:main',
            'replay = wip_bag.replayer_node:main',
            'bag_info = wip_bag.console:bag_info',
            'bag_repair = wip_bag.console:bag_repair',
        ],
    },
)
