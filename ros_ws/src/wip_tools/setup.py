"""Install the wip_tools ament_python package.

Console scripts go to ``lib/wip_tools`` (see setup.cfg), where ``ros2 run`` looks for them.
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
    description='Offline tools: simulate, report, rerun, bench, campaign.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'simulate = wip_tools.simulate:main',
            'report = wip_tools.report:main',
            'rerun = wip_tools.rerun:main',
            'bench = wip_tools.bench:main',
            'campaign = wip_tools.campaign:main',
        ],
    },
)
