from setuptools import find_packages, setup

package_name = 'pisc_model'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_model']),
        ('share/pisc_model', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC rig model without ROS: parameters, cart-pole dynamics with pendulum inertia,'
        ' DC motor and sensor conversions.'
    ),
    license='Apache-2.0',
)
