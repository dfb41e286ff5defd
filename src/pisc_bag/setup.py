from setuptools import find_packages, setup

package_name = 'pisc_bag'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_bag']),
        ('share/pisc_bag', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description='PISC bags: the recorder node and command, MCAP writing, indexing, repair and reading columns.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_record = pisc_bag.record_cli:main',
        ],
    },
)
