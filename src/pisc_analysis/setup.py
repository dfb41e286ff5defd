from setuptools import find_packages, setup

package_name = 'pisc_analysis'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_analysis']),
        ('share/pisc_analysis', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        'PISC analysis of the seeds: symbolic model, linear design, stability tests,'
        ' comparisons and regions of attraction.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_analysis = pisc_analysis.report_cli:main',
        ],
    },
)
