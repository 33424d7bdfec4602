"""Install the wip_description ament_python package.

Self-contained on purpose, like every package's setup.py: colcon builds each package on
its own, so there is no shared helper to import and the files are alike.
"""

from setuptools import find_packages, setup

package_name = 'wip_description'

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
    description=("The robot's description: physical parameters, sensors, the base's wiring "
                 'and the URDF built from them.'),
    license='Apache-2.0',
)
