"""Install collision_node as an ament_python package."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'collision_node'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/scenes', glob('scenes/*.yaml')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='collision_node team',
    maintainer_email='team@collision-node.invalid',
    description='Impulse collisions between spherical particles, with a ROS 2 node.',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'collision_node = collision_node.ros.node:main',
            'viewer = collision_node.ros.viewer:main',
            'simulate = collision_node.simulate:main',
        ],
    },
)
