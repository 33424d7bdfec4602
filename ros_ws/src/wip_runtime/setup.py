"""Install the wip_runtime ament_python package.

Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_runtime'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={package_name: ['*.xml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='wip-ros maintainers',
    maintainer_email='wip-ros@example.com',
    description=('What every node and tool of wip-ros runs on: the exit-code table and CLI '
                 'plumbing, declarative parameters, diagnostics, executors, clocks, QoS, '
                 'composition and intra-process delivery, the Fast DDS profile.'),
    license='Apache-2.0',
)
