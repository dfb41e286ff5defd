from glob import glob

from setuptools import find_packages, setup

package_name = 'pisc_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_bringup']),
        ('share/pisc_bringup', ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.xml')),
        ('share/' + package_name + '/config', glob('config/*.xml')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=('PISC bring-up: the launch files and their reader, the graph runner (a live run, or a bag'
                 ' replayed through the nodes), the DDS profile, and the pisc_bag command.'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_graph = pisc_bringup.graph_cli:main',
            'pisc_bag = pisc_bringup.bag_cli:main',
        ],
    },
)
