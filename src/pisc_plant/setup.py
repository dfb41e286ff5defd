from setuptools import find_packages, setup

package_name = 'pisc_plant'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_plant']),
        ('share/pisc_plant', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC cart-pole and DC-motor simulator: pure dynamics, sensors and integrators,'
        ' and the plant node.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'plant_node = pisc_plant.plant_node:main',
            'pisc_virtual_rig = pisc_plant.virtual_rig_cli:main',
        ],
    },
)
