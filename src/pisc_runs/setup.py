from setuptools import find_packages, setup

package_name = 'pisc_runs'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_runs']),
        ('share/pisc_runs', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description="PISC runs: a run's verdict and summary, analysis and plots, the rig drawn (markers, animation, Foxglove live view), playing a bag and replaying it through the controllers' cores.",
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'markers_node = pisc_runs.markers_node:main',
            'pisc_foxglove = pisc_runs.foxglove_node:main',
        ],
    },
)
