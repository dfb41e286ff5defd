from setuptools import find_packages, setup

package_name = 'pisc_control'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_control']),
        ('share/pisc_control', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC estimator, supervisor (swing-up, catch, switching) and PI current loop:'
        ' pure cores and nodes.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'estimator_node = pisc_control.estimator_node:main',
            'supervisor_node = pisc_control.supervisor_node:main',
            'current_loop_node = pisc_control.current_loop_node:main',
        ],
    },
)
