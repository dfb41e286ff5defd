from glob import glob

from setuptools import find_packages, setup

package_name = 'pisc_sim'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_sim']),
        ('share/pisc_sim', ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/scenes', glob('scenes/*.yaml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC rig simulated without ROS: configurations and their parameter files, scenes,'
        ' and the closed loop of the plant and the controllers, one rig or a batch.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_scene = pisc_sim.scene_cli:main',
        ],
    },
)
