from setuptools import find_packages, setup

package_name = 'pisc_driver'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_driver']),
        ('share/pisc_driver', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC serial driver for the PIC16F877A rig: frame codec, serial link, driver node.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'driver_node = pisc_driver.driver_node:main',
        ],
    },
)
