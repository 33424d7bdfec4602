"""Install the wip_control ament_python package.

Console scripts go to ``lib/wip_control`` (see setup.cfg), where ``ros2 run`` looks for them.
Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_control'

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
    description='ESO, trajectory generator, ARC, MPC and safety mixer of a wheeled inverted '
                'pendulum, as a pure-Python core and rclpy nodes.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'reference = wip_control.nodes.reference_node:main',
            'eso = wip_control.nodes.eso_node:main',
            'trajectory_generator = wip_control.nodes.trajectory_generator_node:main',
            'arc = wip_control.nodes.arc_node:main',
            'mpc = wip_control.nodes.mpc_node:main',
            'torque_mixer = wip_control.nodes.torque_mixer_node:main',
            'controllers = wip_control.nodes.controllers:main',
        ],
    },
)
