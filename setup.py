from glob import glob

from setuptools import find_packages, setup

package_name = 'anyscale_manager'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml', 'README.md']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + package_name + '/config/iros2016', glob('config/iros2016/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='anyscale_manager maintainers',
    maintainer_email='maintainers@anyscale-manager.dev',
    description='Run-time placement and migration of ROS 2 nodes across computers (scales).',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'decider = anyscale_manager.nodes.decider:main',
            'agent = anyscale_manager.nodes.agent:main',
            'master = anyscale_manager.nodes.master:main',
            'workload = anyscale_manager.nodes.workload:main',
            'anyscale-manager = anyscale_manager.cli:main',
        ],
    },
)
